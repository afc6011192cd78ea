"""Input encodings of 3D points (N points): positional encoding and multi-resolution dense grids."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


def positional_encoding(x: torch.Tensor, num_freqs: int, include_input: bool = True) -> torch.Tensor:
    """NeRF's PE: (N, D) -> (N, D (include_input + 2 num_freqs)); frequencies 2^0 .. 2^(L-1) times π."""
    freqs = (2.0 ** torch.arange(num_freqs, dtype=x.dtype, device=x.device)) * math.pi
    xf = (x[..., None, :] * freqs[:, None]).flatten(-2)
    parts = [x] if include_input else []
    return torch.cat(parts + [torch.sin(xf), torch.cos(xf)], dim=-1)


class PositionalEncoding(nn.Module):
    """PE(L) of points normalised by a bounding box to [-1, 1]."""

    def __init__(self, num_freqs: int, bounds: torch.Tensor, in_dim: int = 3):
        super().__init__()
        self.num_freqs = num_freqs
        self.register_buffer("lo", bounds[0].float().clone())
        self.register_buffer("hi", bounds[1].float().clone())
        self.out_dim = in_dim * (1 + 2 * num_freqs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xn = 2 * (x - self.lo) / (self.hi - self.lo) - 1
        return positional_encoding(xn, self.num_freqs)

    def finest_cell(self) -> float:
        """The finest detail it encodes (world units): half the period of its highest frequency
        (2^(L-1) π on the box's longest side normalised to [-1, 1]), extent / 2^L."""
        return float((self.hi - self.lo).max()) / 2**self.num_freqs


class GridEncoding(nn.Module):
    """Multi-resolution dense feature grids over a box, trilinearly sampled (``grid_sample``).

    Level l has resolution round(base · growth^l) along the box's longest side, growth chosen so the
    last level is ``max_res``; the other sides get the same cell size (a body's box is far from a
    cube, so cubic grids would waste most cells). Features of all levels are concatenated.
    Features fade to zero within one cell outside the box and are zero beyond it.
    """

    def __init__(self, bounds: torch.Tensor, levels: int = 6, features: int = 4,
                 base_res: int = 16, max_res: int = 128, init_std: float = 1e-2):  # fmt: skip
        super().__init__()
        self.register_buffer("lo", bounds[0].float().clone())
        self.register_buffer("hi", bounds[1].float().clone())
        growth = (max_res / base_res) ** (1 / max(levels - 1, 1))
        self.resolutions = [int(round(base_res * growth**i)) for i in range(levels)]
        extent = (bounds[1] - bounds[0]).double()
        ratio = (extent / extent.max()).tolist()
        self.shapes = [tuple(max(2, int(math.ceil(r * a))) for a in ratio) for r in self.resolutions]  # (x, y, z)
        self.grids = nn.ParameterList(
            nn.Parameter(init_std * torch.randn(1, features, nz, ny, nx)) for nx, ny, nz in self.shapes
        )
        self.out_dim = levels * features

    def finest_cell(self) -> float:
        """The finest level's node spacing (world units) along the box's longest side."""
        return float((self.hi - self.lo).max()) / (self.resolutions[-1] - 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xn = 2 * (x - self.lo) / (self.hi - self.lo) - 1
        # grid_sample wants (x, y, z) -> (W, H, D) order, which is the grids' own layout here
        g = xn.to(self.grids[0].dtype).view(1, -1, 1, 1, 3)
        feats = [
            F.grid_sample(grid, g, mode="bilinear", padding_mode="zeros", align_corners=True).view(grid.shape[1], -1)
            for grid in self.grids
        ]
        # (N, C) row-major: the first layer's weight gradient (grad_outᵀ · x) is ~3x slower on a CPU
        # when x is the transposed view of a (C, N) tensor
        return torch.cat([f.T for f in feats], dim=1).to(x.dtype)


def make_encoding(kind: str, bounds: torch.Tensor, **kw) -> nn.Module:
    """``pe`` (kw: num_freqs) or ``grid`` (kw: levels, features, base_res, max_res)."""
    if kind == "pe":
        return PositionalEncoding(kw.get("num_freqs", 10), bounds)
    if kind == "grid":
        keys = ("levels", "features", "base_res", "max_res")
        return GridEncoding(bounds, **{k: kw[k] for k in keys if k in kw})
    raise ValueError(f"unknown encoding '{kind}' (expected 'pe' or 'grid')")
