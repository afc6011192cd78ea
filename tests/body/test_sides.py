"""A limb swung to its other side along the view: same pixels, same lengths, the depths mirrored."""

import math

import pytest
import torch
from kornia.geometry.conversions import rotation_matrix_to_axis_angle

from delta.body.lbs import batch_rodrigues, rigid_transforms
from delta.body.model import load_body_model
from delta.body.sides import MIN_SWING, limbs, other_sides
from delta.body.upright import rotation_between
from delta.cameras.models import OrthographicCamera, PinholeCamera
from tests.conftest import tree_model

D = torch.float64
#: root -> shoulder -> elbow -> wrist, and root -> head: the limb is (1, 2, 3)
JOINTS = torch.tensor([[0.0, 0, 0], [0.2, 0.1, 0], [0.5, 0.1, 0], [0.8, 0.1, 0], [0, 0.6, 0]], dtype=D)
PARENTS = torch.tensor([-1, 0, 1, 2, 0])
LIMB = (1, 2, 3)


def pinhole() -> PinholeCamera:
    K = torch.tensor([[500.0, 0, 256], [0, 500.0, 256], [0, 0, 1]], dtype=D)
    R = batch_rodrigues(torch.tensor([0.1, -0.3, 0.05], dtype=D))  # looking at the limb from aside
    return PinholeCamera(K, R, torch.tensor([-0.4, 0.2, 3.0], dtype=D), torch.zeros(5, dtype=D), 512, 512)


def orthographic() -> OrthographicCamera:
    return OrthographicCamera(torch.tensor(0.8, dtype=D), torch.tensor([0.1, -0.2], dtype=D), 512, 512)


