"""Geometry against ground truth: vertex error of the body, Chamfer distance and normal consistency.

Pure functions over arrays in metres. Point sets are compared both ways; ``chamfer`` is
the mean of the two mean nearest-neighbour distances (not squared), ``normal_consistency``
the mean |cos| between each point's normal and its nearest neighbour's, both ways.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh
from scipy.spatial import cKDTree


@dataclasses.dataclass
class SurfaceDistance:
    chamfer: float
    """(accuracy + completeness) / 2, metres."""
    accuracy: float
    """Mean distance from the prediction's points to the reference, metres."""
    completeness: float
    """Mean distance from the reference's points to the prediction, metres."""
    normal_consistency: float
    """Mean |cos| of the normals of nearest neighbours, both ways (1 = parallel everywhere)."""


def sample_surface(mesh: trimesh.Trimesh, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` area-uniform points on a mesh with the normals of their faces (seeded)."""
    points, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points), np.asarray(mesh.face_normals[faces])


def surface_distance(pred: tuple[np.ndarray, np.ndarray], ref: tuple[np.ndarray, np.ndarray]) -> SurfaceDistance:
    """Distances between two (points, normals) samples."""
    (pa, na), (pb, nb) = pred, ref
    if len(pa) == 0 or len(pb) == 0:
        nan = float("nan")
        return SurfaceDistance(nan, nan, nan, nan)
    da, ia = cKDTree(pb).query(pa)
    db, ib = cKDTree(pa).query(pb)
    ca = np.abs((na * nb[ia]).sum(1))
    cb = np.abs((nb * na[ib]).sum(1))
    acc, comp = float(da.mean()), float(db.mean())
    return SurfaceDistance((acc + comp) / 2, acc, comp, float((ca.mean() + cb.mean()) / 2))


def mesh_distance(pred: trimesh.Trimesh, ref: trimesh.Trimesh, count: int = 20000, seed: int = 0) -> SurfaceDistance:
    return surface_distance(sample_surface(pred, count, seed), sample_surface(ref, count, seed + 1))


def vertex_error(pred: np.ndarray, ref: np.ndarray, align: str = "centroid") -> float:
    """Mean per-vertex distance (metres) of two (V, 3) meshes with one topology.

    ``align``: "none", or "centroid" (translate the prediction's centroid onto the reference's:
    an orthographic camera does not observe depth, and a pinhole camera's depth is only as good
    as the fitted scale).
    """
    if pred.shape != ref.shape:
        raise ValueError(f"vertex_error: shapes {pred.shape} and {ref.shape} differ (different topologies)")
    if align == "centroid":
        pred = pred - pred.mean(0) + ref.mean(0)
    elif align != "none":
        raise ValueError(f"align: {align!r} (expected 'none' or 'centroid')")
    return float(np.linalg.norm(pred - ref, axis=1).mean())
