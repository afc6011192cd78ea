"""Camera models shared by data generation, fitting and rendering.

World frame: y up, the subject faces +z (SMPL-X). Pixel (i, j) has its centre
at image coordinates (u, v) = (j + 0.5, i + 0.5); u runs right, v down.

- ``OrthographicCamera`` (DELTA/SCARF): x_ndc = s (X + t_x), y_ndc = -s (Y + t_y),
  u = (x_ndc + 1) W / 2, v = (y_ndc + 1) H / 2; rays travel along -z, depth = -Z.
- ``PinholeCamera`` (OpenCV): X_c = R X + t, (x, y) = X_c[:2] / X_c[2], distorted
  by (k1, k2, p1, p2, k3), u = f_x x' + c_x, v = f_y y' + c_y; depth = Z_c.

All functions are torch, differentiable, batched over leading dimensions.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from delta import DeltaError

MIN_DEPTH = 1e-6
"""Smallest |camera depth| a pinhole projection divides by (world units)."""


def distort(xy: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """Radial-tangential (OpenCV) distortion of normalised coordinates (..., 2), k = (k1, k2, p1, p2, k3)."""
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + k[0] * r2 + k[1] * r2 * r2 + k[4] * r2 * r2 * r2
    xd = x * radial + 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x)
    yd = y * radial + k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y
    return torch.stack([xd, yd], dim=-1)


def undistort(xy_d: torch.Tensor, k: torch.Tensor, iterations: int = 20) -> torch.Tensor:
    """Invert :func:`distort` by fixed-point iteration (as cv2.undistortPoints does)."""
    xy = xy_d.clone()
    for _ in range(iterations):
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1 + k[0] * r2 + k[1] * r2 * r2 + k[4] * r2 * r2 * r2
        dx = 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x)
        dy = k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y
        xy = torch.stack([(xy_d[..., 0] - dx) / radial, (xy_d[..., 1] - dy) / radial], dim=-1)
    return xy


@dataclasses.dataclass
class OrthographicCamera:
    """Scaled orthographic camera p = (s, t_x, t_y) of an W x H image."""

    scale: torch.Tensor
    """() or (B,) isotropic scale s."""
    trans: torch.Tensor
    """(2,) or (B, 2) translation (t_x, t_y) in world units."""
    width: int
    height: int

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., N, 3) world points -> (..., N, 2) pixel coordinates (u, v) and (..., N) depth."""
        s = torch.as_tensor(self.scale, dtype=points.dtype)[..., None]
        t = torch.as_tensor(self.trans, dtype=points.dtype)[..., None, :]
        x = s * (points[..., 0] + t[..., 0])
        y = -s * (points[..., 1] + t[..., 1])
        uv = torch.stack([(x + 1) * self.width / 2, (y + 1) * self.height / 2], dim=-1)
        return uv, -points[..., 2]

    def rays(self, uv: torch.Tensor, z_start: float = 10.0) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through pixel coordinates (..., N, 2): origins on the plane z = z_start, directions -z."""
        s = torch.as_tensor(self.scale, dtype=uv.dtype)[..., None]
        t = torch.as_tensor(self.trans, dtype=uv.dtype)[..., None, :]
        x = (2 * uv[..., 0] / self.width - 1) / s - t[..., 0]
        y = -(2 * uv[..., 1] / self.height - 1) / s - t[..., 1]
        origins = torch.stack([x, y, torch.full_like(x, z_start)], dim=-1)
        dirs = torch.zeros_like(origins)
        dirs[..., 2] = -1.0
        return origins, dirs


@dataclasses.dataclass
class PinholeCamera:
    """Pinhole camera with OpenCV intrinsics, extrinsics (world -> camera) and distortion."""

    K: torch.Tensor
    """(3, 3) intrinsics."""
    R: torch.Tensor
    """(3, 3) world -> camera rotation."""
    t: torch.Tensor
    """(3,) world -> camera translation."""
    dist: torch.Tensor | None
    """(5,) distortion (k1, k2, p1, p2, k3); None: an ideal lens, which projection and rays skip (an
    avatar's camera, whose frames were undistorted: inverting a zero distortion costs 20 iterations,
    660 tensor operations a ray batch)."""
    width: int
    height: int

    @property
    def center(self) -> torch.Tensor:
        """(3,) camera centre in world coordinates."""
        return -self.R.T @ self.t

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., N, 3) world points -> (..., N, 2) pixel coordinates and (..., N) depth Z_c."""
        cam = points @ self.R.T.to(points.dtype) + self.t.to(points.dtype)
        z = cam[..., 2]
        # a point on the camera plane (z = 0, e.g. a body translated onto the camera) has no projection;
        # |z| is floored at MIN_DEPTH (sign kept) so that it lands far off the image instead of at NaN
        z_safe = torch.where(z < 0, -1.0, 1.0).to(z.dtype) * z.abs().clamp_min(MIN_DEPTH)
        xy = cam[..., :2] / z_safe.unsqueeze(-1)
        if self.dist is not None:
            xy = distort(xy, self.dist.to(points.dtype))
        K = self.K.to(points.dtype)
        uv = torch.stack([K[0, 0] * xy[..., 0] + K[0, 1] * xy[..., 1] + K[0, 2], K[1, 1] * xy[..., 1] + K[1, 2]], -1)
        return uv, z

    def rays(self, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Unit-direction rays from the camera centre through pixel coordinates (..., N, 2)."""
        K = self.K.to(uv.dtype)
        y = (uv[..., 1] - K[1, 2]) / K[1, 1]
        x = (uv[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        xy = torch.stack([x, y], dim=-1)
        if self.dist is not None:
            xy = undistort(xy, self.dist.to(uv.dtype))
        d_cam = torch.cat([xy, torch.ones_like(xy[..., :1])], dim=-1)
        dirs = d_cam @ self.R.to(uv.dtype)  # R^T d for row vectors
        dirs = dirs / dirs.norm(dim=-1, keepdim=True)
        return self.center.to(uv.dtype).expand_as(dirs), dirs


def _values(a) -> str:
    """An array's values on one line, for an error message."""
    return str(np.asarray(a).tolist())


def check_camera(camera, where: str, frame_ids=None) -> None:
    """Raise a DeltaError naming ``where`` and the bad value when ``camera`` cannot image anything.

    Pinhole: K (3, 3) finite with focal lengths f_x, f_y > 0 and last row (0, 0, 1); distortion (5,),
    R (3, 3) a rotation and t (3,) all finite. Orthographic: every scale finite and > 0 and every
    translation finite; per-frame values name the frame (``frame_ids[row]`` when given, else the row).
    Both: an image size > 0.
    """
    if not (int(camera.width) > 0 and int(camera.height) > 0):
        raise DeltaError(f"{where}: camera image size {camera.width}x{camera.height} must be > 0")
    if isinstance(camera, OrthographicCamera):
        scale = np.asarray(torch.as_tensor(camera.scale).detach().cpu(), dtype=np.float64)
        trans = np.asarray(torch.as_tensor(camera.trans).detach().cpu(), dtype=np.float64)
        if trans.shape[-1:] != (2,):
            raise DeltaError(f"{where}: orthographic camera translation has shape {trans.shape}, expected (..., 2)")
        checks = (("scale", scale, "finite and > 0", ~(np.isfinite(scale) & (scale > 0))),
                  ("translation", trans, "finite", ~np.isfinite(trans).all(-1)))  # fmt: skip
        for name, values, must, bad in checks:
            if bad.any():
                if bad.ndim == 0:
                    raise DeltaError(f"{where}: orthographic camera {name} must be {must}, found {_values(values)}")
                rows = np.flatnonzero(bad)
                ids = rows if frame_ids is None else np.asarray(frame_ids)[rows]
                raise DeltaError(f"{where}: orthographic camera {name} must be {must}, found "
                                 f"{_values(values[rows[:5]])} at frame(s) {ids[:10].tolist()}")  # fmt: skip
        return
    if not isinstance(camera, PinholeCamera):
        raise DeltaError(f"{where}: unknown camera type {type(camera).__name__}")
    arrays = {}
    named = (("K", (3, 3)), ("R", (3, 3)), ("t", (3,)), ("distortion", (5,)))
    for name, shape in named if camera.dist is not None else named[:3]:
        a = np.asarray(torch.as_tensor(getattr(camera, "dist" if name == "distortion" else name)).detach().cpu(),
                       dtype=np.float64)  # fmt: skip
        if a.shape != shape:
            raise DeltaError(f"{where}: camera {name} has shape {a.shape}, expected {shape}")
        if not np.isfinite(a).all():
            raise DeltaError(f"{where}: camera {name} is not finite: {_values(a)}")
        arrays[name] = a
    K = arrays["K"]
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise DeltaError(f"{where}: camera K has focal lengths fx = {K[0, 0]:g}, fy = {K[1, 1]:g}; both must be > 0 "
                         f"(K = {_values(K)})")  # fmt: skip
    if not np.allclose(K[2], [0.0, 0.0, 1.0], rtol=0.0, atol=1e-6):
        raise DeltaError(f"{where}: camera K's last row is {_values(K[2])}, expected [0, 0, 1] (K = {_values(K)})")
    R = arrays["R"]
    if not (np.allclose(R @ R.T, np.eye(3), rtol=0.0, atol=1e-4) and np.linalg.det(R) > 0):
        raise DeltaError(f"{where}: camera R is not a rotation: {_values(R)}")


def metres_per_pixel(camera, points: torch.Tensor) -> torch.Tensor:
    """(N,) the width in world units of one image pixel at (N, 3) world points, along the image's rows:
    depth / f_x under a pinhole (distortion left out), 2 / (s W) under an orthographic camera."""
    if isinstance(camera, PinholeCamera):
        depth = (points @ camera.R.T.to(points.dtype) + camera.t.to(points.dtype))[..., 2]
        return depth.abs() / float(camera.K[0, 0].detach())
    scale = float(torch.as_tensor(camera.scale).detach())
    return torch.full(points.shape[:-1], 2.0 / (scale * camera.width), dtype=points.dtype)


def camera_vertical(camera) -> torch.Tensor:
    """(3,) float64 the camera's image-up direction (v decreasing) in the world: the up a level camera sees."""
    if isinstance(camera, PinholeCamera):
        return -camera.R[1].detach().to(torch.float64).cpu()
    return torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)


def look_at(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World -> camera (R, t) for an OpenCV camera at ``eye`` looking at ``target`` (y down in the image)."""
    forward = target - eye
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, up)
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    R = torch.stack([right, down, forward])
    return R, -R @ eye
