"""A coarse distance field to a point set on a voxel grid: cheap 'is this near the body?' queries.

Built once per frame from the posed vertices, on the device that holds them, with an exact Euclidean
distance transform over voxel centres (the distance between a voxel's centre and the nearest occupied
voxel's centre): SciPy's on the CPU, the same transform as tensor work elsewhere. A lookup is a tensor
index. A lookup is within √3 cells of the true distance of the query point, which is what culling
samples far from the body needs. Non-differentiable.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import torch
from scipy import ndimage

from delta.devices import host_paths


#: the largest ``render.max_dist`` (m) for which the avatar builds a per-frame distance grid (at 0.02 m
#: cells a 1 m pad is ~10^7 cells, 40 MB; the paper's "no culling" 10 m would be ~10^9)
GRID_REACH = 1.0


@dataclasses.dataclass
class DistanceGrid:
    origin: torch.Tensor
    """(3,) world position of the centre of voxel (0, 0, 0), in the points' dtype."""
    cell: float
    """Voxel side (m)."""
    distance: torch.Tensor
    """(nx, ny, nz) float32 distance from each voxel centre to the points (see the module's note)."""
    nearest: Optional[torch.Tensor] = None
    """(nx, ny, nz) int64 index of a nearest point (when built with ``nearest``)."""


def build(points: torch.Tensor, cell: float, pad: float, nearest: bool = False, method: str = "auto") -> DistanceGrid:
    """Voxelise points (N, 3) at ``cell`` with ``pad`` metres of room around them, on their device.

    ``nearest``: also keep, per voxel, the index of a point in the nearest occupied voxel — about as
    cheap, the transform finds those voxels anyway. ``method``: "scipy" (CPU), "torch" (the same
    transform as tensor work on the points' device) or "auto" (SciPy for CPU points).
    """
    points = points.detach()
    if method == "auto":
        method = "scipy" if host_paths(points.device) else "torch"
    if method not in ("scipy", "torch"):
        raise ValueError(f"unknown method {method!r}; expected 'auto', 'scipy' or 'torch'")
    # the grid's frame in float64 on the host, so both methods lay out the same voxels
    pts = points.cpu().numpy().astype(np.float64)
    lo = pts.min(0) - pad
    shape = np.ceil((pts.max(0) + pad - lo) / cell).astype(int) + 1
    ijk = np.floor((pts - lo) / cell + 0.5).astype(int)
    origin = torch.from_numpy(lo).to(points.dtype)
    if method == "torch":
        dist, who = _transform_torch(torch.from_numpy(ijk).to(points.device), tuple(shape.tolist()), nearest)
        return DistanceGrid(origin.to(points.device), float(cell), dist * cell, who)
    owner = np.full(shape, -1, dtype=np.int64)
    owner[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = np.arange(len(pts))
    if not nearest:
        dist = ndimage.distance_transform_edt(owner < 0)
        return DistanceGrid(origin, float(cell), torch.from_numpy(dist.astype(np.float32) * cell))
    dist, ind = ndimage.distance_transform_edt(owner < 0, return_indices=True)
    who = torch.from_numpy(owner[ind[0], ind[1], ind[2]])
    return DistanceGrid(origin, float(cell), torch.from_numpy(dist.astype(np.float32) * cell), who)


def _transform_torch(ijk: torch.Tensor, shape: tuple[int, int, int], nearest: bool):
    """The exact Euclidean distance transform (in cells) of the voxels ``ijk`` (N, 3) occupy, as three
    separable passes of a 1D min-plus transform, min_k (x - k)² + f(k), one axis at a time: O(cells ×
    side) tensor work. Squared distances are integers, exact in float32. With ``nearest``, the argmin of
    each pass is kept and composed back to the occupied voxel, whose point (the last index in it, as
    in the SciPy path) is named."""
    dev = ijk.device
    f = torch.full(shape, torch.inf, device=dev)
    f[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = 0.0
    args = []
    for axis in (2, 1, 0):
        f, arg = _min_plus(f.movedim(axis, -1))
        f, arg = f.movedim(-1, axis), arg.movedim(-1, axis)
        args.append(arg)
    dist = f.sqrt()
    if not nearest:
        return dist, None
    owner = torch.full(shape, -1, dtype=torch.int64, device=dev)
    flat = (ijk[:, 0] * shape[1] + ijk[:, 1]) * shape[2] + ijk[:, 2]
    owner.view(-1).scatter_reduce_(0, flat, torch.arange(len(ijk), device=dev), "amax")
    k_of, j_of, i_of = args  # source along z, then y, then x
    gi = i_of
    x, y, z = (torch.arange(n, device=dev) for n in shape)
    gj = j_of[gi, y[None, :, None], z[None, None, :]]
    gk = k_of[gi, gj, z[None, None, :]]
    who = torch.where(torch.isfinite(f), owner[gi, gj, gk], -1)
    return dist, who


def _min_plus(f: torch.Tensor, chunk: int = 1 << 25) -> tuple[torch.Tensor, torch.Tensor]:
    """g(.., x) = min_k (x - k)² + f(.., k) along the last axis, and the k attaining it."""
    n = f.shape[-1]
    line = torch.arange(n, device=f.device, dtype=f.dtype)
    sq = (line[:, None] - line[None, :]) ** 2  # (x, k)
    rows = f.reshape(-1, n)
    step = max(1, chunk // (n * n))
    out, arg = torch.empty_like(rows), torch.empty(rows.shape, dtype=torch.int64, device=f.device)
    for s in range(0, len(rows), step):
        out[s : s + step], arg[s : s + step] = (rows[s : s + step, None, :] + sq).min(-1)
    return out.view(f.shape), arg.view(f.shape)


def lookup(grid: DistanceGrid, points: torch.Tensor) -> torch.Tensor:
    """Distances (M,) at points (M, 3) on the grid's device: nearest voxel's value, +inf outside the grid."""
    return _lookup(grid, points)[0]


def lookup_nearest(grid: DistanceGrid, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Distances (M,) as ``lookup`` and the index of a nearest point (M,) (-1 outside the grid)."""
    if grid.nearest is None:
        raise ValueError("the distance grid was built without nearest=True")
    return _lookup(grid, points, nearest=True)


def _lookup(grid: DistanceGrid, points: torch.Tensor, nearest: bool = False):
    # bounds tested in float before the cast: points far out (a ray's box entry can be ~1e18 away) or
    # non-finite ones would overflow int64, an undefined cast that may land inside the grid
    pts = points.detach().to(grid.distance.device, grid.origin.dtype)
    fijk = torch.floor((pts - grid.origin) / grid.cell + 0.5)
    shape = torch.tensor(grid.distance.shape, device=pts.device, dtype=fijk.dtype)
    inside = ((fijk >= 0) & (fijk < shape)).all(1)
    i = torch.where(inside[:, None], fijk, 0).long()
    out = torch.where(inside, grid.distance[i[:, 0], i[:, 1], i[:, 2]], torch.inf)
    if not nearest:
        return out, None
    return out, torch.where(inside, grid.nearest[i[:, 0], i[:, 1], i[:, 2]], -1)
