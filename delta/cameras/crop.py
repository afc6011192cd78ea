"""Camera updates for image crops and resizes (the preprocessing's square crop)."""

from __future__ import annotations

import dataclasses

import torch

from delta.cameras.models import OrthographicCamera, PinholeCamera


@dataclasses.dataclass(frozen=True)
class CropBox:
    """A square crop [u0, u0 + size) x [v0, v0 + size) of the source image, resized to ``out`` pixels."""

    u0: int
    v0: int
    size: int
    out: int

    @property
    def scale(self) -> float:
        return self.out / self.size

    def apply_to_points(self, uv: torch.Tensor) -> torch.Tensor:
        """Pixel coordinates (..., 2) in the source image -> in the cropped, resized image."""
        shift = torch.tensor([self.u0, self.v0], dtype=uv.dtype)
        return (uv - shift) * self.scale


def crop_camera(camera, box: CropBox):
    """The camera of the cropped, resized image (pixel-centre convention kept exactly)."""
    s = box.scale
    if isinstance(camera, PinholeCamera):
        K = camera.K.clone()
        K[0, 2] = (K[0, 2] - box.u0) * s
        K[1, 2] = (K[1, 2] - box.v0) * s
        K[:2, :2] = K[:2, :2] * s
        return PinholeCamera(K, camera.R, camera.t, camera.dist, box.out, box.out)
    if isinstance(camera, OrthographicCamera):
        W, H, c = camera.width, camera.height, box.size
        if W != H:
            raise ValueError("cropping a scaled-orthographic camera needs a square source image")
        scale = torch.as_tensor(camera.scale) * W / c
        tx = camera.trans[..., 0] + (W - 2 * box.u0 - c) / (c * scale)
        # the vertical axis flips (image v grows downwards): the shift enters with the opposite sign
        scale_y = torch.as_tensor(camera.scale) * H / c
        ty = camera.trans[..., 1] - (H - 2 * box.v0 - c) / (c * scale_y)
        return OrthographicCamera(scale, torch.stack([tx, ty], dim=-1), box.out, box.out)
    raise TypeError(f"unknown camera type {type(camera).__name__}")
