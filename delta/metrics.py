"""Image metrics of a render against its reference: PSNR, SSIM, L1, whole image or inside a mask.

Images are (H, W, 3) tensors in [0, 1] (data range 1). Conventions:

* PSNR = 10 log10(1 / MSE), MSE over every pixel and channel (inside the mask when given);
  ``inf`` for identical images, ``nan`` for an empty mask.
* SSIM follows Wang et al. 2004 as the anchors report it (scikit-image's
  ``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
  data_range=1)``): an 11×11 Gaussian window (σ 1.5), K1 = 0.01, K2 = 0.03, local
  statistics with reflected borders, averaged over channels. The whole-image score is the
  mean of the SSIM map with the 5-pixel border left out (as scikit-image does); a masked
  score is the mean of the map over the mask's pixels.
* L1 = mean absolute difference over pixels and channels (inside the mask when given).
* The outline band of a mask: the pixels within a few of its outline, on either side, where an
  error of the silhouette (a pose, a shape) shows; ``error_share`` says how much of an image's
  squared error lies there.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1, SSIM_K2 = 0.01, 0.03


def _check(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None) -> None:
    if a.shape != b.shape or a.dim() != 3 or a.shape[-1] != 3:
        raise ValueError(f"expected two (H, W, 3) images of the same shape, got {tuple(a.shape)} and {tuple(b.shape)}")
    if mask is not None and mask.shape != a.shape[:2]:
        raise ValueError(f"mask of shape {tuple(mask.shape)} for images of shape {tuple(a.shape)}")


def _masked_mean(values: torch.Tensor, mask: torch.Tensor | None) -> float:
    """Mean of (H, W, ...) values over all pixels, or over the mask's pixels (nan when it is empty)."""
    if mask is None:
        return float(values.mean())
    m = mask.bool()
    if not bool(m.any()):
        return float("nan")
    return float(values[m].mean())


def mse(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    _check(a, b, mask)
    return _masked_mean((a.double() - b.double()) ** 2, mask)


def psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """PSNR (dB) with data range 1."""
    e = mse(a, b, mask)
    if math.isnan(e):
        return e
    return float("inf") if e == 0 else -10.0 * math.log10(e)


def l1(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    _check(a, b, mask)
    return _masked_mean((a.double() - b.double()).abs(), mask)


def _gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def _symmetric_pad(x: torch.Tensor, r: int) -> torch.Tensor:
    """Pad the last two dims of (C, H, W) by r, mirroring with the edge repeated (scipy's 'reflect')."""
    x = torch.cat([x[..., :r, :].flip(-2), x, x[..., -r:, :].flip(-2)], dim=-2)
    return torch.cat([x[..., :r].flip(-1), x, x[..., -r:].flip(-1)], dim=-1)


def _blur(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of (C, H, W), borders as scipy.ndimage's default."""
    r = len(g) // 2
    c = x.shape[0]
    x = _symmetric_pad(x, r)[None]
    x = F.conv2d(x, g.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    x = F.conv2d(x, g.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)
    return x[0]


def ssim_map(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(H, W) SSIM map averaged over channels."""
    _check(a, b, None)
    if min(a.shape[:2]) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}×{SSIM_WINDOW} pixels, got {tuple(a.shape[:2])}")
    x, y = a.double().permute(2, 0, 1), b.double().permute(2, 0, 1)
    g = _gaussian_window().to(x.device)
    mx, my = _blur(x, g), _blur(y, g)
    vx = _blur(x * x, g) - mx * mx
    vy = _blur(y * y, g) - my * my
    cxy = _blur(x * y, g) - mx * my
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return s.mean(0)


def ssim(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """SSIM of the whole image (border of 5 pixels left out) or inside a mask."""
    _check(a, b, mask)
    m = ssim_map(a, b)
    if mask is not None:
        return _masked_mean(m, mask)
    r = (SSIM_WINDOW - 1) // 2
    return float(m[r:-r, r:-r].mean())


def iou(a: torch.Tensor, b: torch.Tensor) -> float:
    """IoU of two boolean masks; nan when both are empty."""
    a, b = a.bool(), b.bool()
    union = (a | b).sum()
    return float("nan") if union == 0 else float((a & b).sum() / union)


def outline_band(mask: torch.Tensor, width: int) -> torch.Tensor:
    """(H, W) bool: the pixels within ``width`` pixels (a square's reach, Chebyshev distance) of the
    mask's outline, on either side: those the mask's dilation by ``width`` holds and its erosion does not.
    An image border is not an outline (the mask is extended past it)."""
    if width < 1:
        raise ValueError(f"outline band width {width}: expected at least 1 pixel")
    m = mask.bool()[None, None].float()
    k = 2 * width + 1
    grown = F.max_pool2d(F.pad(m, (width,) * 4, mode="replicate"), k, stride=1)
    shrunk = -F.max_pool2d(F.pad(-m, (width,) * 4, mode="replicate"), k, stride=1)
    return (grown > 0.5)[0, 0] & ~(shrunk > 0.5)[0, 0]


def error_share(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    """The share of the image's squared error that lies inside ``mask`` (nan for identical images)."""
    _check(a, b, mask)
    e = ((a.double() - b.double()) ** 2).sum(-1)
    total = float(e.sum())
    return float("nan") if total == 0 else float(e[mask.bool().to(e.device)].sum()) / total
