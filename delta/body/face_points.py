"""Face points: landmarks that sit on the body mesh, so they follow shape, pose and expression.

A ``FacePoints`` is an embedding: each point is a barycentric combination of three mesh vertices
(a vertex point has weights (1, 0, 0)). Anny's dense set (:func:`dense_face_points`) is chosen from
the mesh itself: front-facing face vertices that the facial actions move, spread evenly by
farthest-point sampling, so that every action moves some of them. A detector's landmarks (a
MediaPipe face mesh) are another embedding of the same kind.

Shapes: K points, V vertices.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from delta import DeltaError
from delta.io import atomic_path
from delta.body.model import REGION, BodyModel

#: a point's rest normal must face the camera of a frontal view this much (cos of the angle to +z)
_FRONT = 0.25


@dataclasses.dataclass
class FacePoints:
    vertex_ids: torch.Tensor
    """(K, 3) int64 vertices each point interpolates."""
    bary: torch.Tensor
    """(K, 3) their weights (rows sum to 1)."""

    @property
    def num_points(self) -> int:
        return int(self.vertex_ids.shape[0])

    def __call__(self, vertices: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) vertices -> (B, K, 3) points."""
        w = self.bary.to(vertices.dtype)
        return (vertices[:, self.vertex_ids] * w[None, ..., None]).sum(2)

    def used_vertices(self) -> torch.Tensor:
        """(U,) the distinct vertices the points read."""
        return torch.unique(self.vertex_ids)

    @classmethod
    def at_vertices(cls, ids) -> "FacePoints":
        ids = torch.as_tensor(ids, dtype=torch.int64)
        bary = torch.zeros(len(ids), 3, dtype=torch.float64)
        bary[:, 0] = 1.0
        return cls(ids[:, None].expand(-1, 3).clone(), bary)


@dataclasses.dataclass
class LandmarkEmbedding:
    landmarks: np.ndarray
    """(K,) int64 detector landmark ids that are kept."""
    points: FacePoints
    """Where the kept landmarks sit on the body mesh."""
    spread_m: np.ndarray
    """(L,) median distance of each landmark's hits from their median (NaN: too few hits)."""
    views: int

    def save(self, path: str | Path, model_name: str) -> None:
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, landmarks=self.landmarks, vertex_ids=self.points.vertex_ids.numpy(),
                     bary=self.points.bary.numpy(), spread_m=self.spread_m, views=self.views,
                     model=np.array(model_name))  # fmt: skip

    @classmethod
    def load(cls, path: str | Path, num_vertices: int | None = None) -> "LandmarkEmbedding":
        try:
            with np.load(path, allow_pickle=False) as f:
                emb = cls(f["landmarks"].astype(np.int64),
                          FacePoints(torch.from_numpy(f["vertex_ids"].astype(np.int64)),
                                     torch.from_numpy(f["bary"].astype(np.float64))),
                          f["spread_m"], int(f["views"]))  # fmt: skip
        except (OSError, ValueError, KeyError) as exc:
            raise DeltaError(f"{path}: not a landmark embedding ({exc}); rebuild it (delta embed-face-landmarks)")
        if num_vertices is not None and int(emb.points.vertex_ids.max()) >= num_vertices:
            raise DeltaError(f"{path}: the embedding is for a mesh of more than {num_vertices} vertices")
        if len(emb.landmarks) != emb.points.num_points:
            raise DeltaError(f"{path}: {len(emb.landmarks)} landmark ids for {emb.points.num_points} points")
        return emb


def farthest_points(points: np.ndarray, count: int, first: int) -> np.ndarray:
    """Indices of ``count`` of (N, 3) ``points`` spread by greedy farthest-point sampling from ``first``."""
    chosen = [first]
    dist = np.linalg.norm(points - points[first], axis=1)
    for _ in range(min(count, len(points)) - 1):
        nxt = int(dist.argmax())
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(points - points[nxt], axis=1))
    return np.array(chosen)


def dense_face_points(model: BodyModel, count: int = 120) -> FacePoints:
    """Anny's dense face points on ``model`` (with its expression space): ``count`` front-facing face-skin
    vertices, among those the facial actions move, spread by farthest-point sampling from the vertex that
    moves most; then the vertex each action moves most, where the sampling missed it."""
    if model.exprdirs is None:
        raise DeltaError(f"body model '{model.name}': dense face points need its expression space")
    import trimesh

    rest = model.v_template.detach().double().cpu().numpy()
    normals = trimesh.Trimesh(rest, model.faces.cpu().numpy(), process=False).vertex_normals
    motion = model.exprdirs.detach().double().norm(dim=1).cpu().numpy()  # (V, E)
    face = model.regions.cpu().numpy() == REGION["face"]
    # vertices of the base mesh only (an upsampled model keeps them first): stable across levels
    base = np.arange(model.num_vertices) < (
        model.num_vertices if model.embed_vertex_ids is None else int(model.embed_vertex_ids.max()) + 1
    )
    candidates = np.flatnonzero(face & base & (normals[:, 2] > _FRONT) & (motion.max(1) > 1e-4))
    if len(candidates) < count:
        raise DeltaError(f"body model '{model.name}': {len(candidates)} front-facing moving face vertices, "
                         f"fewer than the {count} face points asked for")  # fmt: skip
    first = int(motion[candidates].max(1).argmax())
    chosen = set(candidates[farthest_points(rest[candidates], count, first)].tolist())
    for e in range(motion.shape[1]):
        strongest = candidates[int(motion[candidates, e].argmax())]
        if motion[strongest, e] > 1e-3:
            chosen.add(int(strongest))
    return FacePoints.at_vertices(sorted(chosen))


def restrict(model: BodyModel, ids: torch.Tensor) -> BodyModel:
    """The model on the vertices ``ids`` only (no faces): posing it costs K vertices, not V."""
    pick = lambda t: None if t is None else t[ids]  # noqa: E731
    return dataclasses.replace(
        model,
        v_template=model.v_template[ids],
        faces=torch.zeros(0, 3, dtype=torch.int64),
        shapedirs=model.shapedirs[ids],
        weights=model.weights[ids],
        regions=model.regions[ids],
        posedirs=pick(model.posedirs),
        exprdirs=pick(model.exprdirs),
        embed_vertex_ids=None,
        embed_bary=None,
    )
