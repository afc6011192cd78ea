"""Seen keypoints the fitted body hides (``fitting/visibility.py``), and how the fit chooses between the
poses it reached from rest and from limbs swung forward (``fit.choose_start``, ``fit.limb_starts``)."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

from delta.cameras.models import OrthographicCamera, PinholeCamera
from delta.fitting.fit import KeypointModel, choose_start, limb_starts
from delta.fitting.visibility import JOINT_DEPTH, camera_rays, hidden_seen

D = torch.float64
#: a 0.4 m cube (the torso) at the origin; the body faces +z, toward both cameras
BOX = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
VERTS, FACES = torch.tensor(BOX.vertices, dtype=D), torch.tensor(BOX.faces)
PINHOLE = PinholeCamera(torch.tensor([[500.0, 0, 256], [0, 500.0, 256], [0, 0, 1]], dtype=D),
                        torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=D)), torch.tensor([0.0, 0.0, 3.0], dtype=D),
                        torch.zeros(5, dtype=D), 512, 512)  # fmt: skip
ORTHO = OrthographicCamera(torch.tensor(1.0, dtype=D), torch.zeros(2, dtype=D), 512, 512)


@pytest.mark.parametrize("camera", [PINHOLE, ORTHO], ids=["pinhole", "orthographic"])
def test_a_seen_keypoint_behind_the_torso_is_hidden_and_one_in_front_or_just_inside_is_not(camera):
    points = torch.tensor([[[0.05, 0.0, 0.5],  # in front of the torso
                            [0.05, 0.0, -0.5],  # behind it: its ray meets the front face 0.7 m before it
                            [0.05, 0.0, 0.2 - JOINT_DEPTH + 0.02],  # a joint just inside the front face
                            [0.6, 0.0, -0.5]]], dtype=D)  # behind the torso's plane but beside it  # fmt: skip
    seen = torch.ones(1, 4, dtype=torch.bool)
    assert hidden_seen(VERTS[None], FACES, points, seen, camera).tolist() == [1]
    # a keypoint the detector did not see is never counted
    assert hidden_seen(VERTS[None], FACES, points, torch.tensor([[True, False, True, True]]), camera).tolist() == [0]
    # the rays end at their points: the distance along the ray is the point's
    origins, dirs, dist = camera_rays(camera, points[0])
    torch.testing.assert_close(origins + dist[:, None] * dirs, points[0])
    torch.testing.assert_close(dirs.norm(dim=-1), torch.ones(4, dtype=D))


def test_frames_are_counted_apart():
    points = torch.tensor([[[0.0, 0.0, 0.5]], [[0.0, 0.0, -0.5]]], dtype=D)
    assert hidden_seen(
        VERTS.expand(2, -1, -1), FACES, points, torch.ones(2, 1, dtype=torch.bool), PINHOLE
    ).tolist() == [0, 1]


def test_rest_is_kept_unless_it_hides_what_was_seen():
    hidden = torch.tensor([[0, 0, 0, 0], [1, 0, 2, 0], [2, 1, 1, 2], [1, 1, 1, 1]])
    cost = torch.tensor(
        [[0.9, 0.1, 0.2, 0.3], [0.1, 0.5, 0.0, 0.4], [0.0, 0.6, 0.3, 0.0], [0.5, float("nan"), 0.2, 0.3]]
    )
    # frame 0: rest hides nothing: kept though costlier; 1: the cheaper of the two that hide none;
    # 2: the cheaper of the two that hide one; 3: all hide one: the cheapest, a NaN cost never wins
    assert choose_start(hidden, cost).tolist() == [0, 3, 2, 2]


def test_the_limb_starts_swing_the_elbows_and_knees_forward(body):
    model, kp_map = body
    starts = limb_starts(model, 0.4)
    assert starts.shape == (4, model.num_joints, 3) and not starts[0].any()
    assert limb_starts(model, 0.0).shape == (1, model.num_joints, 3)
    kp = KeypointModel(model, kp_map)(torch.zeros(model.num_shape, dtype=D), starts, torch.zeros(4, 3, dtype=D))
    forward = kp[..., 2] - kp[:1, :, 2]  # +z: toward the front of the body
    elbows, wrists, knees, ankles = [3, 6], [4, 7], [9, 12], [10, 13]
    for arms, legs in ((1, 2), (2, 1)):  # which start holds the arms and which the legs depends on the rules' order
        if forward[arms, elbows].min() > 0:
            break
    assert forward[arms, elbows + wrists].min() > 0.03 and forward[arms, knees + ankles].abs().max() < 1e-9
    assert forward[legs, knees + ankles].min() > 0.03 and forward[legs, elbows + wrists].abs().max() < 1e-9
    torch.testing.assert_close(forward[3], forward[1] + forward[2])  # both: each limb as its own start
    # the swing is a rotation of 0.4 rad about the shoulder: the elbow moves by 2 sin(0.2) of its distance to it
    assert math.isclose(float(starts[arms].norm(dim=-1).max()), 0.4, rel_tol=1e-12)


def _frontal_camera():
    from delta.cameras.models import look_at

    R, t = look_at(
        torch.tensor([0.0, 0.0, 3.0], dtype=D), torch.zeros(3, dtype=D), torch.tensor([0.0, 1.0, 0.0], dtype=D)
    )
    K = torch.tensor([[700.0, 0, 256], [0, 700, 256], [0, 0, 1]], dtype=D)
    return PinholeCamera(K, R, t, torch.zeros(5, dtype=D), 512, 512)


def test_where_rest_hides_nothing_the_limb_starts_change_nothing(body):
    """The starts run side by side in one batch: a frame whose rest fit hides no seen keypoint keeps it (the
    fit with ``forward_start`` is the fit without, to the rounding of a larger batch's arithmetic)."""
    from delta.fitting.fit import fit
    from delta.fitting.settings import FitConfig
    from tests.fitting.test_fit import true_motion

    model, kp_map = body
    cam, pose = _frontal_camera(), true_motion(model, 3)
    kp3d = KeypointModel(model, kp_map)(torch.zeros(model.num_shape, dtype=D), pose, torch.zeros(3, 3, dtype=D))
    uv, _ = cam.project(kp3d)
    detected = torch.cat([uv, torch.ones_like(uv[..., :1])], -1)
    runs = [fit(model, kp_map, detected, cam, FitConfig(iterations=(40, 60, 10), forward_start=a)) for a in (0.0, 0.4)]
    torch.testing.assert_close(runs[1].pose, runs[0].pose, rtol=0, atol=1e-9)
    torch.testing.assert_close(runs[1].transl, runs[0].transl, rtol=0, atol=1e-9)
