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

import dataclasses
import math

import numpy as np
import torch

from delta.body.model import REGION
from delta.geometry.harmonic import harmonic_fill
from delta.geometry.mirror import MirrorGrid, cell_of, through_planes
from delta.geometry.nearest import PointIndex
from delta.geometry.raymesh import keep_scene
from delta.geometry.sight import vertex_normals, visible_points

FACING = 0.2
"""A vertex counts as seen in a frame where its normal turns towards the camera by a cosine above this
(within ~78° of facing it): a vertex seen only at a grazing angle covers a sliver of a pixel and its albedo
is barely trained."""
MAX_FRAMES = 40
"""At most this many training frames, evenly spread, are looked through: on tight's 80-frame turn, 40 frames
see all but 100 of the 47 130 vertices the 80 see (0.2 %, each filled from its seen neighbours), in half the
time (30 s against 66 s on 2 cores, a training beside them)."""


@torch.no_grad()
def survey(model, frames, cells: "Cells | None" = None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """What ``frames`` see, each frame posed once: the (V,) body vertices some frame sees (in the image, first on
    the camera's ray, turned to it by :data:`FACING`) and, with ``cells``, the (C,) exterior cells some frame sees
    (:func:`exterior_mirror`), on the model's own posed body and camera."""
    faces = model.body.faces
    seen = torch.zeros(model.body.num_vertices, dtype=torch.bool)
    cells_seen = None if cells is None else torch.zeros(len(cells.points), dtype=torch.bool)
    offsets = model.offsets()
    for f in frames:
        out = model.pose_body(int(f), offsets)
        verts, camera = out.vertices[0], model.camera(int(f))
        keep_scene(verts, faces)
        normals = vertex_normals(verts, faces)
        seen |= visible_points(verts, verts, faces, camera, normals=normals, facing=FACING)
        if cells is not None:
            posed = canonical_to_posed(model, cells.points.to(verts.device), cells.nearest, out)
            cells_seen |= visible_points(posed, verts, faces, camera, normals=normals[cells.nearest], facing=FACING)
    return seen, cells_seen


def seen_vertices(model, frames) -> torch.Tensor:
    """(V,) bool: the body vertices some frame of ``frames`` sees (:func:`survey`)."""
    return survey(model, frames)[0]


def spread(frames: np.ndarray, most: int = MAX_FRAMES) -> np.ndarray:
    """At most ``most`` of ``frames``, evenly spread from the first to the last."""
    frames = np.asarray(frames)
    if len(frames) <= most:
        return frames
    return frames[np.unique(np.linspace(0, len(frames) - 1, most).round().astype(int))]


@torch.no_grad()
def unseen_albedo(model, frames, seen: torch.Tensor | None = None,
                  outside: bool = True) -> tuple[torch.Tensor, torch.Tensor, dict]:  # fmt: skip
    """The fill of the albedo where no frame of ``frames`` looked (``seen``: the vertices they see, when
    :func:`survey` has them): (U,) int64 vertex ids, (U, 3) their albedo, and the evidence (vertices seen and
    filled) for the log. With ``outside`` the fill is of the seen surface as it looks from outside
    (:func:`outside_look`: the scalp under short hair gives the back of the head the hair's colour), else of
    the seen albedo alone."""
    if seen is None:
        seen = seen_vertices(model, spread(frames))
    mouth = (model.body.regions == REGION["mouth"]).cpu() if model.body.regions.numel() else None
    unseen = ~seen if mouth is None else ~seen & ~mouth
    ids = torch.nonzero(unseen).squeeze(1)
    evidence = {"frames_looked": int(len(spread(frames))), "vertices": int(len(seen)), "seen": int(seen.sum()),
                "filled": int(len(ids))}  # fmt: skip
    if not len(ids) or not bool(seen.any()):
        return ids, torch.zeros(0, 3), dict(evidence, filled=0)
    faces = model.body.faces.cpu()
    values = model.albedo().detach().cpu()
    if outside and model.nerf is not None:
        # only the seen vertices beside an unseen one bound the fill: the rest need no look
        touch = unseen[faces].any(1)
        border = torch.zeros_like(seen)
        border[faces[touch].reshape(-1)] = True
        border &= seen if mouth is None else seen & ~mouth
        own = values[border]
        look = outside_look(model, torch.nonzero(border).squeeze(1), own).to(values)
        evidence["border_covered"] = int((look - own).abs().amax(-1).gt(0.1).sum())
        values[border] = look
    filled = harmonic_fill(values, seen, faces, mouth)
    return ids, filled[ids].float(), evidence


LOOK_SAMPLES = 32
"""Samples of the exterior along a vertex's outward normal, over ``render.max_dist`` (:func:`outside_look`)."""


@torch.no_grad()
def outside_look(model, ids: torch.Tensor, albedo: torch.Tensor | None = None) -> torch.Tensor:
    """(N, 3) how the canonical body's vertices ``ids`` (N,) look from outside along their normals: the
    exterior's colour composited over their albedo (the volume rendering of :data:`LOOK_SAMPLES` samples out to
    ``render.max_dist``, where the occupancy grid holds the exterior), their albedo where nothing covers them.
    ``albedo``: their (N, 3) albedo where the caller has it (else the model's)."""
    cano = model.canonical_vertices.detach()
    albedo = (model.albedo().detach()[ids] if albedo is None else albedo).to(cano)
    if model.nerf is None or not len(ids):
        return albedo
    normals = vertex_normals(cano, model.body.faces)[ids]
    reach = float(model.spec.render.max_dist)
    step = reach / LOOK_SAMPLES
    t = (torch.arange(LOOK_SAMPLES, device=cano.device, dtype=cano.dtype) + 0.5) * step
    x = (cano[ids][:, None] + t[None, :, None] * normals[:, None]).reshape(-1, 3).float()
    color, sigma = model.nerf(x)
    if model.occupancy is not None:
        sigma = torch.where(model.occupancy.contains(x), sigma, torch.zeros_like(sigma))
    alpha = (1 - torch.exp(-sigma.reshape(len(ids), LOOK_SAMPLES) * step)).to(albedo)
    through = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], 1), 1)
    weight = through * alpha
    covered = (weight[..., None] * color.reshape(len(ids), LOOK_SAMPLES, 3).to(albedo)).sum(1)
    return covered + (1 - weight.sum(1, keepdim=True)) * albedo


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


