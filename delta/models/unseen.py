"""The body's albedo where no training frame looked: filled from what the frames saw.

A capture that never turns (a talking head, a dancer facing the camera) never shows the back of the head or of
the arms; no loss reaches the albedo there, so it holds whatever the field extrapolates from its start, and a
turntable or a novel view shows it (a bald, skin-coloured back of a head of short hair). After training, the
vertices some training frame saw are found (:func:`seen_vertices`: inside the image, first along the camera's
ray, turned towards it), and the rest take the harmonic fill of the seen ones' albedo
(:func:`delta.geometry.harmonic.harmonic_fill`): smooth, without a seam at the seen border, within the seen
colours' range. The mouth's inside keeps its own prior (no frame with the mouth shut sees it either, and a
fill from the lips would paint it lip-coloured); it neither gives to the fill nor takes from it.

Shapes: V vertices, U unseen vertices.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from delta.body.model import REGION
from delta.geometry.harmonic import harmonic_fill
from delta.geometry.mirror import MirrorGrid, cell_of, through_planes
from delta.geometry.nearest import PointIndex
from delta.geometry.raymesh import keep_scene
from delta.geometry.sight import vertex_normals, visible_points, visible_vertices

FACING = 0.2
"""A vertex counts as seen in a frame where its normal turns towards the camera by a cosine above this
(within ~78° of facing it): a vertex seen only at a grazing angle covers a sliver of a pixel and its albedo
is barely trained."""
MAX_FRAMES = 40
"""At most this many training frames, evenly spread, are looked through: on tight's 80-frame turn, 40 frames
see all but 100 of the 47 130 vertices the 80 see (0.2 %, each filled from its seen neighbours), in half the
time (30 s against 66 s on 2 cores, a training beside them)."""


@torch.no_grad()
def seen_vertices(model, frames) -> torch.Tensor:
    """(V,) bool: the body vertices some frame of ``frames`` sees (:func:`visible_vertices` with
    :data:`FACING`), on the model's own posed body and camera."""
    faces = model.body.faces
    seen = torch.zeros(model.body.num_vertices, dtype=torch.bool)
    offsets = model.offsets()
    for f in frames:
        verts = model.pose_body(int(f), offsets).vertices[0]
        keep_scene(verts, faces)
        seen |= visible_vertices(verts, faces, model.camera(int(f)), facing=FACING)
    return seen


def spread(frames: np.ndarray, most: int = MAX_FRAMES) -> np.ndarray:
    """At most ``most`` of ``frames``, evenly spread from the first to the last."""
    frames = np.asarray(frames)
    if len(frames) <= most:
        return frames
    return frames[np.unique(np.linspace(0, len(frames) - 1, most).round().astype(int))]


@torch.no_grad()
def unseen_albedo(model, frames) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """The fill of the albedo where no frame of ``frames`` looked: (U,) int64 vertex ids, (U, 3) their
    albedo, and the evidence (vertices seen and filled, frames looked through) for the log."""
    looked = spread(frames)
    seen = seen_vertices(model, looked)
    mouth = (model.body.regions == REGION["mouth"]).cpu() if model.body.regions.numel() else None
    unseen = ~seen if mouth is None else ~seen & ~mouth
    ids = torch.nonzero(unseen).squeeze(1)
    evidence = {"frames_looked": int(len(looked)), "vertices": int(len(seen)), "seen": int(seen.sum()),
                "filled": int(len(ids))}  # fmt: skip
    if not len(ids) or not bool(seen.any()):
        return ids, torch.zeros(0, 3), dict(evidence, filled=0)
    albedo = model.albedo().detach().cpu()
    filled = harmonic_fill(albedo, seen, model.body.faces.cpu(), mouth)
    return ids, filled[ids].float(), evidence


MIRROR_CELL = 0.02
"""The exterior's mirror grid's cell (metres)."""


def canonical_to_posed(model, points: torch.Tensor, nearest: torch.Tensor, out) -> torch.Tensor:
    """(N, 3) canonical points carried into a frame's pose (``out``: :meth:`HybridAvatar.pose_body`'s) by the maps
    of their ``nearest`` (N,) body vertices: x = G_i (G^c_i^{-1} x_c + d_i) (``delta.deformers.knn``)."""
    gc = model.canonical_T[nearest].double()
    local = torch.linalg.solve(gc[:, :, :3], (points.double() - gc[:, :, 3])[..., None])[..., 0]
    d = (out.rest_vertices[0] - model.body.v_template)[nearest].double()
    g = out.vertex_transforms_3x4[0][nearest].double()
    return (g[:, :, :3] @ (local + d)[..., None])[..., 0] + g[:, :, 3]


