"""Density grids and marching cubes (pure numpy / scikit-image, no model inside)."""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np
import torch
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from skimage import measure

from delta.geometry.sight import seen_along, view_ring

#: the views that decide the outside of an exterior surface (:func:`hidden_faces`): from the side and from
#: above (degrees looking down), as cameras see a standing person; none from below, where a capture's camera
#: does not look from and only the NeRF's underside (a hem's, a sleeve's) faces
OUTSIDE_ELEVATIONS = (0.0, 30.0, 60.0)
#: a face counts as facing a view where its normal turns at least this far (cos of 80 degrees) towards it
OUTSIDE_FACING = 0.17


@dataclasses.dataclass
class Grid:
    """A regular grid of cubic cells over a box."""

    origin: np.ndarray
    """(3,) position of sample (0, 0, 0)."""
    spacing: float
    """Cell size (m)."""
    shape: tuple[int, int, int]
    """Samples along x, y, z."""

    def points(self) -> np.ndarray:
        """(N, 3) sample positions, x slowest, z fastest (the order of ``values.reshape(shape)``)."""
        axes = [self.origin[i] + self.spacing * np.arange(self.shape[i]) for i in range(3)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def make_grid(lo: np.ndarray, hi: np.ndarray, cells: int) -> Grid:
    """Cubic cells, ``cells`` of them along the box's longest side."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    if not np.all(hi > lo):
        raise ValueError(f"empty box {lo} .. {hi}")
    h = float((hi - lo).max()) / cells
    shape = tuple(int(np.ceil((hi[i] - lo[i]) / h)) + 1 for i in range(3))
    return Grid(lo, h, shape)  # type: ignore[arg-type]


def nearest_side(points: np.ndarray, vertices: np.ndarray, normals: np.ndarray,
                 max_dist: float = np.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """For points (N, 3): (N,) bool within ``max_dist`` of a body vertex, and for those (M of them) the nearest
    vertex's index (M,) and the point's offset along its normal (M,), (x - v_nn) · n_nn: positive outside."""
    dist, idx = cKDTree(vertices).query(points, k=1, distance_upper_bound=max_dist, workers=1)
    near = np.isfinite(dist)
    i = idx[near]
    return near, i, ((points[near] - vertices[i]) * normals[i]).sum(-1)


def near_and_outside(points: np.ndarray, vertices: np.ndarray, normals: np.ndarray, max_dist: float) -> np.ndarray:
    """(N,) bool: within ``max_dist`` of a body vertex and on the outer side of the nearest one.

    The side test (x - v_nn) · n_nn > 0 is exact near the surface, which is where the
    exterior lives; inside the body the NeRF is never rendered (rays stop at the mesh).
    """
    near, _, side = nearest_side(points, vertices, normals, max_dist)
    out = np.zeros(len(points), dtype=bool)
    out[near] = side > 0
    return out


def skin_faces(vertices: np.ndarray, faces: np.ndarray, body: np.ndarray, normals: np.ndarray,
               depth: float) -> np.ndarray:  # fmt: skip
    """(F,) bool: the faces of a surface extracted with :func:`near_and_outside`'s mask that the mask made,
    not the field: faces facing into the body (their normal against the nearest body vertex's) whose centre
    lies less than ``depth`` outside it (a grid cell: the level set between a masked sample and its
    neighbour) or inside it.

    The exterior's density is cut to 0 inside the body, so its level set closes on the skin: a second wall
    under the garment that no ray sees (rays stop at the mesh) and a garment does not have.
    """
    if len(faces) == 0:
        return np.zeros(0, dtype=bool)
    normal, _ = face_normals(vertices, faces)
    _, idx, side = nearest_side(vertices[faces].mean(1), body, normals)
    return ((normal * normals[idx]).sum(-1) < 0) & (side < depth)


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, 3) unit normals (counter-clockwise seen from outside) and (F,) areas of a triangle mesh."""
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(cross, axis=-1)
    return cross / np.maximum(length, 1e-20)[:, None], length / 2


def hidden_faces(vertices: np.ndarray, faces: np.ndarray, body: np.ndarray, body_faces: np.ndarray,
                 azimuths: int, tol: float, keep_area: float) -> np.ndarray:  # fmt: skip
    """(F,) bool: the faces of an exterior surface that no outside view sees, in regions of ``keep_area`` (m²)
    or more.

    The views are parallel, ``azimuths`` turns about the up axis (y) at each of ``OUTSIDE_ELEVATIONS``; the
    surface and the ``body`` (its vertices (B, 3), ``body_faces``) hide it. A face is seen where its centre is
    (:func:`delta.geometry.sight.seen_along`, within ``tol`` metres, facing the view by ``OUTSIDE_FACING``).
    The NeRF's density fills what lies between a loose garment and the body, so its level set has walls
    inside the garment (under a skirt, beside the legs) and a cap under its hem that a one-sheet garment
    lacks; no view from outside reaches them. Smaller hidden patches (a fold's floor, a crease) stay.
    """
    if len(faces) == 0 or azimuths == 0:
        return np.zeros(len(faces), dtype=bool)
    normals, area = face_normals(vertices, faces)
    mesh_v = torch.from_numpy(np.concatenate([vertices, body]))
    mesh_f = torch.from_numpy(np.concatenate([faces, body_faces + len(vertices)]).astype(np.int64))
    centres = torch.from_numpy(vertices[faces].mean(1))
    dirs = view_ring(azimuths, OUTSIDE_ELEVATIONS)
    hidden = ~seen_along(centres, torch.from_numpy(normals), mesh_v, mesh_f, dirs, tol, OUTSIDE_FACING).numpy()
    pairs = trimesh.graph.face_adjacency(faces)
    pairs = pairs[hidden[pairs].all(1)]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(faces), len(faces)))
    _, label = connected_components(graph, directed=False)
    region_area = np.bincount(label, weights=area * hidden, minlength=label.max() + 1)
    return hidden & (region_area[label] >= keep_area)


def sample(grid: Grid, field: Callable[[np.ndarray], np.ndarray], mask: np.ndarray | None = None,
           chunk: int = 65536) -> np.ndarray:  # fmt: skip
    """Values of ``field`` (M, 3) -> (M,) on the grid, 0 where ``mask`` (N,) is False; shape ``grid.shape``."""
    pts = grid.points()
    values = np.zeros(len(pts), dtype=np.float32)
    ids = np.arange(len(pts)) if mask is None else np.flatnonzero(mask)
    for s in range(0, len(ids), chunk):
        sel = ids[s : s + chunk]
        values[sel] = field(pts[sel])
    return values.reshape(grid.shape)


def extract_surface(values: np.ndarray, grid: Grid, level: float) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of the ``level`` set, normals outward (towards lower values).

    The volume is padded with zeros so that surfaces touching the box close. Returns
    vertices (V, 3) float64 and faces (F, 3) int64, both empty when nothing reaches ``level``.
    """
    if not np.isfinite(values).all():
        raise ValueError("density grid has non-finite values")
    if values.size == 0 or values.max() <= level:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    padded = np.pad(values, 1, constant_values=min(0.0, float(values.min())))
    verts, faces, _, _ = measure.marching_cubes(padded, level=level, spacing=(grid.spacing,) * 3)
    # skimage orients faces so that normals point towards increasing values; flip them outwards
    return verts + grid.origin - grid.spacing, faces[:, ::-1].astype(np.int64)
