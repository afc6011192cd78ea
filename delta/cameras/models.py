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

import torch

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
    dist: torch.Tensor
    """(5,) distortion (k1, k2, p1, p2, k3)."""
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
        xy = distort(cam[..., :2] / z_safe.unsqueeze(-1), self.dist.to(points.dtype))
        K = self.K.to(points.dtype)
        uv = torch.stack([K[0, 0] * xy[..., 0] + K[0, 1] * xy[..., 1] + K[0, 2], K[1, 1] * xy[..., 1] + K[1, 2]], -1)
        return uv, z

    def rays(self, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Unit-direction rays from the camera centre through pixel coordinates (..., N, 2)."""
        K = self.K.to(uv.dtype)
        y = (uv[..., 1] - K[1, 2]) / K[1, 1]
        x = (uv[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        xy = undistort(torch.stack([x, y], dim=-1), self.dist.to(uv.dtype))
        d_cam = torch.cat([xy, torch.ones_like(xy[..., :1])], dim=-1)
        dirs = d_cam @ self.R.to(uv.dtype)  # R^T d for row vectors
        dirs = dirs / dirs.norm(dim=-1, keepdim=True)
        return self.center.to(uv.dtype).expand_as(dirs), dirs


def look_at(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World -> camera (R, t) for an OpenCV camera at ``eye`` looking at ``target`` (y down in the image)."""
    forward = target - eye
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, up)
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    R = torch.stack([right, down, forward])
    return R, -R @ eye
