"""Input encodings of 3D points (N points): positional encoding and multi-resolution dense grids.

Both also encode a fixed set of points (a mesh's template vertices, read every training step) with
``at_fixed``, which keeps what does not change between calls: the positional encoding's features, the
grids' trilinear weights as sparse matrices (on the CPU, where ``grid_sample``'s backward pass is slow).
"""

from __future__ import annotations

import math
import warnings
import weakref

import torch
import torch.nn.functional as F
from torch import nn

from delta.devices import host_paths


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

    def at_fixed(self, x: torch.Tensor) -> torch.Tensor:
        """``forward`` of points that come back unchanged (the same tensor, not requiring grad): computed once."""
        if x.requires_grad:
            return self.forward(x)
        if getattr(self, "_fixed", None) is None or not self._fixed[0].matches(x, self.lo):
            self._fixed = (_FixedKey(x, self.lo), self.forward(x))
        return self._fixed[1]

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

    def at_fixed(self, x: torch.Tensor) -> torch.Tensor:
        """``forward`` of points that come back unchanged (the same tensor, not requiring grad). On the CPU each
        level is a sparse (N, cells) matrix of the points' eight trilinear weights, built once, and the
        features its product with the grid (the backward pass the transpose's): the same values as
        ``grid_sample``'s, a third of its time forward and backward for a body's 55k vertices."""
        if x.requires_grad or not host_paths(x.device):
            return self.forward(x)
        if getattr(self, "_fixed", None) is None or not self._fixed[0].matches(x, self.lo):
            xn = 2 * (x - self.lo) / (self.hi - self.lo) - 1
            mats = [trilinear_matrix(xn.to(self.grids[0].dtype), shape) for shape in self.shapes]
            self._fixed = (_FixedKey(x, self.lo), mats)
        feats = [_Interpolate.apply(grid.view(grid.shape[1], -1).T, W, WT)
                 for grid, (W, WT) in zip(self.grids, self._fixed[1])]  # fmt: skip
        return torch.cat(feats, dim=1).to(x.dtype)


class _FixedKey:
    """Which points a cached encoding was made for: the same tensor object, unmodified (its ``_version``), in
    the same box (a loaded state's ``lo``). A weak reference: a freed tensor never matches a new one."""

    def __init__(self, x: torch.Tensor, lo: torch.Tensor):
        self.ref, self.version, self.lo = weakref.ref(x), x._version, lo.detach().clone()

    def matches(self, x: torch.Tensor, lo: torch.Tensor) -> bool:
        return self.ref() is x and self.version == x._version and torch.equal(self.lo, lo)


def trilinear_matrix(xn: torch.Tensor, shape: tuple[int, int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """``grid_sample``'s trilinear interpolation (``align_corners=True``, zeros outside) of points ``xn``
    (P, 3) in [-1, 1] from a grid of ``shape`` (nx, ny, nz) nodes, as a sparse CSR matrix W (P, nx·ny·nz)
    with the points' eight corner weights (corners outside the grid weigh 0) and its transpose, so that
    ``W @ table`` interpolates a (nodes, C) table whose rows run x fastest, then y, then z."""
    P = xn.shape[0]
    size = torch.tensor(shape, dtype=xn.dtype, device=xn.device)
    u = (xn + 1) / 2 * (size - 1)  # (P, 3) node coordinates
    i0 = u.floor()
    frac = u - i0
    i0 = i0.long()
    steps = torch.tensor([[(corner >> a) & 1 for a in range(3)] for corner in range(8)], device=xn.device)  # (8, 3)
    node = i0[:, None] + steps  # (P, 8, 3): a cell's eight corners, distinct, in increasing column order
    weights = torch.where(steps.bool(), frac[:, None], 1 - frac[:, None]).prod(-1)
    inside = ((node >= 0) & (node < size.long())).all(-1)  # corners outside the grid are left out (weigh 0)
    cols = ((node[..., 2] * shape[1] + node[..., 1]) * shape[0] + node[..., 0])[inside]
    rows = torch.arange(P, device=xn.device)[:, None].expand(P, 8)[inside]
    values = weights[inside]
    n = math.prod(shape)
    # built as CSR directly (rows sorted, each row's columns sorted and unique), not coalesced from COO:
    # coalescing's two sorts would be most of a 55k-vertex model's setup
    crow = torch.zeros(P + 1, dtype=torch.long, device=xn.device)
    crow[1:] = inside.sum(1).cumsum(0)
    order = torch.sort(cols, stable=True).indices  # the transpose: by column, rows ascending within each
    crow_t = torch.zeros(n + 1, dtype=torch.long, device=xn.device)
    crow_t[1:] = torch.bincount(cols, minlength=n).cumsum(0)
    with warnings.catch_warnings():  # torch calls its CSR support beta, in every job's log
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
        W = torch.sparse_csr_tensor(crow, cols, values, (P, n), check_invariants=False)
        WT = torch.sparse_csr_tensor(crow_t, rows[order], values[order], (n, P), check_invariants=False)
    return W, WT


class _Interpolate(torch.autograd.Function):
    """W @ table with the gradient WT @ grad: W and WT from :func:`trilinear_matrix` (constants)."""

    @staticmethod
    def forward(ctx, table, W, WT):
        ctx.WT = WT
        return W @ table

    @staticmethod
    def backward(ctx, grad):
        return ctx.WT @ grad, None, None


def make_encoding(kind: str, bounds: torch.Tensor, **kw) -> nn.Module:
    """``pe`` (kw: num_freqs) or ``grid`` (kw: levels, features, base_res, max_res)."""
    if kind == "pe":
        return PositionalEncoding(kw.get("num_freqs", 10), bounds)
    if kind == "grid":
        keys = ("levels", "features", "base_res", "max_res")
        return GridEncoding(bounds, **{k: kw[k] for k in keys if k in kw})
    raise ValueError(f"unknown encoding '{kind}' (expected 'pe' or 'grid')")
