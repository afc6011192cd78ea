"""A detector's relative depths in the init fit (``terms.depth_term``, ``FitConfig.depth_weight``): the side a
limb swings to, which keypoints alone leave open."""

from __future__ import annotations

import math

import pytest
import torch

from delta.cameras.models import PinholeCamera, look_at
from delta.fitting import terms
from delta.body.lbs import batch_rodrigues
from delta.fitting.fit import DEPTH_BONES, KeypointModel, fit
from delta.fitting.settings import FitConfig

D = torch.float64


def test_the_depth_term_by_hand():
    # the model's bones: (0, 1) 0.2 m away from the camera, (0, 2) 0.1 m toward it, (0, 3) 0.3 m away
    depth = torch.tensor([[1.0, 1.2, 0.9, 1.3]], dtype=D)
    # the detector's: (0, 1) 0.15 m toward it (the other side), (0, 2) 0.4 m toward it (the same side, farther:
    # free), (0, 3) 0.05 m toward it (below the margin: says no side)
    detected = torch.tensor([[5.0, 4.85, 4.6, 4.95]], dtype=D)
    weight = torch.tensor([[1.0, 0.5, 0.8, 1.0]], dtype=D)
    bones = torch.tensor([[0, 1], [0, 2], [0, 3]])
    sigma = 0.1
    rho = sigma**2 * 0.04 / (sigma**2 + 0.04)  # bone (0, 1): 0.2 m on the wrong side, weight min(1, 0.5)
    expected = 0.5 * rho / sigma**2 / (0.5 + 0.8 + 1.0)
    got = terms.depth_term(depth, detected, weight, bones, sigma, margin=0.1)
    torch.testing.assert_close(got, torch.tensor([expected], dtype=D))
    # the detector's depth origin and scale drop out (above the margin)
    torch.testing.assert_close(terms.depth_term(depth, 2 * detected - 3.0, weight, bones[:2], sigma),
                               torch.tensor([0.5 * rho / sigma**2 / 1.3], dtype=D))  # fmt: skip
    # a keypoint without a depth takes its bones out
    detected[0, 2] = float("nan")
    torch.testing.assert_close(terms.depth_term(depth, detected, weight, bones, sigma),
                               torch.tensor([0.5 * rho / sigma**2 / 1.5], dtype=D))  # fmt: skip
    assert terms.depth_term(depth, torch.full_like(detected, float("nan")), weight, bones).item() == 0.0
    # bounded by 1 however far a bone is off
    far = terms.depth_term(torch.tensor([[0.0, 100.0]], dtype=D), torch.tensor([[0.0, -1.0]], dtype=D),
                           torch.ones(1, 2, dtype=D), bones[:1])  # fmt: skip
    assert 0.99 < far.item() < 1.0


def test_the_depth_terms_gradient_against_finite_differences():
    gen = torch.Generator().manual_seed(0)
    depth = torch.rand(3, 14, generator=gen, dtype=D).requires_grad_()
    detected, weight = 2 * torch.rand(3, 14, generator=gen, dtype=D), torch.rand(3, 14, generator=gen, dtype=D)
    bones = torch.tensor(DEPTH_BONES)
    assert torch.autograd.gradcheck(lambda d: terms.depth_term(d, detected, weight, bones, 0.1), (depth,))


def facing_camera() -> PinholeCamera:
    """A 512² pinhole camera 3 m in front of the body (on +z), looking at its origin."""
    R, t = look_at(
        torch.tensor([0.0, 0.0, 3.0], dtype=D), torch.zeros(3, dtype=D), torch.tensor([0.0, 1.0, 0.0], dtype=D)
    )
    return PinholeCamera(torch.tensor([[700.0, 0, 256], [0, 700, 256], [0, 0, 1]], dtype=D), R, t,
                         torch.zeros(5, dtype=D), 512, 512)  # fmt: skip


