"""Initialisation fitting: loss terms against hand-computed values; recovery from noiseless keypoints."""

import math

import pytest
import torch

from delta.cameras.models import OrthographicCamera, PinholeCamera, look_at
from delta.fitting import terms
from delta.fitting.fit import KeypointModel, fit
from delta.fitting.settings import FitConfig


def test_gmof_hand_computed():
    r = torch.tensor([[3.0, 4.0], [0.0, 0.0]])  # |r|² = 25 and 0
    torch.testing.assert_close(terms.gmof(r, 5.0), torch.tensor([25 * 25 / 50, 0.0]))


def test_keypoint_term_weights_and_normalises():
    proj = torch.zeros(1, 3, 2)
    det = torch.tensor([[[1.0, 0.0, 1.0], [0.0, 2.0, 0.5], [100.0, 0.0, 0.0]]])
    # gmof with a large sigma is |r|²: (1 * 1 + 0.5 * 4) / (1 + 0.5) = 2
    torch.testing.assert_close(terms.keypoint_term(proj, det, sigma=1e6), torch.tensor([2.0]), rtol=1e-6, atol=0)
    assert terms.keypoint_term(proj, torch.zeros(1, 3, 3)).item() == 0.0


def test_priors_and_smoothness():
    pose = torch.zeros(2, 3, 3)
    pose[1, 2, 0] = -0.5  # a knee bent the wrong way
    assert terms.bend_prior(pose, [2], 0, 1.0)[0] == 0
    torch.testing.assert_close(terms.bend_prior(pose, [2], 0, 1.0)[1], torch.tensor((math.exp(0.5) - 1) ** 2))
    pose[1, 2, 0] = 0.5  # bent the right way: free
    assert terms.bend_prior(pose, [2], 0, 1.0)[1] == 0
    x = torch.tensor([[0.0], [1.0], [3.0]])
    assert terms.smoothness(x).item() == 1.0 + 4.0 and terms.smoothness(x[:1]).item() == 0.0
    torch.testing.assert_close(terms.shape_prior(torch.tensor([3.0, 4.0])), torch.tensor(25.0))


def true_motion(model, frames, seed=0):
    gen = torch.Generator().manual_seed(seed)
    pose = torch.zeros(frames, model.num_joints, 3, dtype=torch.float64)
    for name, scale in (("upperarm01.L", 0.4), ("upperarm01.R", 0.4), ("lowerleg01.L", 0.3), ("spine03", 0.15)):
        pose[:, model.joint_names.index(name)] = scale * torch.rand(frames, 3, generator=gen, dtype=torch.float64)
    pose[:, 0, 1] = torch.linspace(-0.4, 0.4, frames, dtype=torch.float64)  # turning
    return pose


@pytest.mark.parametrize("reach", [0, 1], ids=["joint", "neighbour-starts"])
def test_recovers_pinhole_pose_and_position_from_noiseless_keypoints(body, reach):
    model, kp_map = body
    R, t = look_at(torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                   torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))  # fmt: skip
    K = torch.tensor([[700.0, 0, 256], [0, 700, 256], [0, 0, 1]], dtype=torch.float64)
    cam = PinholeCamera(K, R, t, torch.zeros(5, dtype=torch.float64), 512, 512)
    pose = true_motion(model, 4)
    transl = torch.tensor([[0.05, -0.02, 0.1]], dtype=torch.float64).expand(4, 3)
    kp3d = KeypointModel(model, kp_map)(torch.zeros(model.num_shape, dtype=torch.float64), pose, transl)
    uv, _ = cam.project(kp3d)
    detected = torch.cat([uv, torch.ones_like(uv[..., :1])], -1)
    cfg = FitConfig(iterations=(100, 200, 50), shape_weight=10.0, neighbour_reach=reach)
    res = fit(model, kp_map, detected, cam, cfg)
    assert not res.flagged.any() and res.residual_px.max() < 1.5
    fitted = KeypointModel(model, kp_map)(res.betas, res.pose, res.transl)
    hips = [8, 11]
    root_err = (fitted[:, hips].mean(1) - kp3d[:, hips].mean(1)).norm(dim=-1)
    assert root_err.max() < 0.06  # metres: the mean shape fixes the scale
    err = (fitted - kp3d).norm(dim=-1).mean()
    assert err < 0.05, err
    # the pelvis turns with the subject: the hip line points the same way (root and spine may share a
    # twist, and the hips' depth is weakly observed from one view: ~0.2 rad of play)
    hip_true, hip_fit = kp3d[:, 11] - kp3d[:, 8], fitted[:, 11] - fitted[:, 8]
    cos = (hip_true * hip_fit).sum(-1) / (hip_true.norm(dim=-1) * hip_fit.norm(dim=-1))
    assert cos.min() > math.cos(0.25)


def test_recovers_orthographic_camera(body):
    model, kp_map = body
    pose = true_motion(model, 3, seed=1)
    kp3d = KeypointModel(model, kp_map)(torch.zeros(model.num_shape, dtype=torch.float64), pose,
                                        torch.zeros(3, 3, dtype=torch.float64))  # fmt: skip
    truth = OrthographicCamera(torch.full((3,), 1.1, dtype=torch.float64),
                               torch.tensor([[0.02, -0.05]] * 3, dtype=torch.float64), 256, 256)  # fmt: skip
    uv, _ = truth.project(kp3d)
    detected = torch.cat([uv, torch.ones_like(uv[..., :1])], -1)
    template = OrthographicCamera(torch.tensor(1.0), torch.zeros(2), 256, 256)
    res = fit(model, kp_map, detected, template, FitConfig(iterations=(100, 150, 50), shape_weight=10.0))
    assert res.residual_px.max() < 1.0
    assert (res.camera.scale / 1.1 - 1).abs().max() < 0.03


def test_frames_without_keypoints_are_flagged_and_interpolated(body):
    model, kp_map = body
    R, t = look_at(torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                   torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))  # fmt: skip
    cam = PinholeCamera(torch.tensor([[700.0, 0, 256], [0, 700, 256], [0, 0, 1]], dtype=torch.float64), R, t,
                        torch.zeros(5, dtype=torch.float64), 512, 512)  # fmt: skip
    pose = true_motion(model, 3, seed=2)
    kp3d = KeypointModel(model, kp_map)(torch.zeros(model.num_shape, dtype=torch.float64), pose,
                                        torch.zeros(3, 3, dtype=torch.float64))  # fmt: skip
    uv, _ = cam.project(kp3d)
    detected = torch.cat([uv, torch.ones_like(uv[..., :1])], -1)
    detected[1, :, 2] = 0.0  # nothing detected in the middle frame
    res = fit(model, kp_map, detected, cam, FitConfig(iterations=(30, 30, 10)))
    assert res.flagged.tolist() == [False, True, False]
    assert torch.isfinite(res.pose).all() and torch.isfinite(res.transl).all()
    torch.testing.assert_close(res.transl[1], (res.transl[0] + res.transl[2]) / 2)
    assert torch.isnan(res.residual_px[1]) and torch.isfinite(res.residual_px[[0, 2]]).all()
