"""The smooth-in-time heading and placement correction (delta/models/trajectory.py) inside the avatar."""

import math

import pytest
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle

from delta import DeltaError
from delta.body.model import load_body_model
from delta.data.frames import load_frames, sample_rays
from delta.models.init import load_init
from delta.models.trajectory import hat_weights
from delta.training.presets import resolve
from delta.training.run import build_avatar
from delta.training.trainer import loss_terms


def test_hat_weights_by_hand():
    tau = torch.tensor([0.0, 0.125, 0.5, 0.6, 1.0, float("nan")])
    w = hat_weights(tau, 5)  # knots at 0, 0.25, 0.5, 0.75, 1
    expect = torch.tensor([[1, 0, 0, 0, 0], [0.5, 0.5, 0, 0, 0], [0, 0, 1, 0, 0], [0, 0, 0.6, 0.4, 0],
                           [0, 0, 0, 0, 1], [0, 0, 0, 0, 0]], dtype=torch.float32)  # fmt: skip
    torch.testing.assert_close(w, expect)
    with pytest.raises(ValueError, match="knots"):
        hat_weights(tau, 1)


@pytest.mark.parametrize("bad", [{"pose_knots": 1}, {"pose_knots": -2}])
def test_bad_knot_counts_name_the_key(bad):
    with pytest.raises(DeltaError, match="training.dynamics"):
        resolve("fast", {"dynamics": bad})


def _avatars(inputs, knots):
    """The same stage-1 avatar without and with a trajectory of ``knots`` knots."""
    st0 = resolve("fast", {"resolution": 32, "render": {"samples": 8}, "dynamics": {"pose_knots": 0}})
    st1 = resolve("fast", {"resolution": 32, "render": {"samples": 8}, "dynamics": {"pose_knots": knots}})
    data = load_frames(inputs["record"], st0.resolution, st0.background, st0.box_margin)
    body, init = load_body_model(inputs["body"]), load_init(inputs["init"], data)
    scope = {"capture": "full", "frozen_joints": []}
    plain = build_avatar(body, st0, init, data, 1, torch.device("cpu"), scope)
    corrected = build_avatar(body, st1, init, data, 1, torch.device("cpu"), scope)
    corrected.load_state_dict(plain.state_dict(), strict=False)
    return plain, corrected, data, st1


@pytest.mark.slow
@pytest.mark.parametrize("subject", ["tight", "loose"])
def test_a_knot_turn_is_a_turn_of_the_root_and_nan_times_are_untouched(tiny_training, subject):
    plain, model, data, _ = _avatars(tiny_training[subject], 3)
    # tiny captures: odd frames are held-out views, the novel poses come last (time nan)
    outside = torch.isnan(model.frame_time).nonzero().squeeze(1).tolist()
    assert 0 < model.frame_time[1] < 1 and outside and outside[-1] == len(data.frame_ids) - 1
    for f in range(len(data.frame_ids)):  # zero knots: nothing changes
        torch.testing.assert_close(model.pose_body(f).vertices, plain.pose_body(f).vertices, rtol=0, atol=0)
    angle, shift = 0.3, torch.tensor([0.05, 0.02, -0.03])
    with torch.no_grad():
        model.trajectory.rotation[:, 1] = angle  # every knot: a turn of 0.3 rad about the vertical
        model.trajectory.shift[:] = shift
    f = 1  # a held-out view between the training frames: both neighbouring knots' (equal) correction
    R = axis_angle_to_rotation_matrix(torch.tensor([[0.0, angle, 0.0]]))[0]
    root = rotation_matrix_to_axis_angle((R @ axis_angle_to_rotation_matrix(plain.poses[f, :1].detach()))[None])[0]
    with torch.no_grad():
        plain.poses[f, 0] = root
        if plain.pinhole:
            plain.transl[f] += shift
        else:
            plain.ortho_scale[f] *= math.exp(0.05)
            plain.ortho_trans[f] += shift[1:]
    torch.testing.assert_close(model.pose_body(f).vertices, plain.pose_body(f).vertices, rtol=0, atol=2e-6)
    cam, ref = model.camera(f), plain.camera(f)
    torch.testing.assert_close(cam.project(model.pose_body(f).vertices[0])[0],
                               ref.project(plain.pose_body(f).vertices[0])[0], rtol=0, atol=2e-4)  # fmt: skip
    for f in outside:  # outside the training sequence: no correction
        torch.testing.assert_close(model.pose_body(f).vertices, plain.pose_body(f).vertices, rtol=0, atol=0)


@pytest.mark.slow
def test_the_render_loss_reaches_only_the_knots_around_the_frame(tiny_training):
    _, model, data, st = _avatars(tiny_training["loose"], 5)  # knots at times 0, 0.25, ..., 1
    batch = sample_rays(data, 0, 256, torch.Generator().manual_seed(0))  # frame 0: time 0, knot 0 only
    terms, _ = loss_terms(model, batch, st, data.skin_color, generator=torch.Generator().manual_seed(1))
    (terms["pixel"] + terms["silhouette"]).backward()
    grad = model.trajectory.rotation.grad.abs().sum(1) + model.trajectory.shift.grad.abs().sum(1)
    assert grad[0] > 0 and (grad[1:] == 0).all()


@pytest.mark.slow
def test_the_knot_gradient_matches_finite_differences(tiny_training):
    _, model, data, _ = _avatars(tiny_training["tight"], 3)
    f, target = 1, torch.randn(model.pose_body(1).vertices.shape, generator=torch.Generator().manual_seed(0))

    def energy() -> torch.Tensor:
        return (model.pose_body(f).vertices * target).sum()

    energy().backward()
    analytic = model.trajectory.rotation.grad[1, 1].item()  # frame 1 sits on knot 1 (time 0.5)
    eps = 1e-3
    with torch.no_grad():
        model.trajectory.rotation[1, 1] += eps
        up = energy().item()
        model.trajectory.rotation[1, 1] -= 2 * eps
        down = energy().item()
    assert analytic != 0
    assert (up - down) / (2 * eps) == pytest.approx(analytic, rel=2e-2)


@pytest.mark.slow
def test_a_turntable_acts_on_the_corrected_body(tiny_training):
    from delta.export.video import baked_trajectory

    _, model, _, _ = _avatars(tiny_training["loose"], 3)
    with torch.no_grad():
        model.trajectory.rotation[:, 1] = 0.4
        model.trajectory.shift[:, 0] = 0.1
    before = model.pose_body(1).vertices.clone()
    cam_before = model.camera(1).project(before[0])[0]
    with baked_trajectory(model, 1):
        assert model.trajectory is None
        torch.testing.assert_close(model.pose_body(1).vertices, before, rtol=0, atol=2e-6)
        torch.testing.assert_close(model.camera(1).project(before[0])[0], cam_before, rtol=0, atol=1e-4)
    assert model.trajectory is not None  # restored, with the frame's own parameters
    torch.testing.assert_close(model.pose_body(1).vertices, before, rtol=0, atol=0)
