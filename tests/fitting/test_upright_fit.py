"""A video's world is its camera's frame: the up direction estimated from the fit of a subject filmed by a
pitched and rolled camera is the world's up, where the camera's own vertical is far off."""

import math

import pytest
import torch

from delta.body.lbs import batch_rodrigues, posed_joints
from delta.body.upright import angle_deg, estimate_upright
from delta.cameras.models import PinholeCamera
from delta.fitting.fit import fit
from delta.fitting.settings import FitConfig
from delta.synthetic.generate import frame_span, make_camera
from delta.synthetic.spec import parse_subject
from tests.fitting.test_robust import keypoints

D = torch.float64


def turning_poses(model, frames: int, gen: torch.Generator) -> torch.Tensor:
    """(F, J, 3) a body turning in place with its arms and legs moving a little."""
    pose = 0.08 * torch.randn(frames, model.num_joints, 3, generator=gen, dtype=D)
    pose[:, 0] = 0.0
    pose[:, 0, 1] = torch.linspace(0, 2 * math.pi, frames + 1, dtype=D)[:-1]
    return pose


@pytest.mark.parametrize("pitch,roll", [(20.0, 15.0), (-10.0, -25.0)])
def test_the_fit_of_a_tilted_camera_stands_the_body_on_the_worlds_up(body, pitch, roll):
    model, kp_map = body
    spec = parse_subject("tilted", {"camera_pitch": pitch, "camera_roll": roll, "resolution": 256})
    cam = make_camera(spec, *frame_span(spec, model.v_template[:, 1].double().numpy()))
    gen = torch.Generator().manual_seed(0)
    F = 8
    pose = turning_poses(model, F, gen)
    transl = torch.zeros(F, 3, dtype=D)
    detected = keypoints(model, kp_map, cam, pose, transl)
    truth_up = cam.R @ torch.tensor([0.0, 1.0, 0.0], dtype=D)  # the world's up in the camera's frame
    camera_up = torch.tensor([0.0, -1.0, 0.0], dtype=D)
    assert angle_deg(truth_up, camera_up) > 0.8 * math.hypot(pitch, roll)
    # what a video gives: the camera's intrinsics, its frame as the world
    video = PinholeCamera(cam.K, torch.eye(3, dtype=D), torch.zeros(3, dtype=D), cam.dist, cam.width, cam.height)
    res = fit(model, kp_map, detected, video, FitConfig(iterations=(80, 60, 0), sil_weight=0.0))
    assert res.residual_px.median() < 2.0
    rot = batch_rodrigues(res.pose)
    est = estimate_upright(rot[:, 0], posed_joints(model.to(dtype=D), res.betas, rot, res.transl))
    assert angle_deg(est.up, truth_up) < 4.0, (angle_deg(est.up, truth_up), angle_deg(est.up, camera_up))
