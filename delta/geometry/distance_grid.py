"""A coarse distance field to a point set on a voxel grid: cheap 'is this near the body?' queries.

Built once per frame from the posed vertices with an exact Euclidean distance transform over
voxel centres; a lookup is an array index. Distances are accurate to about one cell
(√3/2 · cell), which is what culling samples far from the body needs. Non-differentiable.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
from scipy import ndimage


#: the largest ``render.max_dist`` (m) for which the avatar builds a per-frame distance grid (at 0.02 m
#: cells a 1 m pad is ~10^7 cells, 40 MB; the paper's "no culling" 10 m would be ~10^9)
GRID_REACH = 1.0


@dataclasses.dataclass
class DistanceGrid:
    origin: np.ndarray
    """(3,) world position of the centre of voxel (0, 0, 0)."""
    cell: float
    """Voxel side (m)."""
    distance: np.ndarray
    """(nx, ny, nz) float32 distance from each voxel centre to the nearest occupied voxel centre."""
    nearest: Optional[np.ndarray] = None
    """(nx, ny, nz) int64 index of a point in the nearest occupied voxel (when built with ``nearest``)."""


def build(points: np.ndarray, cell: float, pad: float, nearest: bool = False) -> DistanceGrid:
    """Voxelise points (N, 3) at ``cell`` with ``pad`` metres of room around them.

    ``nearest``: also keep, per voxel, which point lies in the nearest occupied voxel (a point of
    that voxel when several share it) — about as cheap, the transform finds those voxels anyway.
    """
    lo = points.min(0) - pad
    shape = np.ceil((points.max(0) + pad - lo) / cell).astype(int) + 1
    owner = np.full(shape, -1, dtype=np.int64)
    ijk = np.floor((points - lo) / cell + 0.5).astype(int)
    owner[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = np.arange(len(points))
    if not nearest:
        dist = ndimage.distance_transform_edt(owner < 0)
        return DistanceGrid(lo, float(cell), dist.astype(np.float32) * cell)
    dist, ind = ndimage.distance_transform_edt(owner < 0, return_indices=True)
    return DistanceGrid(lo, float(cell), dist.astype(np.float32) * cell, owner[ind[0], ind[1], ind[2]])


def lookup(grid: DistanceGrid, points: np.ndarray) -> np.ndarray:
    """Distances (M,) at points (M, 3): nearest voxel's value, +inf outside the grid."""
    return _lookup(grid, points)[0]


def lookup_nearest(grid: DistanceGrid, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances (M,) as ``lookup`` and the index of a nearest point (M,) (-1 outside the grid)."""
    if grid.nearest is None:
        raise ValueError("the distance grid was built without nearest=True")
    return _lookup(grid, points, nearest=True)


def _lookup(grid: DistanceGrid, points: np.ndarray, nearest: bool = False):
    # bounds tested in float before the cast: points far out (a ray's box entry can be ~1e18 away) or
    # non-finite ones would overflow int64, an undefined cast that may land inside the grid
    fijk = np.floor((points - grid.origin) / grid.cell + 0.5)
    shape = np.array(grid.distance.shape)
    inside = np.all((fijk >= 0) & (fijk < shape), axis=1)
    out = np.full(len(points), np.inf, dtype=np.float32)
    i = fijk[inside].astype(np.int64)
    out[inside] = grid.distance[i[:, 0], i[:, 1], i[:, 2]]
    if not nearest:
        return out, None
    who = np.full(len(points), -1, dtype=np.int64)
    who[inside] = grid.nearest[i[:, 0], i[:, 1], i[:, 2]]
    return out, who
