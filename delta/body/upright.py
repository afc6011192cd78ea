"""Which way is up, and where is the floor, for a body seen in a capture: estimated from the fit.

A video's world is its camera's frame, and a camera is rarely level: a phone held high looks
down, a hand-held one rolls. A turntable turned about the camera's vertical then sweeps the body
through a cone, and a motion placed by its first frame inherits that frame's lean. Gravity is
constant over a static camera's capture, and a person stands, walks and dances about it: the
body's own vertical axis (the root's rotation of the canonical up, y) over all frames, averaged
robustly so that a bow or a lean does not drag it, is the capture's up, unless it agrees with the
camera's own vertical within a few degrees: then the camera is level and its vertical is up. The floor is where the
lowest joint sits in most frames, measured along that up.

Canonical frame of every body model here: y up, the body faces +z. Shapes: F frames, J joints.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from delta.body.rotations import axis_angle_to_matrix

#: the bodies' up within this angle (degrees) of the camera's vertical: the camera is taken as level
#: (``benchmarks/upright.csv``: the estimate is 2-7 degrees off for cameras pitched and rolled by up to 30)
LEVEL_SNAP_DEG = 3.0
#: angle (degrees) beyond which a frame's body axis no longer counts towards the up direction
#: (Tukey's biweight: full weight at 0, none from here on)
OUTLIER_DEG = 30.0


@dataclasses.dataclass(frozen=True)
class Upright:
    """The capture's up direction (unit, world) and floor height (metres along ``up``)."""

    up: torch.Tensor
    """(3,) unit vector."""
    floor: float
    """u·x of the floor: the median over frames of the lowest joint's height."""
    spread_deg: float
    """Median angle between a frame's body axis and ``up``: how much the body leans about it."""
    frames: int
    """Frames the estimate came from."""
    source: str = "bodies"
    """What ``up`` is: the bodies' estimate, or the camera's vertical that it agreed with."""

    def tilt_deg(self, reference: torch.Tensor) -> float:
        """Angle in degrees between ``up`` and a reference direction (e.g. the camera's vertical)."""
        return angle_deg(self.up, reference)

    def describe(self, camera_up: torch.Tensor | None = None) -> dict:
        out = {"up": [round(float(c), 5) for c in self.up], "floor_m": round(self.floor, 4),
               "spread_deg": round(self.spread_deg, 2), "frames": self.frames, "source": self.source}  # fmt: skip
        if camera_up is not None:
            out["tilt_from_camera_vertical_deg"] = round(self.tilt_deg(camera_up), 2)
        return out


def angle_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    """Angle in degrees between two (3,) directions."""
    cos = (a / a.norm()).dot(b.to(a) / b.norm()).clamp(-1.0, 1.0)
    return math.degrees(float(torch.arccos(cos)))


def body_axes(root_rotations: torch.Tensor) -> torch.Tensor:
    """(F, 3) each frame's body vertical: the (F, 3, 3) root rotations applied to the canonical up (y)."""
    return root_rotations[..., :, 1]


def robust_direction(vectors: torch.Tensor, outlier_deg: float = OUTLIER_DEG, iterations: int = 20) -> torch.Tensor:
    """(3,) unit mean direction of (N, 3) directions with Tukey's biweight on the angle to the mean: the
    bulk of the directions decides, those more than ``outlier_deg`` away count for nothing."""
    v = vectors / vectors.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    mean = v.mean(0)
    if mean.norm() < 1e-9:  # opposite directions in equal numbers: take the first
        mean = v[0]
    mean = mean / mean.norm()
    c = math.radians(outlier_deg)
    for _ in range(iterations):
        angle = torch.arccos((v @ mean).clamp(-1.0, 1.0))
        w = (1 - (angle / c).square()).clamp_min(0).square()
        if w.sum() <= 0:
            break
        new = (w[:, None] * v).sum(0)
        new = new / new.norm()
        if (new - mean).norm() < 1e-12:
            mean = new
            break
        mean = new
    return mean