def posed(pose: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
    return rigid_transforms(batch_rodrigues(pose)[None], JOINTS[None], PARENTS)[0][0] + transl


def apply(pose: torch.Tensor, local: dict) -> torch.Tensor:
    out = pose.clone()
    for j, r in local.items():
        out[j] = rotation_matrix_to_axis_angle(r[None])[0]
    return out


def along_rays(points: torch.Tensor, camera) -> list[float]:
    """Each bone's extent along the camera's ray through its end, and that ray."""
    out = []
    for j, e in zip(LIMB[:-1], LIMB[1:]):
        _, d = camera.rays(camera.project(points[e : e + 1])[0])
        out.append(float(torch.dot(points[e] - points[j], d[0] / d[0].norm())))
    return out


@pytest.mark.parametrize("camera", [pinhole(), orthographic()], ids=["pinhole", "orthographic"])
@pytest.mark.parametrize("seed", range(8))
def test_the_other_sides_keep_the_pixels_and_lengths_and_mirror_the_depths_along_the_rays(camera, seed):
    g = torch.Generator().manual_seed(seed)
    pose = 0.8 * torch.randn(5, 3, generator=g, dtype=D)
    transl = 0.2 * torch.randn(3, generator=g, dtype=D)
    before = posed(pose, transl)
    lengths = [(before[e] - before[j]).norm() for j, e in zip(LIMB[:-1], LIMB[1:])]
    along = along_rays(before, camera)
    square = [abs(a) < math.sin(MIN_SWING) * float(n) for a, n in zip(along, lengths)]
    found = dict(other_sides(batch_rodrigues(pose), JOINTS, PARENTS, transl, camera, LIMB))
    assert (1, 0) not in found or not square[0]  # a bone square to its ray has no other side
    assert len(found) >= 1 and (0, 0) not in found
    for pattern, local in found.items():
        assert set(local) == {1, 2}  # the shoulder and the elbow turn; nothing else does
        after = posed(apply(pose, local), transl)
        for j in (0, 1, 4):  # the root, the shoulder, the head stay
            torch.testing.assert_close(after[j], before[j], rtol=0, atol=1e-12)
        # the bones' lengths and the elbow's pixel are kept
        for (j, e), n in zip(zip(LIMB[:-1], LIMB[1:]), lengths):
            assert float((after[e] - after[j]).norm()) == pytest.approx(float(n), abs=1e-10)
        torch.testing.assert_close(camera.project(after[2:3])[0], camera.project(before[2:3])[0], rtol=0, atol=1e-7)
        now = along_rays(after, camera)
        assert now[0] == pytest.approx((-1 if pattern[0] else 1) * along[0], abs=1e-9)  # mirrored or kept
        # the wrist's pixel too, unless the elbow swung beyond the forearm's reach of the wrist's ray: then
        # the forearm points at the ray's nearest point (and has no other side)
        origin, d = camera.rays(camera.project(before[3:4])[0])
        origin, d = origin[0], d[0] / d[0].norm()
        off = after[2] - origin - torch.dot(after[2] - origin, d) * d  # the elbow from the ray, square to it
        if off.norm() > lengths[1] + 1e-9:
            assert pattern[1] == 0
            wrist_off = after[3] - origin - torch.dot(after[3] - origin, d) * d
            assert float(wrist_off.norm()) == pytest.approx(float(off.norm() - lengths[1]), abs=1e-9)
        else:
            torch.testing.assert_close(camera.project(after[3:4])[0], camera.project(before[3:4])[0], rtol=0, atol=1e-7)
            assert math.copysign(1, now[1]) == (-1 if pattern[1] else 1) * math.copysign(1, along[1])


def test_a_bone_square_to_the_view_has_no_other_side():
    pose = torch.zeros(5, 3, dtype=D)  # the limb lies along +x; the orthographic camera looks along -z
    assert other_sides(batch_rodrigues(pose), JOINTS, PARENTS, torch.zeros(3, dtype=D), orthographic(), LIMB) == []
    pose[1, 1], pose[2, 1] = 0.3, -0.3  # the upper arm swung out of the image plane, the forearm still in it
    found = other_sides(batch_rodrigues(pose), JOINTS, PARENTS, torch.zeros(3, dtype=D), orthographic(), LIMB)
    assert [p for p, _ in found] == [(1, 0)]
    # the upper arm swung to -0.3 about y; the forearm keeps its own (square) direction in the world
    zero = torch.zeros(3, dtype=D)
    swung = apply(pose, found[0][1])
    torch.testing.assert_close(batch_rodrigues(swung[1]), batch_rodrigues(torch.tensor([0.0, -0.3, 0], dtype=D)))
    after, before = posed(swung, zero), posed(pose, zero)
    torch.testing.assert_close(after[3] - after[2], before[3] - before[2], rtol=0, atol=1e-12)


def test_the_other_side_of_the_other_side_is_the_pose_as_given():
    g = torch.Generator().manual_seed(3)
    pose, transl, camera = 0.8 * torch.randn(5, 3, generator=g, dtype=D), torch.zeros(3, dtype=D), pinhole()
    for pattern, local in other_sides(batch_rodrigues(pose), JOINTS, PARENTS, transl, camera, LIMB):
        swung = apply(pose, local)
        back = dict(other_sides(batch_rodrigues(swung), JOINTS, PARENTS, transl, camera, LIMB))[pattern]
        torch.testing.assert_close(posed(apply(swung, back), transl), posed(pose, transl), rtol=0, atol=1e-9)


def test_the_axis_angle_the_swings_are_written_in_inverts_rodrigues_up_to_a_half_turn():
    g = torch.Generator().manual_seed(0)
    axes = torch.randn(200, 3, generator=g, dtype=D)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    angles = torch.cat(
        [torch.rand(190, generator=g, dtype=D) * math.pi, torch.tensor([0.0, 1e-9, math.pi] * 3 + [3.1])]
    )
    for a, t in zip(axes, angles):
        R = batch_rodrigues(a * t)
        torch.testing.assert_close(batch_rodrigues(rotation_matrix_to_axis_angle(R[None])[0]), R, rtol=0, atol=1e-9)
    a, b = torch.randn(3, generator=g, dtype=D), torch.randn(3, generator=g, dtype=D)
    q = rotation_between(a, b)
    torch.testing.assert_close(q @ (a / a.norm()), b / b.norm(), rtol=0, atol=1e-12)
    torch.testing.assert_close(q @ q.T, torch.eye(3, dtype=D), rtol=0, atol=1e-12)


def test_the_limbs_are_the_arms_and_legs_of_anny(anny_files):
    body = load_body_model(anny_files["body"])
    names = [(n, tuple(body.joint_names[j] for j in chain)) for n, chain in limbs(body)]
    assert [n for n, _ in names] == ["upperarm01.L", "upperarm01.R", "upperleg01.L", "upperleg01.R"]
    assert names[0][1] == ("upperarm01.L", "lowerarm01.L", "wrist.L")
    assert limbs(tree_model()) == []
