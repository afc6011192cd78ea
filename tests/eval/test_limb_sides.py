"""The held-out refinement chooses a limb's side along the view by the frame: a thigh fitted on the wrong side
of its keypoints comes back to the side the photograph shows."""

import numpy as np
import pytest
import torch
from kornia.geometry.conversions import rotation_matrix_to_axis_angle

from delta.body.lbs import rigid_transforms, shaped_joints
from delta.body.sides import limbs, other_sides
from delta.data.frames import ByteFrames
from delta.eval.heldout import choose_sides, limb_box
from delta.models.image import render_image
from delta.training.run import load_trained

pytestmark = pytest.mark.slow


def posed_joints_of(model, frame: int) -> torch.Tensor:
    rot, transl = model.local_rotations()
    joints = shaped_joints(model.body, model.betas[None])[0]
    return rigid_transforms(rot[frame : frame + 1], joints[None], model.body.parents)[0][0] + transl[frame]


@pytest.fixture()
def lifted_knee(tiny_trained):
    """A tiny avatar whose first held-out pose lifts the left knee toward the camera, coloured by where a
    point lies on the template (front and back of a thigh differ), and that frame's photograph its render."""
    t = tiny_trained["tight"]
    tr = load_trained(t["model"], t["record"], t["body"])
    model, data = tr.model, tr.data
    v = model.body.v_template
    colour = ((v - v.min(0).values) / (v.max(0).values - v.min(0).values)).clamp(0.05, 0.95)
    model.albedo = lambda: colour  # front (z) and back of each limb in other colours
    f = int(np.flatnonzero(data.split == 2)[0])
    leg = dict(limbs(model.body))["upperleg01.L"]
    assert not model.pose_mask[list(leg)].any()  # the tiny capture's legs never move: training froze them
    model.pose_mask.fill_(1.0)  # as a capture whose legs move leaves them
    with torch.no_grad():
        model.poses[f, 0] = 0.0  # facing the camera (+z)
        model.poses[f, leg[0]] = torch.tensor([-0.7, 0.0, 0.1])  # the thigh swung forward
        model.poses[f, leg[1]] = torch.tensor([1.0, 0.0, 0.0])  # the knee bent
        img = render_image(model, f)
    for field, value in (("images", img["rgb"]), ("person", img["silhouette"])):  # the frame's photograph
        frames = getattr(data, field)
        frames.bytes[f] = torch.from_numpy(ByteFrames.quantise(value.detach().cpu().numpy()))
    return model, data, f, leg


def test_a_thigh_fitted_on_its_other_side_comes_back_to_the_photographs(lifted_knee):
    model, data, f, leg = lifted_knee
    truth = posed_joints_of(model, f).detach()
    with torch.no_grad():
        rot, transl = model.local_rotations()
        one_rot, one_transl = model.local_rotations(torch.tensor([f]))  # one frame's alone: the same values
        torch.testing.assert_close((one_rot[0], one_transl[0]), (rot[f], transl[f]), rtol=0, atol=0)
        joints = shaped_joints(model.body, model.betas[None])[0].double()
        found = dict(other_sides(rot[f].double(), joints, model.body.parents, transl[f].double(), model.camera(f), leg))
        for j, r in found[(1, 0)].items():  # the thigh swung back, the ankle on its pixel: the wrong side
            model.poses[f, j] = rotation_matrix_to_axis_angle(r[None])[0].to(model.poses.dtype)
    wrong = posed_joints_of(model, f).detach()
    assert (wrong[leg[1]] - truth[leg[1]]).norm() > 0.1  # the knee tens of centimetres off
    camera = model.camera(f)  # the knee and the ankle on their pixels: what the keypoints cannot tell apart
    torch.testing.assert_close(
        camera.project(wrong[list(leg)])[0], camera.project(truth[list(leg)])[0], atol=1e-3, rtol=0
    )
    model.pose_mask[list(leg)] = 0.0  # joints training froze are not swung
    assert not any(name.startswith("upperleg01.L") for name in choose_sides(model, data, f, seed=0))
    model.pose_mask.fill_(1.0)
    taken = choose_sides(model, data, f, seed=0)
    assert "upperleg01.L:10" in taken
    back = posed_joints_of(model, f).detach()
    torch.testing.assert_close(back[list(leg)], truth[list(leg)], rtol=0, atol=1e-4)
    # from the photograph's own pose nothing is swung
    assert not any(name.startswith("upperleg01.L") for name in choose_sides(model, data, f, seed=0))


def test_the_box_around_a_limb_holds_its_joints_with_room():
    uv = torch.tensor([[10.0, 20.0], [14.0, 40.0], [12.0, 60.0]])
    i0, i1, j0, j1 = limb_box(uv, pad=0.25, px=2.0)
    assert (i0, i1, j0, j1) == (8, 73, -2, 27)  # rows 20..60 and columns 10..14 grown by 0.25 × 40 + 2 px
