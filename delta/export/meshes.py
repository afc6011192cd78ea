"""The avatar's meshes: the body (canonical and posed, albedo as vertex colours) and the clothing/hair
surface of the NeRF (marching cubes in the canonical space, cleaned with pymeshlab, posed by forward skinning).

Canonical exports are in the subject's canonical space: the template with the subject's shape and
offsets in the canonical pose (so that body and clothing line up). The NeRF itself lives in the
mean-shape canonical space; its surface reaches the subject's canonical pose (or a frame's pose) by
forward skinning, the inverse of the renderer's backward skinning. Stage 2's non-rigid F_e is
conditioned on posed body points and is left out of the exported clothing.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Optional

import numpy as np
import pymeshlab
import torch
import trimesh
from scipy.spatial import cKDTree

from delta.body.lbs import LBSOutput, lbs
from delta.deformers.knn import SkinningFrame
from delta.export import marching
from delta.export.settings import ExportSettings
from delta.export.skinning import forward_skin, prepare_forward
from delta.io import atomic_path
from delta.models.avatar import HybridAvatar


#: hidden patches of the exterior's surface narrower than this many grid cells stay (a fold's floor)
HIDDEN_CELLS = 4

#: the file of one exterior layer's mesh (``space``: nerf_space or canonical), beside the whole exterior's
#: clothing_{space}.ply (a layer named clothing must not overwrite it)
LAYER_MESH = "layer_{layer}_{space}.ply"


@dataclasses.dataclass
class MeshPart:
    """One exported mesh (V vertices, F faces)."""

    vertices: np.ndarray
    """(V, 3) float64 positions (m)."""
    faces: np.ndarray
    """(F, 3) int64 vertex indices, counter-clockwise seen from outside."""
    colors: np.ndarray
    """(V, 3) float RGB in [0, 1]."""

    @property
    def empty(self) -> bool:
        return len(self.faces) == 0

    def to_trimesh(self) -> trimesh.Trimesh:
        rgba = np.concatenate([np.round(np.clip(self.colors, 0, 1) * 255), np.full((len(self.colors), 1), 255)], 1)
        return trimesh.Trimesh(self.vertices, self.faces, vertex_colors=rgba.astype(np.uint8), process=False)


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().double().numpy()


@torch.no_grad()
def canonical_pose(model: HybridAvatar, offsets: torch.Tensor) -> LBSOutput:
    """The subject (shape and offsets) in the canonical pose, without translation."""
    pose = model.body.canonical_pose[None].to(model.betas)
    return lbs(model.body, model.betas[None], pose, offsets=offsets)


@torch.no_grad()
def body_mesh(model: HybridAvatar, frame: Optional[int] = None) -> tuple[MeshPart, LBSOutput]:
    """The body with albedo colours in the canonical pose (``frame`` None) or posed as a frame."""
    offsets = model.offsets()
    out = canonical_pose(model, offsets) if frame is None else model.pose_body(frame, offsets)
    part = MeshPart(_np(out.vertices[0]), model.body.faces.cpu().numpy().astype(np.int64), _np(model.albedo()))
    return part, out


def forward_frame(model: HybridAvatar, out: LBSOutput) -> SkinningFrame:
    """Forward skinning from the NeRF's canonical space to a posed body, over the vertices the renderer uses."""
    ids = model.knn_ids
    template, cano_T = model.body.v_template[ids], model.canonical_T[ids]
    # where backward skinning sends posed vertex i: G^c_i template_i (no canonical pose correctives)
    canonical = (cano_T[..., :3] @ template[..., None]).squeeze(-1) + cano_T[..., 3]
    disp = out.rest_vertices[0, ids] - template
    return prepare_forward(canonical, cano_T, out.vertex_transforms_3x4[0, ids], disp, model.body.weights[ids])


