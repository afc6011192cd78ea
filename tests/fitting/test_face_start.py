"""A close-up's fit starts from its face: the perspective-n-point start recovers a body's turn and place
from its face points alone, and the fit's steps shrink with the distance so a face 0.5 m from the camera
is not thrown off by them."""

import math

import numpy as np
import pytest
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle

from delta.body.face_points import FacePoints, farthest_points
from delta.body.lbs import lbs
from delta.body.model import REGION, load_body_model
from delta.cameras.models import PinholeCamera
from delta.fitting.fit import REFERENCE_DISTANCE, distance_scale
from delta.fitting.start import MIN_FACE_POINTS, face_start

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def body(anny_files):
    return load_body_model(anny_files["body"], dtype=torch.float64)


def _camera(f=540.0, size=512):
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=torch.float64)
    return PinholeCamera(K, torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                         torch.zeros(5, dtype=torch.float64), size, size)  # fmt: skip


def _axis_angle(axis, degrees):
    a = torch.tensor(axis, dtype=torch.float64)
    return a / a.norm() * math.radians(degrees)


def test_the_face_start_recovers_the_bodys_turn_and_place(body):
    regions = body.regions.numpy()
    front = np.flatnonzero((regions == REGION["face"]) & (body.v_template[:, 2].numpy() > np.percentile(
        body.v_template[regions == REGION["face"], 2].numpy(), 40)))  # fmt: skip
    points = FacePoints.at_vertices(front[farthest_points(body.v_template[front].numpy(), 150, 0)])
    camera = _camera()
    F = 4
    facing = _axis_angle([1, 0, 0], 180)  # upright, facing a camera that looks along +z with y down
    turns = [([0, 1, 0], 0), ([0, 1, 0], 25), ([1, 0, 0], 12), ([0, 0, 1], -15)]
    pose = torch.zeros(F, body.num_joints, 3, dtype=torch.float64)
    for f, (axis, deg) in enumerate(turns):
        R = axis_angle_to_rotation_matrix(_axis_angle(axis, deg)[None]) @ axis_angle_to_rotation_matrix(facing[None])
        pose[f, 0] = rotation_matrix_to_axis_angle(R)[0]
    betas = torch.zeros(body.num_shape, dtype=torch.float64)
    # each frame's face centre half a metre to a metre ahead of the camera
    where = torch.stack([torch.tensor([0.05 * f, -0.02, 0.5 + 0.15 * f], dtype=torch.float64) for f in range(F)])
    posed = lbs(body, betas[None].expand(F, -1), pose, transl=torch.zeros(F, 3, dtype=torch.float64))
    transl = where - points(posed.vertices).mean(1)
    truth = lbs(body, betas[None].expand(F, -1), pose, transl=transl)
    uv, _ = camera.project(points(truth.vertices))
    gen = torch.Generator().manual_seed(0)
    detected = torch.cat([uv + 0.5 * torch.randn(uv.shape, generator=gen, dtype=torch.float64),
                          torch.ones(*uv.shape[:2], 1, dtype=torch.float64)], -1)  # fmt: skip
    detected[2, :, 2] = 0.0  # a frame whose face was not seen takes its neighbours' values
    start = face_start(body, points, detected, camera)
    got = lbs(body, start.betas[None].expand(F, -1), start.pose, transl=start.transl)
    err = (points(got.vertices) - points(truth.vertices)).norm(dim=-1).mean(-1)
    assert (err[[0, 1, 3]] < 0.004).all(), err  # metres: the face where it was
    assert (start.pose[:, 1:] == 0).all() and (start.betas == 0).all()
    interpolated = (start.transl[1] + start.transl[3]) / 2
    torch.testing.assert_close(start.transl[2], interpolated)
    detected[..., 2] = 0.0
    detected[0, :MIN_FACE_POINTS, 2] = 1.0
    assert face_start(body, points, detected, camera) is not None
    detected[0, 0, 2] = 0.0
    assert face_start(body, points, detected, camera) is None


def test_steps_shrink_with_the_distance():
    camera = _camera()
    near = torch.tensor([[[0.0, 0.0, 0.6], [0.1, 0.0, 0.6]]], dtype=torch.float64)
    assert distance_scale(camera, near) == pytest.approx(0.6 / REFERENCE_DISTANCE)
    far = near + torch.tensor([0.0, 0.0, 5.0], dtype=torch.float64)
    assert distance_scale(camera, far) == 1.0
    assert distance_scale(camera, near * 0.0) == pytest.approx(0.02)  # on the camera: the floor, not zero
