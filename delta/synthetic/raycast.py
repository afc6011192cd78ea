"""The generator's own renderer: first-hit ray casting (Embree) with edge supersampling.

It belongs to data generation only; training never uses it, so a reconstruction
does not fit its own forward model. Labels, depth and masks come from one ray
through each pixel centre, so they are exactly the projection of the meshes;
colours at pixels where labels or colours change are averaged over an S x S
grid of sub-pixel rays (anti-aliasing).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np
import torch
import trimesh
from trimesh.ray.ray_pyembree import RayMeshIntersector

AlbedoFn = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
"""(object ids (N,), canonical points (N, 3), labels (N,)) -> (N, 3) albedo."""


@dataclasses.dataclass
class SceneMesh:
    """All surfaces of one frame as one triangle mesh."""

    vertices: np.ndarray
    """(Nv, 3) posed world positions."""
    faces: np.ndarray
    """(Nf, 3) triangles."""
    face_object: np.ndarray
    """(Nf,) 0 for the body, k for the k-th layer."""
    canonical: np.ndarray
    """(Nv, 3) canonical positions (texture space)."""
    canonical_normals: np.ndarray
    """(Nv, 3) canonical normals (baked lighting)."""
    vertex_label: np.ndarray
    """(Nv,) label each vertex paints."""


@dataclasses.dataclass
class RenderedFrame:
    image: np.ndarray
    """(H, W, 3) float32 RGB in [0, 1]."""
    label: np.ndarray
    """(H, W) uint8 label at the pixel centre (0 = background)."""
    depth: np.ndarray
    """(H, W) float32 camera depth at the pixel centre (+inf = background; orthographic depth is -Z)."""
    alpha: np.ndarray
    """(H, W) float32 fraction of the pixel covered (from the sub-samples at edges)."""


def _shade(scene, tri, locations, albedo_fn, shade_fn):
    corners = scene.faces[tri]
    bary = trimesh.triangles.points_to_barycentric(scene.vertices[corners], locations)
    bary = np.clip(np.nan_to_num(bary, nan=1.0 / 3), 0, 1)
    bary = bary / bary.sum(1, keepdims=True)
    canon = np.einsum("nk,nkc->nc", bary, scene.canonical[corners])
    normals = np.einsum("nk,nkc->nc", bary, scene.canonical_normals[corners])
    label = scene.vertex_label[corners[np.arange(len(tri)), bary.argmax(1)]]
    colour = albedo_fn(scene.face_object[tri], canon, label) * shade_fn(normals)[:, None]
    return colour, label


def _cast(inter, camera, uv):
    origins, dirs = camera.rays(torch.from_numpy(uv))
    origins, dirs = origins.numpy(), dirs.numpy()
    tri, ray, loc = inter.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
    return tri, ray, loc


def render(scene: SceneMesh, camera, albedo_fn: AlbedoFn, shade_fn, background, supersample: int = 2) -> RenderedFrame:
    """Render one frame with a camera from :mod:`delta.cameras`."""
    H, W = camera.height, camera.width
    mesh = trimesh.Trimesh(scene.vertices, scene.faces, process=False)
    inter = RayMeshIntersector(mesh)
    ii, jj = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    uv = np.stack([jj.ravel() + 0.5, ii.ravel() + 0.5], 1).astype(np.float64)
    bg = np.asarray(background, dtype=np.float64)
    image = np.tile(bg, (H * W, 1))
    label = np.zeros(H * W, dtype=np.uint8)
    depth = np.full(H * W, np.inf, dtype=np.float32)
    alpha = np.zeros(H * W, dtype=np.float32)
    tri, ray, loc = _cast(inter, camera, uv)
    if len(tri):
        colour, lab = _shade(scene, tri, loc, albedo_fn, shade_fn)
        image[ray], label[ray], alpha[ray] = colour, lab, 1.0
        depth[ray] = camera.project(torch.from_numpy(loc))[1].numpy()
    # anti-aliasing where labels or colours change
    img2, lab2 = image.reshape(H, W, 3), label.reshape(H, W)
    edge = np.zeros((H, W), bool)
    for axis in (0, 1):
        dl = np.diff(lab2.astype(np.int16), axis=axis) != 0
        dc = np.abs(np.diff(img2, axis=axis)).max(-1) > 0.08
        d = dl | dc
        if axis == 0:
            edge[1:] |= d
            edge[:-1] |= d
        else:
            edge[:, 1:] |= d
            edge[:, :-1] |= d
    idx = np.flatnonzero(edge.ravel())
    if supersample > 1 and len(idx):
        offs = (np.arange(supersample) + 0.5) / supersample - 0.5
        grid = np.stack(np.meshgrid(offs, offs, indexing="ij"), -1).reshape(-1, 2)
        sub_uv = (uv[idx][:, None, :] + grid[None]).reshape(-1, 2)
        acc = np.tile(bg, (len(sub_uv), 1))
        hit = np.zeros(len(sub_uv), np.float32)
        stri, sray, sloc = _cast(inter, camera, sub_uv)
        if len(stri):
            acc[sray] = _shade(scene, stri, sloc, albedo_fn, shade_fn)[0]
            hit[sray] = 1.0
        n = len(grid)
        image[idx] = acc.reshape(-1, n, 3).mean(1)
        alpha[idx] = hit.reshape(-1, n).mean(1)
    return RenderedFrame(
        image=np.clip(image, 0, 1).reshape(H, W, 3).astype(np.float32),
        label=label.reshape(H, W),
        depth=depth.reshape(H, W),
        alpha=alpha.reshape(H, W),
    )