@torch.no_grad()
def exterior_mirror(model, frames) -> tuple[MirrorGrid | None, dict]:
    """Where no frame of ``frames`` looked at the exterior's canonical space, its mirror through the body along
    the canonical front axis (z): the back of a shirt that never turned to the camera is read from its front.
    None where nothing is mirrored (or there is no exterior); the evidence (cells near the body, seen,
    mirrored) for the log.

    A canonical cell within the exterior's reach (``render.max_dist``) of the body is seen in a frame where its
    centre, carried into the pose by its nearest vertex's map, is in the image with no body face before it on
    the camera's ray, and that vertex turns towards the camera (:data:`FACING`: the exterior over a surface
    seen only at a grazing angle is barely trained either). An unseen cell on a line along z whose seen cells
    hold the exterior somewhere (the occupancy grid's cells, else density over 0.5) takes the mirror plane of
    the line along +z (else -z) from its centre that enters the canonical body and leaves it again
    (:func:`delta.geometry.mirror.through_planes`), where the mirrored centre's cell is seen. A bare arm's back,
    or the hair behind a face that never turned (its line holds no exterior before the face), keep what the
    field holds."""
    if model.nerf is None:
        return None, {"exterior": False}
    looked = spread(frames)
    cano = model.canonical_vertices.detach().double().cpu()
    faces = model.body.faces.cpu()
    room, cell = float(model.spec.render.max_dist), MIRROR_CELL
    lo = cano.amin(0) - room
    size = [max(1, math.ceil(float(x))) for x in (cano.amax(0) + room - lo) / cell]
    axes = [lo[i] + cell * (torch.arange(size[i], dtype=torch.float64) + 0.5) for i in range(3)]
    centres = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    dist, nearest = PointIndex(cano).query(centres, 1)
    near = torch.nonzero(dist.reshape(-1) <= room).squeeze(1)
    nearest = nearest.reshape(-1)[near].to(model.canonical_T.device)
    points = centres[near]
    seen = torch.zeros(len(near), dtype=torch.bool)
    offsets = model.offsets()
    for f in looked:
        out = model.pose_body(int(f), offsets)
        verts = out.vertices[0]
        keep_scene(verts, model.body.faces)
        posed = canonical_to_posed(model, points.to(verts.device), nearest, out)
        normals = vertex_normals(verts, model.body.faces)[nearest]
        seen |= visible_points(posed, verts, model.body.faces, model.camera(int(f)), normals=normals, facing=FACING)
    seen_grid = torch.zeros(len(centres), dtype=torch.bool)
    seen_grid[near[seen]] = True
    unseen = torch.nonzero(~seen).squeeze(1)
    planes = torch.full((len(centres),), float("nan"), dtype=torch.float64)
    evidence = {"frames_looked": int(len(looked)), "cells_near_body": int(len(near)), "seen": int(seen.sum()),
                "mirrored": 0}  # fmt: skip
    # a line along z whose seen cells hold the exterior lends it to the line's unseen cells
    held = torch.zeros(len(centres), dtype=torch.bool)
    held[near[seen]] = _holds(model, points[seen])
    column = held.reshape(size).any(-1).reshape(-1)
    todo = unseen[column[torch.div(near[unseen], size[2], rounding_mode="floor")]]
    for sign in (1.0, -1.0):
        if not len(todo):
            break
        m = through_planes(points[todo], cano, faces, 2, sign)
        target = points[todo].clone()
        target[:, 2] = m - target[:, 2]
        ok = m.isfinite() & _seen_at(target, seen_grid, lo, cell, size)
        planes[near[todo[ok]]] = m[ok]
        todo = todo[~ok]
    mirrored = int(planes.isfinite().sum())
    evidence["mirrored"] = mirrored
    if not mirrored:
        return None, evidence
    return MirrorGrid(lo.float(), cell, planes.reshape(size).float()), evidence


def _seen_at(points: torch.Tensor, seen_grid: torch.Tensor, lo: torch.Tensor, cell: float, size) -> torch.Tensor:
    flat, inside = cell_of(points, lo, cell, tuple(size))
    return inside & seen_grid[flat]


def _holds(model, points: torch.Tensor) -> torch.Tensor:
    """(N,) bool: the exterior is at the canonical points (the occupancy grid's cells, else density over 0.5)."""
    x = torch.nan_to_num(points).float().to(model.background.device)
    if model.occupancy is not None:
        return model.occupancy.contains(x).cpu()
    return (model.nerf.density(x) > 0.5).cpu()


def mirror_state(mirror: MirrorGrid | None) -> dict | None:
    """What model.pt keeps of an exterior's mirror grid (tensors and numbers only)."""
    if mirror is None:
        return None
    return {"lo": mirror.lo.cpu().clone(), "cell": float(mirror.cell), "planes": mirror.planes.cpu().clone(),
            "axis": int(mirror.axis)}  # fmt: skip


def mirror_from_state(state: dict | None) -> MirrorGrid | None:
    """The mirror grid :func:`mirror_state` kept (None: none)."""
    if state is None:
        return None
    planes = state["planes"]
    if not torch.is_tensor(planes) or planes.dim() != 3 or tuple(state["lo"].shape) != (3,):
        raise ValueError("exterior_mirror: planes (X, Y, Z) and lo (3,) expected")
    return MirrorGrid(state["lo"].float(), float(state["cell"]), planes.float(), int(state.get("axis", 2)))