def floor_height(joints: torch.Tensor, up: torch.Tensor) -> float:
    """u·x of the floor under (F, J, 3) posed joints: the median over frames of the lowest joint, so
    that jumps and crouches in a minority of frames do not move it."""
    return float((joints @ up.to(joints)).amin(-1).median())


def estimate_upright(root_rotations: torch.Tensor, joints: torch.Tensor, level: torch.Tensor | None = None,
                     snap_deg: float = LEVEL_SNAP_DEG) -> Upright:  # fmt: skip
    """The capture's :class:`Upright` from (F, 3, 3) root rotations and (F, J, 3) posed joints.

    ``level`` (3,): the camera's own vertical. Within ``snap_deg`` of it the estimate takes it: a camera
    is level more often than not (a tripod, a phone held upright), and the fitted bodies say which way
    is up to a few degrees only (their lean, the depth a single view cannot see)."""
    axes = body_axes(root_rotations.to(torch.float64))
    up = robust_direction(axes)
    source = "bodies"
    if level is not None:
        level = level.to(up) / level.norm()
        if angle_deg(up, level) < snap_deg:
            up, source = level, f"camera (level: the bodies agree within {snap_deg:g} deg)"
    spread = torch.rad2deg(torch.arccos((axes @ up).clamp(-1.0, 1.0))).median()
    return Upright(up, floor_height(joints.to(torch.float64), up), float(spread), int(root_rotations.shape[0]), source)


def axis_angle_matrix(axis: torch.Tensor, angle: float | torch.Tensor) -> torch.Tensor:
    """(3, 3) rotation by ``angle`` radians about the (3,) ``axis`` (normalised here)."""
    k = axis / axis.norm()
    return axis_angle_to_matrix(k * torch.as_tensor(angle, dtype=k.dtype, device=k.device))


def _perpendicular(a: torch.Tensor) -> torch.Tensor:
    other = torch.zeros_like(a)
    other[int(a.abs().argmin())] = 1.0
    p = torch.linalg.cross(a, other)
    return p / p.norm()


def rotation_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(3, 3) the smallest rotation taking direction ``a`` onto direction ``b`` (a half turn about an
    axis perpendicular to both when they are opposite)."""
    a, b = a / a.norm(), b.to(a) / b.norm()
    axis = torch.linalg.cross(a, b)
    s, c = axis.norm(), a.dot(b)
    if s < 1e-12:
        if c > 0:
            return torch.eye(3, dtype=a.dtype, device=a.device)
        return axis_angle_matrix(_perpendicular(a), math.pi)
    return axis_angle_matrix(axis / s, torch.atan2(s, c))


def signed_angle(a: torch.Tensor, b: torch.Tensor, axis: torch.Tensor) -> float:
    """Angle (radians) about unit ``axis`` from ``a`` to ``b``, both projected onto the plane normal to it
    (0 when either projection vanishes)."""
    axis = axis / axis.norm()
    pa, pb = a - a.dot(axis) * axis, b.to(a) - b.to(a).dot(axis) * axis
    if pa.norm() < 1e-9 or pb.norm() < 1e-9:
        return 0.0
    return float(torch.atan2(torch.linalg.cross(pa, pb).dot(axis), pa.dot(pb)))


def heading(rotation: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """(3,) where a body with root ``rotation`` faces, in the plane normal to ``up`` (its chest's
    normal, or for a body lying along ``up``, the direction its head points)."""
    for axis in (2, 1):
        d = rotation[:, axis]
        d = d - d.dot(up) * up
        if d.norm() > 0.1:
            return d / d.norm()
    return _perpendicular(up)


def level_rotation(up: torch.Tensor, view_dir: torch.Tensor, image_up: torch.Tensor) -> torch.Tensor:
    """(3, 3) rotation about the viewing direction that makes ``up`` look vertical in the image: it takes
    ``up`` into the plane of ``view_dir`` and the camera's ``image_up`` (all world directions)."""
    r = view_dir / view_dir.norm()
    return axis_angle_matrix(r, signed_angle(up, image_up, r))