@dataclasses.dataclass
class Cells:
    """The exterior's canonical cells within its reach of the body (C of them) on a grid of ``MIRROR_CELL``."""

    lo: torch.Tensor
    """(3,) float64 the grid's corner."""
    size: tuple[int, int, int]
    near: torch.Tensor
    """(C,) int64 the cells' flat indices into the grid."""
    nearest: torch.Tensor
    """(C,) int64 each cell centre's nearest canonical body vertex (on the model's device)."""
    points: torch.Tensor
    """(C, 3) float64 the cells' centres."""


def exterior_cells(model) -> Cells:
    """The canonical cells within ``render.max_dist`` of the canonical body (:class:`Cells`)."""
    cano = model.canonical_vertices.detach().double().cpu()
    room, cell = float(model.spec.render.max_dist), MIRROR_CELL
    lo = cano.amin(0) - room
    size = tuple(max(1, math.ceil(float(x))) for x in (cano.amax(0) + room - lo) / cell)
    axes = [lo[i] + cell * (torch.arange(size[i], dtype=torch.float64) + 0.5) for i in range(3)]
    centres = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    dist, nearest = PointIndex(cano).query(centres, 1)
    near = torch.nonzero(dist.reshape(-1) <= room).squeeze(1)
    return Cells(lo, size, near, nearest.reshape(-1)[near].to(model.canonical_T.device), centres[near])


@torch.no_grad()
def exterior_mirror(
    model, frames, surveyed: tuple[Cells, torch.Tensor] | None = None
) -> tuple[MirrorGrid | None, dict]:
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
    if surveyed is None:
        cells = exterior_cells(model)
        surveyed = cells, survey(model, spread(frames), cells)[1]
    cells, seen = surveyed
    cano = model.canonical_vertices.detach().double().cpu()
    faces = model.body.faces.cpu()
    lo, size, near, points = cells.lo, cells.size, cells.near, cells.points
    total = size[0] * size[1] * size[2]
    seen_grid = torch.zeros(total, dtype=torch.bool)
    seen_grid[near[seen]] = True
    unseen = torch.nonzero(~seen).squeeze(1)
    planes = torch.full((total,), float("nan"), dtype=torch.float64)
    evidence = {"frames_looked": int(len(spread(frames))), "cells_near_body": int(len(near)), "seen": int(seen.sum()),
                "mirrored": 0}  # fmt: skip
    # a line along z whose seen cells hold the exterior lends it to the line's unseen cells
    held = torch.zeros(total, dtype=torch.bool)
    held[near[seen]] = _holds(model, points[seen])
    column = held.reshape(size).any(-1).reshape(-1)
    todo = unseen[column[torch.div(near[unseen], size[2], rounding_mode="floor")]]
    for sign in (1.0, -1.0):
        if not len(todo):
            break
        m = through_planes(points[todo], cano, faces, 2, sign)
        target = points[todo].clone()
        target[:, 2] = m - target[:, 2]
        flat, inside = cell_of(target, lo, MIRROR_CELL, size)
        ok = m.isfinite() & inside & seen_grid[flat]
        planes[near[todo[ok]]] = m[ok]
        todo = todo[~ok]
    mirrored = int(planes.isfinite().sum())
    evidence["mirrored"] = mirrored
    if not mirrored:
        return None, evidence
    return MirrorGrid(lo.float(), MIRROR_CELL, planes.reshape(size).float()), evidence


@torch.no_grad()
def unseen_parts(model, frames, albedo: bool = True, exterior: bool = True,
                 outside: bool = True) -> tuple[tuple, MirrorGrid | None, dict]:  # fmt: skip
    """What training's end sets where no frame of ``frames`` looked, the frames posed once for both: the albedo's
    fill ((U,) ids, (U, 3) values; empty without ``albedo``; of the seen surface's look from outside with
    ``outside``: :func:`unseen_albedo`), the exterior's mirror (None without ``exterior`` or an exterior) and the
    evidence of both for the log."""
    looked = spread(frames)
    cells = exterior_cells(model) if exterior and model.nerf is not None else None
    if not albedo and cells is None:
        return (torch.zeros(0, dtype=torch.int64), torch.zeros(0, 3)), None, {}
    seen, cells_seen = survey(model, looked, cells)
    evidence = {"frames_looked": int(len(looked))}
    fill = (torch.zeros(0, dtype=torch.int64), torch.zeros(0, 3))
    if albedo:
        ids, values, evidence["albedo"] = unseen_albedo(model, looked, seen, outside)
        fill = (ids, values)
    mirror = None
    if cells is not None:
        mirror, evidence["exterior"] = exterior_mirror(model, looked, (cells, cells_seen))
    return fill, mirror, evidence


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