@torch.no_grad()
def nerf_query(model: HybridAvatar, points: np.ndarray, chunk: int = 65536,
               layer: str | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Colour (N, 3) and density (N,) of the NeRF (of one ``layer`` of a layered one) at canonical points (read at
    their mirror image where no training frame looked: ``model.exterior_mirror``)."""
    dev = model.canonical_vertices.device
    field = model.nerf if layer is None else model.nerf.layers[layer]
    rgb, sigma = [], []
    for s in range(0, len(points), chunk):
        x = torch.from_numpy(points[s : s + chunk]).float().to(dev)
        c, d = field(x if model.exterior_mirror is None else model.exterior_mirror(x))
        rgb.append(c.cpu().numpy())
        sigma.append(d.cpu().numpy())
    if not rgb:
        return np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(rgb).astype(np.float64), np.concatenate(sigma).astype(np.float64)


def clean(vertices: np.ndarray, faces: np.ndarray, settings: ExportSettings) -> tuple[np.ndarray, np.ndarray]:
    """pymeshlab: drop small components, Taubin smoothing, quadric decimation to ``settings.decimate`` faces."""
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=vertices, face_matrix=faces.astype(np.int32)))
    if settings.min_component_faces > 0:
        ms.meshing_remove_connected_component_by_face_number(mincomponentsize=settings.min_component_faces)
    if settings.smooth > 0 and ms.current_mesh().face_number() > 0:
        ms.apply_coord_taubin_smoothing(stepsmoothnum=settings.smooth)
    if 0 < settings.decimate < ms.current_mesh().face_number():
        ms.meshing_decimation_quadric_edge_collapse(targetfacenum=settings.decimate, preservenormal=True,
                                                    preservetopology=True, autoclean=True)  # fmt: skip
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    return m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64).reshape(-1, 3)


def edge_lengths(part: MeshPart) -> np.ndarray:
    """(3F,) the length of every face's edges (shared edges counted once a face)."""
    v = part.vertices[part.faces]
    return np.linalg.norm(v - np.roll(v, 1, axis=1), axis=-1).reshape(-1)


def split_long_edges(vertices: np.ndarray, faces: np.ndarray, longest: float) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint subdivision of every edge longer than ``longest`` until none is (the surface unchanged:
    new vertices lie on the old edges)."""
    if longest <= 0 or len(faces) == 0:
        return vertices, faces
    edge = edge_lengths(MeshPart(vertices, faces, np.zeros_like(vertices))).max()
    if edge <= longest:
        return vertices, faces
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=vertices, face_matrix=faces.astype(np.int32)))
    passes = math.ceil(math.log2(edge / longest)) + 1
    ms.meshing_surface_subdivision_midpoint(iterations=passes, threshold=pymeshlab.PureValue(longest))
    m = ms.current_mesh()
    return m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64).reshape(-1, 3)


def canonical_surface(model: HybridAvatar) -> tuple[np.ndarray, np.ndarray]:
    """The canonical body's vertices (V, 3) and vertex normals (V, 3), float64."""
    cano = model.canonical_vertices.detach().cpu().numpy().astype(np.float64)
    return cano, trimesh.Trimesh(cano, model.body.faces.cpu().numpy(), process=False).vertex_normals


def density_grid(model: HybridAvatar, settings: ExportSettings, layer: str | None = None,
                 surface: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, marching.Grid]:  # fmt: skip
    """NeRF density on a grid over the canonical body's box plus ``max_dist``, 0 farther than ``max_dist``
    from the body (the renderer never evaluates the NeRF there) and inside it (rays stop at the mesh);
    ``surface``: the model's :func:`canonical_surface`, when the caller has it."""
    cano, normals = surface or canonical_surface(model)
    max_dist = float(model.spec.render.max_dist)
    grid = marching.make_grid(cano.min(0) - max_dist, cano.max(0) + max_dist, settings.grid)
    mask = marching.near_and_outside(grid.points(), cano, normals, max_dist)
    values = marching.sample(grid, lambda p: nerf_query(model, p, settings.chunk, layer)[1], mask, settings.chunk)
    return values, grid


def clothing_nerf_space(model: HybridAvatar, settings: ExportSettings, longest_edge: float = 0.0,
                        layer: str | None = None) -> MeshPart:  # fmt: skip
    """The clothing/hair surface {σ = threshold} in the NeRF's canonical space (one ``layer``'s of a layered
    NeRF) as a sheet, as a garment is: without the wall the density grid's cut at the skin makes
    (:func:`marching.skin_faces`) nor the walls no view from outside sees (:func:`marching.hidden_faces`,
    ``settings.outside_views``); cleaned, NeRF colours read at its vertices after edges longer than
    ``longest_edge`` (m; 0: none) are split."""
    if model.nerf is None:
        raise ValueError("the avatar has no NeRF (no clothing or hair was modelled)")
    surface = canonical_surface(model)
    values, grid = density_grid(model, settings, layer, surface)
    verts, faces = marching.extract_surface(values, grid, settings.threshold)
    faces = faces[~marching.skin_faces(verts, faces, *surface, grid.spacing)]
    body_faces = model.body.faces.cpu().numpy().astype(np.int64)
    faces = faces[~marching.hidden_faces(verts, faces, surface[0], body_faces, settings.outside_views,
                                         grid.spacing / 2, (HIDDEN_CELLS * grid.spacing) ** 2)]  # fmt: skip
    if len(faces):
        verts, faces = split_long_edges(*clean(verts, faces, settings), longest_edge)
    else:
        verts = verts[:0]
    colors = nerf_query(model, verts, settings.chunk, layer)[0] if len(verts) else np.zeros((0, 3))
    return MeshPart(verts, faces, colors)


@torch.no_grad()
def pose_clothing(model: HybridAvatar, part: MeshPart, out: LBSOutput) -> MeshPart:
    """Forward-skin a NeRF-space surface onto a posed (or canonical-pose) body."""
    if part.empty:
        return part
    frame = forward_frame(model, out)
    rs = model.spec.render
    x = torch.from_numpy(part.vertices).to(model.canonical_vertices)
    posed = forward_skin(frame, x, rs.k, rs.sigma)
    return MeshPart(_np(posed), part.faces, part.colors)


@torch.no_grad()
def rest_body(model: HybridAvatar) -> tuple[MeshPart, LBSOutput]:
    """The body with albedo colours in the rest pose (every rotation the identity): the bind pose of a
    skinned export."""
    pose = torch.zeros(1, model.body.num_joints, 3).to(model.betas)
    out = lbs(model.body, model.betas[None], pose, offsets=model.offsets())
    return MeshPart(_np(out.vertices[0]), model.body.faces.cpu().numpy().astype(np.int64), _np(model.albedo())), out


def borrowed_weights(body_vertices: np.ndarray, weights: np.ndarray, points: np.ndarray, k: int = 4) -> np.ndarray:
    """(N, J) skinning weights of ``points`` from the (V, J) ``weights`` of their k nearest body vertices
    (V, 3), blended by inverse distance."""
    if len(points) == 0:
        return np.zeros((0, weights.shape[1]))
    d, idx = cKDTree(body_vertices).query(points, k=k)
    inv = 1.0 / np.maximum(d, 1e-6)
    w = (inv[..., None] * weights[idx]).sum(1)
    return w / w.sum(1, keepdims=True)


def write_mesh(path: str | os.PathLike, part: MeshPart) -> None:
    """PLY (binary, vertex colours) or OBJ, by the suffix, atomically."""
    with atomic_path(path) as tmp:
        part.to_trimesh().export(tmp)


def read_mesh(path: str | os.PathLike) -> MeshPart:
    """A mesh ``write_mesh`` wrote (PLY or OBJ), its vertex colours included (grey where it has none)."""
    tm = trimesh.load(path, process=False, force="mesh")
    colors = np.asarray(tm.visual.vertex_colors)[:, :3] / 255.0 if len(tm.vertices) else np.zeros((0, 3))
    return MeshPart(np.asarray(tm.vertices, np.float64), np.asarray(tm.faces, np.int64).reshape(-1, 3), colors)


def write_glb(path: str | os.PathLike, parts: dict[str, MeshPart]) -> None:
    """One GLB scene with a node per non-empty part."""
    scene = trimesh.Scene()
    for name, part in parts.items():
        if not part.empty:
            scene.add_geometry(part.to_trimesh(), node_name=name, geom_name=name)
    with atomic_path(path) as tmp:
        scene.export(tmp, file_type="glb")
