"""The capture's up direction and floor from the fitted bodies, and the rotations that stand a body on them."""

import math

import pytest
import torch

from delta.body.upright import (
    angle_deg,
    axis_angle_matrix,
    estimate_upright,
    floor_height,
    heading,
    level_rotation,
    robust_direction,
    rotation_between,
    signed_angle,
)
from delta.cameras.models import PinholeCamera, look_at

D = torch.float64


def random_rotation(gen: torch.Generator) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=D))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def tilted(up: torch.Tensor, deg: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """(N, 3) directions at the given angles (degrees) from ``up``, at random azimuths."""
    out = []
    for a in deg:
        side = torch.linalg.cross(up, torch.randn(3, generator=gen, dtype=D))
        out.append(axis_angle_matrix(side, math.radians(float(a))) @ up)
    return torch.stack(out)


def test_the_bulk_of_the_body_axes_decides_the_up_direction_not_the_leaning_minority():
    gen = torch.Generator().manual_seed(0)
    up = torch.nn.functional.normalize(torch.tensor([0.2, -0.9, 0.35], dtype=D), dim=0)
    upright = tilted(up, 5 * torch.rand(80, generator=gen, dtype=D), gen)  # standing: within 5°
    # 20 %: bows, all the same way (towards the camera, say): they drag a plain mean
    towards = torch.linalg.cross(up, torch.tensor([1.0, 0.0, 0.0], dtype=D))
    bowing = torch.stack([axis_angle_matrix(towards, math.radians(65.0)) @ up] * 20)
    axes = torch.cat([upright, bowing])
    assert angle_deg(robust_direction(axes), up) < 1.0
    assert angle_deg(axes.mean(0), up) > 8.0
    # equivariant: the estimate of rotated axes is the rotated estimate
    Q = random_rotation(gen)
    torch.testing.assert_close(robust_direction(axes @ Q.T), Q @ robust_direction(axes), rtol=0, atol=1e-9)


def test_the_floor_is_where_the_lowest_joint_is_in_most_frames():
    up = torch.nn.functional.normalize(torch.tensor([0.0, 0.6, 0.8], dtype=D), dim=0)
    gen = torch.Generator().manual_seed(1)
    joints = torch.randn(9, 5, 3, generator=gen, dtype=D)
    lowest = torch.tensor([0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.6, 0.9, 0.1], dtype=D)  # two frames jump
    heights = joints @ up
    joints = joints + (lowest - heights.amin(1))[:, None, None] * up  # each frame's lowest joint at `lowest`
    assert floor_height(joints, up) == pytest.approx(0.1, abs=1e-12)


def test_estimate_upright_from_root_rotations_and_joints():
    gen = torch.Generator().manual_seed(2)
    W = random_rotation(gen)  # the capture's world: canonical y-up turned by W
    yaw = torch.linspace(0, 2 * math.pi, 12, dtype=D)
    y = torch.tensor([0.0, 1.0, 0.0], dtype=D)
    roots = torch.stack([W @ axis_angle_matrix(y, float(a)) for a in yaw])  # a turn in place
    joints = torch.randn(12, 4, 3, generator=gen, dtype=D) @ W.T
    est = estimate_upright(roots, joints)
    assert angle_deg(est.up, W @ y) < 1e-6 and est.spread_deg < 1e-4 and est.frames == 12
    assert est.floor == pytest.approx(float((joints @ (W @ y)).amin(1).median()))
    about = est.describe(torch.tensor([0.0, -1.0, 0.0], dtype=D))
    assert about["tilt_from_camera_vertical_deg"] == pytest.approx(angle_deg(W @ y, -y), abs=0.01)


def test_rotations_between_directions_headings_and_signed_angles():
    gen = torch.Generator().manual_seed(3)
    for _ in range(5):
        a, b = torch.randn(3, generator=gen, dtype=D), torch.randn(3, generator=gen, dtype=D)
        R = rotation_between(a, b)
        torch.testing.assert_close(R @ (a / a.norm()), b / b.norm(), rtol=0, atol=1e-12)
        torch.testing.assert_close(R.T @ R, torch.eye(3, dtype=D), rtol=0, atol=1e-12)
        assert torch.det(R) == pytest.approx(1.0)
        # the smallest such rotation: its angle is the angle between them
        assert math.degrees(math.acos((float(torch.trace(R)) - 1) / 2)) == pytest.approx(angle_deg(a, b), abs=1e-6)
    a = torch.tensor([0.0, 0.0, 2.0], dtype=D)
    torch.testing.assert_close(rotation_between(a, -a) @ a, -a, rtol=0, atol=1e-12)  # opposite: a half turn
    torch.testing.assert_close(rotation_between(a, a), torch.eye(3, dtype=D))
    z, y = torch.tensor([0.0, 0.0, 1.0], dtype=D), torch.tensor([0.0, 1.0, 0.0], dtype=D)
    x = torch.tensor([1.0, 0.0, 0.0], dtype=D)
    assert signed_angle(z, x, y) == pytest.approx(math.pi / 2)  # z to x: a quarter turn about +y
    assert signed_angle(x, z, y) == pytest.approx(-math.pi / 2)
    assert signed_angle(y, x, y) == 0.0  # along the axis: no angle
    # heading: a body turned by 0.7 rad about y and leaning 20° forwards still faces 0.7 rad round
    R = axis_angle_matrix(y, 0.7) @ axis_angle_matrix(x, math.radians(20.0))
    torch.testing.assert_close(heading(R, y), axis_angle_matrix(y, 0.7) @ z, rtol=0, atol=1e-12)
    lying = axis_angle_matrix(x, -math.pi / 2)  # lying on its back, facing up: the head points the way
    torch.testing.assert_close(heading(lying, y), lying[:, 1], rtol=0, atol=1e-12)


@pytest.mark.parametrize("pitch,roll", [(0.0, 15.0), (25.0, -10.0), (-15.0, 30.0)])
def test_levelling_rolls_the_up_axis_onto_the_image_vertical(pitch, roll):
    """A camera pitched and rolled against the world: the level rotation about the viewing ray makes a
    segment along the world's up through the body's centre project straight up the image."""
    y = torch.tensor([0.0, 1.0, 0.0], dtype=D)
    centre = torch.tensor([0.3, 1.0, 0.1], dtype=D)
    p = math.radians(pitch)
    eye = centre + 3.0 * torch.tensor([0.0, math.sin(p), math.cos(p)], dtype=D) + torch.tensor([0.4, 0, 0], dtype=D)
    R, _ = look_at(eye, centre, y)
    R = axis_angle_matrix(torch.tensor([0.0, 0.0, 1.0], dtype=D), math.radians(roll)) @ R
    cam = PinholeCamera(torch.tensor([[500.0, 0, 256], [0, 500.0, 256], [0, 0, 1]], dtype=D), R, -R @ eye,
                        torch.zeros(5, dtype=D), 512, 512)  # fmt: skip
    ends = torch.stack([centre, centre + 0.5 * y])
    uv, _ = cam.project(ends)
    before = math.degrees(math.atan2(float(uv[1, 0] - uv[0, 0]), float(uv[0, 1] - uv[1, 1])))
    assert abs(before) > 0.5 * abs(roll)  # the rolled camera shows the body leaning
    level = level_rotation(y, centre - cam.center, -R[1])
    uv, _ = cam.project(centre + (ends - centre) @ level.T)
    assert abs(float(uv[1, 0] - uv[0, 0])) < 1e-6 and uv[1, 1] < uv[0, 1]  # straight up the image
    torch.testing.assert_close(level @ (centre - cam.center), centre - cam.center)  # a turn about the ray


def test_a_level_camera_is_taken_when_the_bodies_agree_with_it():
    """The bodies' up within LEVEL_SNAP_DEG of the camera's vertical: the camera's vertical (a level camera,
    the common case, is exact where the bodies are a few degrees off); beyond, the bodies'."""
    y = torch.tensor([0.0, 1.0, 0.0], dtype=D)
    x = torch.tensor([1.0, 0.0, 0.0], dtype=D)
    joints = torch.zeros(3, 2, 3, dtype=D)
    for lean, took in ((2.0, True), (5.0, False)):
        roots = axis_angle_matrix(x, math.radians(lean)).expand(3, 3, 3)
        est = estimate_upright(roots, joints, level=2 * y)
        assert (est.source != "bodies") == took
        assert angle_deg(est.up, y) == pytest.approx(0.0 if took else lean, abs=1e-6)
    assert estimate_upright(roots, joints).source == "bodies"


def test_extremes_stay_finite():
    """A camera looking straight down the up axis has no roll to level (identity, not NaN); one frame, a
    body upside down, opposite axes in equal numbers all give a unit direction."""
    y = torch.tensor([0.0, 1.0, 0.0], dtype=D)
    level = level_rotation(y, -y, torch.tensor([0.0, 0.0, 1.0], dtype=D))
    assert torch.isfinite(level).all()
    torch.testing.assert_close(level, torch.eye(3, dtype=D))
    flipped = axis_angle_matrix(torch.tensor([1.0, 0.0, 0.0], dtype=D), math.pi)[None]
    one = estimate_upright(flipped, torch.zeros(1, 2, 3, dtype=D))
    assert angle_deg(one.up, -y) < 1e-9 and one.frames == 1
    both = torch.stack([y, -y, y, -y])
    assert robust_direction(both).norm() == pytest.approx(1.0)
    assert torch.isfinite(rotation_between(y, -y)).all() and torch.isfinite(rotation_between(y, 1e-9 * y)).all()
