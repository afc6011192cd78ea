"""The fit's start from several headings (a subject facing away) and its prior on rotations no keypoint sees."""

import math

import pytest
import torch

from delta.body.lbs import batch_rodrigues
from delta.cameras.models import OrthographicCamera
from delta.fitting import terms
from delta.fitting.fit import KeypointModel, fit, unobserved_projectors
from delta.fitting.settings import FitConfig
from tests.fitting.test_robust import keypoints

D = torch.float64


def heading_error_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    rel = batch_rodrigues(a).transpose(-1, -2) @ batch_rodrigues(b)
    return torch.rad2deg(torch.arccos(((rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)))


def test_subjects_facing_away_or_turned_are_found_from_several_headings(body):
    model, kp_map = body
    yaws = torch.tensor([math.pi, 0.75 * math.pi, 1.48 * math.pi, 0.3], dtype=D)  # 1.48 pi: written past pi
    pose = torch.zeros(4, model.num_joints, 3, dtype=D)
    pose[:, 0, 1] = yaws
    cam = OrthographicCamera(torch.full((4,), 0.9, dtype=D), torch.zeros(4, 2, dtype=D), 256, 256)
    detected = keypoints(model, kp_map, cam, pose)
    template = OrthographicCamera(torch.tensor(1.0, dtype=D), torch.zeros(2, dtype=D), 256, 256)
    cfg = FitConfig(iterations=(80, 0, 0), sil_weight=0.0)
    res = fit(model, kp_map, detected, template, cfg)
    assert heading_error_deg(res.pose[:, 0], pose[:, 0]).max() < 10.0
    assert res.residual_px.max() < 1.0
    # the body-pose stage keeps the headings (the joint limits leave the root free: a limit at pi
    # on its axis-angle once turned subjects facing away round, with the spine twisted back)
    res = fit(model, kp_map, detected, template, FitConfig(iterations=(80, 60, 0), sil_weight=0.0))
    assert heading_error_deg(res.pose[:, 0], pose[:, 0]).max() < 10.0
    assert res.residual_px.max() < 1.0
    # the single camera-facing start stays in wrong minima (here 28, 86, 1 and 34 degrees off)
    one = fit(model, kp_map, detected, template, FitConfig(iterations=(80, 0, 0), sil_weight=0.0, facing_starts=1))
    assert heading_error_deg(one.pose[:, 0], pose[:, 0]).max() > 60.0


def test_unobserved_projectors_find_what_openpose_cannot_see(body):
    model, kp_map = body
    proj = unobserved_projectors(KeypointModel(model, kp_map), model.num_shape, model.num_joints)
    rank = proj.diagonal(dim1=1, dim2=2).sum(-1).round()
    names = model.joint_names
    for name in ("wrist.L", "foot.R", "wrist.R"):  # nothing beyond them: blind in all three axes
        assert rank[names.index(name)] == 3, name
    for name in ("root", "upperleg01.L", "spine03", "upperarm01.R", "head"):  # they move keypoints
        assert rank[names.index(name)] == 0, name
    assert rank[names.index("lowerleg01.L")] == 1  # a straight shin's twist about itself
    torch.testing.assert_close(proj @ proj, proj)  # projectors
    # a blind rotation moves no keypoint; the prior charges exactly its size
    kp = KeypointModel(model, kp_map)
    zero = torch.zeros(1, model.num_joints, 3, dtype=D)
    turned = zero.clone()
    shin = names.index("lowerleg01.L")
    turned[0, shin] = 0.3 * proj[shin] @ torch.tensor([0.6, 0.8, 0.0], dtype=D)
    turned[0, names.index("wrist.R")] = torch.tensor([0.2, -0.1, 0.3], dtype=D)
    betas, transl = torch.zeros(model.num_shape, dtype=D), torch.zeros(1, 3, dtype=D)
    moved = (kp(betas, turned, transl) - kp(betas, zero, transl)).norm(dim=-1).max()
    assert moved < 2e-3  # metres: second order in the angle for the shin, none at all for the wrist
    expect = turned[0, shin].square().sum() + 0.14
    torch.testing.assert_close(terms.subspace_prior(turned, proj), expect[None])


def test_root_smoothness_is_measured_on_rotations_not_vectors():
    # 3.1 and -3.1 rad about the vertical are 2 pi - 6.2 apart as rotations
    a = torch.tensor([[0.0, 3.1, 0.0], [0.0, -3.1, 0.0], [0.0, -3.1, 0.0]], dtype=D)
    gap = 2 * math.pi - 6.2
    torch.testing.assert_close(terms.rotation_smoothness(a), torch.tensor(2 * (1 - math.cos(gap)), dtype=D))
    assert terms.smoothness(a) > 38.0  # the vector difference: 6.2²
    small = torch.tensor([[0.1, 0.0, 0.0], [0.13, 0.0, 0.0]], dtype=D)  # ≈ Δθ² for small steps
    torch.testing.assert_close(terms.rotation_smoothness(small), terms.smoothness(small), rtol=1e-3, atol=0)
    assert terms.rotation_smoothness(a[:1]) == 0


def test_acceleration_is_free_for_a_steady_turn_and_prices_a_wobble():
    # a steady turn about the vertical: both the rotation and the vector versions are exactly 0
    yaw = torch.arange(8, dtype=D) * 0.3
    steady = torch.stack([torch.zeros_like(yaw), yaw, torch.zeros_like(yaw)], -1)
    assert terms.rotation_acceleration(steady).item() < 1e-24
    assert terms.acceleration(steady).item() < 1e-24
    assert terms.smoothness(steady) > 0  # what the first-order term charges for it
    # one frame off by e: Δ² is (e, -2e, e) around it, so Σ|Δ²|² = 6 e²
    e = 0.01
    wobble = steady.clone()
    wobble[4, 1] += e
    torch.testing.assert_close(terms.acceleration(wobble), torch.tensor(6 * e * e, dtype=D))
    # on rotations the same to first order: ½|R_a - R_b|² = 2(1 - cos Δ) ≈ Δ²
    torch.testing.assert_close(terms.rotation_acceleration(wobble), torch.tensor(6 * e * e, dtype=D), rtol=1e-3, atol=0)
    # a steady turn across the ±π seam of axis-angle vectors stays free on rotations
    seam = torch.stack([torch.zeros(5, dtype=D), torch.tensor([2.9, 3.1, -3.0, -2.8, -2.6], dtype=D),
                        torch.zeros(5, dtype=D)], -1)  # fmt: skip
    seam[:, 1] = torch.remainder(torch.tensor([2.9, 3.1, 3.3, 3.5, 3.7], dtype=D) + math.pi, 2 * math.pi) - math.pi
    assert terms.rotation_acceleration(seam).item() < 1e-20
    assert terms.acceleration(seam) > 10
    assert terms.acceleration(torch.tensor([1.0, 2.0, 4.0])) == 1.0  # (F,) parameters too (a camera scale)
    assert terms.acceleration(steady[:2]) == 0 and terms.rotation_acceleration(steady[:2]) == 0


def test_temporal_terms_do_not_tie_two_sequences():
    # frames 0-2 one sequence, 3-4 another (a novel-pose sequence after the training one)
    x = torch.tensor([[0.0], [1.0], [2.0], [10.0], [13.0]], dtype=D)
    links = torch.tensor([True, True, False, True])
    assert terms.smoothness(x, links).item() == 1 + 1 + 9  # the 2 -> 10 jump is not charged
    assert terms.smoothness(x).item() == 1 + 1 + 64 + 9
    assert terms.acceleration(x, links).item() == 0  # the only triple inside one sequence is steady
    assert terms.acceleration(x).item() == 49 + 25
    rot = torch.zeros(5, 3, dtype=D)
    rot[:, 1] = x[:, 0] * 0.1
    assert terms.rotation_acceleration(rot, links).item() < 1e-24 < terms.rotation_acceleration(rot).item()
    assert terms.rotation_smoothness(rot, links) < terms.rotation_smoothness(rot)


def test_static_pose_hand_computed():
    x = torch.tensor([[0.0], [2.0], [4.0]], dtype=D)
    assert terms.static_pose(x).item() == 8.0  # mean 2: 4 + 0 + 4
    assert terms.static_pose(x, torch.tensor([True, True, False])).item() == 2.0  # mean 1: 1 + 1
    assert terms.static_pose(x, torch.tensor([True, False, False])).item() == 0.0
    x.requires_grad_()
    terms.static_pose(x).backward()
    torch.testing.assert_close(x.grad, torch.tensor([[-4.0], [0.0], [4.0]], dtype=D))  # 2 (x_f - mean)


@pytest.mark.slow
def test_static_weight_holds_the_turn_and_frees_the_novel_sequence(body):
    """Noisy keypoints of a subject turning in one pose, then two frames of another pose (label 1)."""
    model, kp_map = body
    F, held = 8, torch.tensor([0] * 6 + [1] * 2)
    arm = model.joint_names.index("lowerarm01.L")
    pose = torch.zeros(F, model.num_joints, 3, dtype=D)
    pose[:, 0, 1] = torch.linspace(-1.2, 1.2, F, dtype=D)  # turning through 140 degrees
    pose[:, arm, 2] = 0.5
    pose[6:, arm, 2] = 1.4  # the novel pose bends the elbow further
    kp3d = KeypointModel(model, kp_map)(torch.zeros(model.num_shape, dtype=D), pose, torch.zeros(F, 3, dtype=D))
    cam = OrthographicCamera(torch.tensor(1.0, dtype=D), torch.zeros(2, dtype=D), 256, 256)
    uv, _ = cam.project(kp3d)
    uv = uv + 2.5 * torch.randn(uv.shape, generator=torch.Generator().manual_seed(0), dtype=D)
    detected = torch.cat([uv, torch.ones_like(uv[..., :1])], -1)
    spread, novel = {}, {}
    for w in (0.0, 30.0):
        res = fit(model, kp_map, detected, cam, FitConfig(iterations=(60, 150, 100), static_weight=w), sequence=held)
        body_pose = res.pose[:6, 1:]
        spread[w] = (body_pose - body_pose.mean(0)).norm(dim=-1).mean().item()
        novel[w] = (res.pose[6:, arm] - pose[6:, arm]).norm(dim=-1).max().item()
    assert spread[30.0] < 0.3 * spread[0.0], spread
    assert novel[30.0] < novel[0.0] + 0.1, novel  # the novel frames are not pulled to the turn's pose
