"""A turntable turns the body about the capture's up, estimated from the fit, and levels the view: it is the
same film whichever frame the world was written in (a video's world is its camera's frame, not the
ground's)."""

import numpy as np
import pytest
import torch
from kornia.geometry.conversions import rotation_matrix_to_axis_angle

from delta.body.lbs import batch_rodrigues
from delta.body.upright import angle_deg, axis_angle_matrix
from delta.export.video import capture_upright, turntable, turntable_rotations
from delta.models.image import render_image
from delta.training.run import load_trained

pytestmark = pytest.mark.slow
D = torch.float64


def rotate_world(model, Q: torch.Tensor) -> None:
    """Write the avatar's world in a frame turned by Q (x -> Q x): bodies and camera move together, so every
    render stays the same."""
    Q = Q.to(model.poses)
    with torch.no_grad():
        root = model.pose_body(0).rest_joints[0, 0]
        R = batch_rodrigues(model.poses[:, 0])
        model.poses[:, 0] = rotation_matrix_to_axis_angle(Q @ R)
        model.transl.copy_((root + model.transl) @ Q.T - root)
        model.cam_R.copy_(model.cam_R @ Q.T)


def test_the_turntable_is_the_same_film_in_a_tilted_world(tiny_trained):
    inputs = tiny_trained["tight"]
    model = load_trained(inputs["model"], inputs["record"], inputs["body"]).model
    assert model.pinhole and model.trajectory is None
    frames = 4
    straight = list(turntable(model, 0, frames))
    up = capture_upright(model).up
    with torch.no_grad():
        before = render_image(model, 0, soft_silhouette=False)["rgb"]
    # the world of the camera's frame, pitched 20° and rolled 15° further: a phone held high and askew
    x, z = torch.tensor([1.0, 0.0, 0.0], dtype=D), torch.tensor([0.0, 0.0, 1.0], dtype=D)
    Q = axis_angle_matrix(z, np.radians(15.0)) @ axis_angle_matrix(x, np.radians(20.0)) @ model.cam_R.detach().double()
    rotate_world(model, Q)
    with torch.no_grad():
        torch.testing.assert_close(render_image(model, 0, soft_silhouette=False)["rgb"], before, rtol=0, atol=1e-2)
    tilted_up = capture_upright(model).up
    assert angle_deg(tilted_up, Q @ up.double()) < 1e-3  # the estimate turns with the world
    tilted = list(turntable(model, 0, frames))
    for k, (a, b) in enumerate(zip(straight, tilted)):
        diff = np.abs(a.astype(int) - b.astype(int)).max(-1)
        # the same film to the rounding of a rotated frame: a ray grazing an edge may land on the other
        # side of it in one film, so a pixel or two may differ more; the rest agree to 3 levels of 255
        assert (diff > 3).sum() <= 2 and diff.mean() < 0.5, (k, diff.max(), (diff > 3).sum(), diff.mean())
    assert np.abs(straight[0].astype(int) - straight[frames // 2].astype(int)).mean() > 1.0  # it turns
    # turning about the world's y axis instead, which is no longer up, sweeps the body's axis round a cone
    y = torch.tensor([0.0, 1.0, 0.0], dtype=D)
    swept = [angle_deg(A @ tilted_up, tilted_up) for A in turntable_rotations(y, torch.eye(3, dtype=D), 8)]
    assert max(swept) > 30.0


def test_the_turntable_turns_about_what_the_capture_frames(tiny_trained):
    """A capture that frames only the head turns about the head: its centre stays put in every view (the
    whole body's centre, half a metre below, would swing it round and tilt the view down to the belly)."""
    from delta.body.parts import head_vertices
    from delta.export.video import posed_as, turntable_poses

    inputs = tiny_trained["tight"]
    model = load_trained(inputs["model"], inputs["record"], inputs["body"]).model
    up = capture_upright(model).up
    head = head_vertices(model.body).to(model.framed.device)

    def centres(framed):
        model.framed = framed
        out = []
        with torch.no_grad():
            for pose, transl in turntable_poses(model, 0, 6, up):
                with posed_as(model, 0, pose, transl):
                    v = model.pose_body(0).vertices[0].double()
                out.append((v[head].mean(0), v.mean(0)))
        return out

    def apart(a, b):  # distance across the up axis
        d = a - b
        return float((d - (d @ up.to(d)) * up.to(d)).norm())

    whole = torch.ones_like(head)
    turned = centres(head)
    assert max(apart(h, turned[0][0]) for h, _ in turned) < 1e-4  # the head stays on the axis
    assert max(apart(b, turned[0][1]) for _, b in turned) > 0.02  # the body swings round it (4.8 cm here)
    turned = centres(whole)
    assert max(apart(b, turned[0][1]) for _, b in turned) < 1e-4  # a whole body turns about its own centre