@pytest.fixture(scope="module")
def swung_arms(body):
    """Two frames facing a pinhole camera 3 m away: the left upper arm swung 0.9 rad forward, then 0.9 rad
    back. Their keypoints project alike up to the perspective; the elbows lie ~0.3 m apart in depth."""
    model, kp_map = body
    camera = facing_camera()
    pose = torch.zeros(2, model.num_joints, 3, dtype=D)
    arm = model.joint_names.index("upperarm01.L")
    pose[0, arm, 0], pose[1, arm, 0] = -0.9, 0.9
    kp3d = KeypointModel(model, kp_map)(torch.zeros(model.num_shape, dtype=D), pose, torch.zeros(2, 3, dtype=D))
    uv, z = camera.project(kp3d)
    return model, kp_map, camera, kp3d, torch.cat([uv, torch.ones_like(uv[..., :1])], -1), z


@pytest.mark.parametrize("mirrored", [False, True], ids=["true", "mirrored"])
def test_the_detected_depths_choose_the_side_the_arm_swings_to(swung_arms, mirrored):
    model, kp_map, camera, kp3d, detected, z = swung_arms
    shoulder, elbow = 5, 6  # OpenPose-18's left shoulder and elbow
    truth = z[:, elbow] - z[:, shoulder]
    assert truth[0] < -0.1 and truth[1] > 0.1  # forward: nearer the camera; back: farther
    # relative depths as a detector gives them (origin at the hips' centre), or each frame's the other way round
    rel = z[:, :18] - z[:, [8, 11]].mean(1, keepdim=True)
    if mirrored:
        rel = rel.flip(0)
    cfg = FitConfig(iterations=(60, 150, 40), shape_weight=10.0, sil_weight=0.0)
    res = fit(model, kp_map, detected, camera, cfg, depth=rel)
    fitted = camera.project(KeypointModel(model, kp_map)(res.betas, res.pose, res.transl))[1]
    got = fitted[:, elbow] - fitted[:, shoulder]
    wanted = truth.flip(0) if mirrored else truth
    assert (torch.sign(got) == torch.sign(wanted)).all(), (got, wanted)
    assert res.residual_px.max() < 6.0  # either side fits the keypoints; how far in depth is theirs to say
    assert math.isfinite(float(res.residual_px.sum()))


@pytest.mark.parametrize("mirrored", [False, True], ids=["true", "mirrored"])
def test_the_torsos_depths_choose_its_turn_when_the_face_looks_the_other_way(body, mirrored):
    """A torso turned 0.5 rad one way with the head turned 1 rad the other (its face looks 0.5 rad the
    other way): stage 1's heading follows the hips' depths, and the mirrored depths the mirrored turn, so
    the depths decide it (without them, the face picks the mirrored turn)."""
    model, kp_map = body
    camera = facing_camera()
    pose = torch.zeros(1, model.num_joints, 3, dtype=D)
    pose[0, 0, 1] = -0.5
    for name in ("neck01", "head"):
        pose[0, model.joint_names.index(name), 1] = 0.5
    kp3d = KeypointModel(model, kp_map)(torch.zeros(model.num_shape, dtype=D), pose, torch.zeros(1, 3, dtype=D))
    uv, z = camera.project(kp3d)
    detected = torch.cat([uv, torch.ones_like(uv[..., :1])], -1)
    rel = z[:, :18] - z[:, [8, 11]].mean(1, keepdim=True)
    if mirrored:  # the same depths about the torso's own vertical plane: each pair's side swapped
        rel = -rel
    cfg = FitConfig(iterations=(80, 0, 0), sil_weight=0.0)
    res = fit(model, kp_map, detected, camera, cfg, depth=rel)
    forward = batch_rodrigues(res.pose[:, 0]) @ torch.tensor([0.0, 0.0, 1.0], dtype=D)
    heading = torch.atan2(forward[0, 0], forward[0, 2]).item()
    wanted = 0.5 if mirrored else -0.5
    assert abs(heading - wanted) < 0.2, heading
