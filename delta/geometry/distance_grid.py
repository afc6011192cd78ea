"""A coarse distance field to a point set on a voxel grid: cheap 'is this near the body?' queries.

Built once per frame from the posed vertices, on the device that holds them: on the CPU an exact
Euclidean distance transform over voxel centres (the distance between a voxel's centre and the
nearest occupied voxel's centre), elsewhere the exact distance from each voxel centre to the nearest
point (:class:`delta.geometry.nearest.PointIndex`). A lookup is a tensor index. Either way a lookup is
within √3 cells of the true distance of the query point, which is what culling samples far from the
body needs. Non-differentiable.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import torch
from scipy import ndimage

from delta.geometry.nearest import PointIndex


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

    ``nearest``: also keep, per voxel, the index of a nearest point — about as cheap, the transform
    finds those voxels anyway. ``method``: "transform" (SciPy, CPU), "search" (any device) or "auto"
    (the transform for CPU points).
    """
    points = points.detach()
    if method == "auto":
        method = "transform" if points.device.type == "cpu" else "search"
    if method == "search":
        return _build_search(points, cell, pad, nearest)
    if method != "transform":
        raise ValueError(f"unknown method {method!r}; expected 'auto', 'transform' or 'search'")
    points = points.cpu()
    pts = points.numpy().astype(np.float64)
    lo = pts.min(0) - pad
    shape = np.ceil((pts.max(0) + pad - lo) / cell).astype(int) + 1
    owner = np.full(shape, -1, dtype=np.int64)
    ijk = np.floor((pts - lo) / cell + 0.5).astype(int)
    owner[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = np.arange(len(pts))
    origin = torch.from_numpy(lo).to(points.dtype)
    if not nearest:
        dist = ndimage.distance_transform_edt(owner < 0)
        return DistanceGrid(origin, float(cell), torch.from_numpy(dist.astype(np.float32) * cell))
    dist, ind = ndimage.distance_transform_edt(owner < 0, return_indices=True)
    who = torch.from_numpy(owner[ind[0], ind[1], ind[2]])
    return DistanceGrid(origin, float(cell), torch.from_numpy(dist.astype(np.float32) * cell), who)


def _build_search(points: torch.Tensor, cell: float, pad: float, nearest: bool) -> DistanceGrid:
    """The grid from a nearest-point search at every voxel centre (devices without SciPy's transform)."""
    lo = points.amin(0) - pad
    shape = [int(n) for n in torch.ceil((points.amax(0) + pad - lo) / cell).long() + 1]
    axes = [lo[i] + cell * torch.arange(n, device=points.device, dtype=points.dtype) for i, n in enumerate(shape)]
    centres = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    dist, idx = PointIndex(points).query(centres, 1)
    distance = dist[:, 0].float().reshape(shape)
    return DistanceGrid(lo, float(cell), distance, idx[:, 0].reshape(shape) if nearest else None)


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
