"""A coarse distance field to a point set on a voxel grid: cheap 'is this near the body?' queries.

Built once per frame from the posed vertices with an exact Euclidean distance transform over
voxel centres; a lookup is an array index. Distances are accurate to about one cell
(√3/2 · cell), which is what culling samples far from the body needs. Non-differentiable.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage


@dataclasses.dataclass
class DistanceGrid:
    origin: np.ndarray
    """(3,) world position of the centre of voxel (0, 0, 0)."""
    cell: float
    """Voxel side (m)."""
    distance: np.ndarray
    """(nx, ny, nz) float32 distance from each voxel centre to the nearest occupied voxel centre."""


def build(points: np.ndarray, cell: float, pad: float) -> DistanceGrid:
    """Voxelise points (N, 3) at ``cell`` with ``pad`` metres of room around them."""
    lo = points.min(0) - pad
    shape = np.ceil((points.max(0) + pad - lo) / cell).astype(int) + 1
    occupied = np.zeros(shape, dtype=bool)
    ijk = np.floor((points - lo) / cell + 0.5).astype(int)
    occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    dist = ndimage.distance_transform_edt(~occupied).astype(np.float32) * cell
    return DistanceGrid(lo, float(cell), dist)


def lookup(grid: DistanceGrid, points: np.ndarray) -> np.ndarray:
    """Distances (M,) at points (M, 3): nearest voxel's value, +inf outside the grid."""
    # bounds tested in float before the cast: points far out (a ray's box entry can be ~1e18 away) or
    # non-finite ones would overflow int64, an undefined cast that may land inside the grid
    fijk = np.floor((points - grid.origin) / grid.cell + 0.5)
    shape = np.array(grid.distance.shape)
    inside = np.all((fijk >= 0) & (fijk < shape), axis=1)
    out = np.full(len(points), np.inf, dtype=np.float32)
    i = fijk[inside].astype(np.int64)
    out[inside] = grid.distance[i[:, 0], i[:, 1], i[:, 2]]
    return out
