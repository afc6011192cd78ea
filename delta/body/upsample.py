"""Mesh upsampling by midpoint subdivision with a barycentric embedding.

Every new vertex is a fixed barycentric combination of base-mesh vertices, so
any per-vertex quantity (template, blend shapes, skinning weights) is carried
by one sparse (V', V) interpolation matrix. SCARF upsamples SMPL-X the same
way (10,475 -> 38,703 vertices).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse
import torch

from delta.body.model import BodyModel


def subdivide_faces(faces: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """One level of 1-to-4 midpoint subdivision.

    Args:
        faces: (F, 3) triangles.
        num_vertices: V, the number of vertices the faces index.
    Returns:
        new_faces (4F, 3) over V + E vertices, and edges (E, 2): new vertex
        V + e is the midpoint of edge e.
    """
    faces = np.asarray(faces, dtype=np.int64)
    half = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])  # (3F, 2)
    edges, inverse = np.unique(np.sort(half, axis=1), axis=0, return_inverse=True)
    mid = num_vertices + inverse.reshape(3, -1).T  # (F, 3): midpoints of edges 01, 12, 20
    a, b, c = faces.T
    m01, m12, m20 = mid.T
    new_faces = np.concatenate(
        [
            np.stack([a, m01, m20], 1),
            np.stack([m01, b, m12], 1),
            np.stack([m20, m12, c], 1),
            np.stack([m01, m12, m20], 1),
        ]
    )
    return new_faces, edges


def embedding(faces: np.ndarray, num_vertices: int, level: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Faces after ``level`` subdivisions and each vertex's base-mesh embedding.

    Returns:
        faces (F', 3), vertex_ids (V', 3) base vertices and bary (V', 3) weights
        (rows sum to 1; base vertices embed as themselves with weights (1, 0, 0)).
        Every subdivided vertex lies in one base triangle, so three suffice.
    """
    interp = scipy.sparse.identity(num_vertices, format="csr")
    for _ in range(level):
        faces, edges = subdivide_faces(faces, interp.shape[0])
        mids = 0.5 * (interp[edges[:, 0]] + interp[edges[:, 1]])
        interp = scipy.sparse.vstack([interp, mids], format="csr")
    interp.sort_indices()
    counts = np.diff(interp.indptr)
    if counts.max() > 3:
        raise AssertionError("a subdivided vertex depends on more than 3 base vertices")
    ids = np.zeros((interp.shape[0], 3), dtype=np.int64)
    bary = np.zeros((interp.shape[0], 3))
    slot = np.arange(interp.nnz) - np.repeat(interp.indptr[:-1], counts)
    row = np.repeat(np.arange(interp.shape[0]), counts)
    ids[row, slot] = interp.indices
    bary[row, slot] = interp.data
    # pad unused slots with the row's first vertex at weight 0
    ids = np.where(bary > 0, ids, ids[:, :1])
    return faces, ids, bary


def interpolation_matrix(vertex_ids: torch.Tensor, bary: torch.Tensor, num_base: int) -> torch.Tensor:
    """Sparse (V', V) matrix M with M @ base_values = upsampled values."""
    rows = torch.arange(vertex_ids.shape[0]).repeat_interleave(3)
    idx = torch.stack([rows, vertex_ids.reshape(-1)])
    return torch.sparse_coo_tensor(
        idx, bary.reshape(-1), (vertex_ids.shape[0], num_base), check_invariants=True
    ).coalesce()


def upsample_body_model(model: BodyModel, level: int) -> BodyModel:
    """The model with its mesh subdivided ``level`` times; per-vertex data interpolated.

    Region labels take the label of the embedding's heaviest base vertex (ties: the lowest index).
    """
    if level == 0:
        return model
    faces, ids, bary = embedding(model.faces.cpu().numpy(), model.num_vertices, level)
    ids_t = torch.from_numpy(ids)
    bary_t = torch.from_numpy(bary).to(model.v_template.dtype)

    def interp(values: torch.Tensor | None) -> torch.Tensor | None:
        if values is None:
            return None
        gathered = values[ids_t]  # (V', 3, ...)
        w = bary_t.reshape(bary_t.shape + (1,) * (values.ndim - 1))
        return (gathered * w).sum(1)

    weights = interp(model.weights)
    return dataclasses.replace(
        model,
        name=f"{model.name}_sub{level}",
        v_template=interp(model.v_template),
        faces=torch.from_numpy(faces),
        shapedirs=interp(model.shapedirs),
        posedirs=interp(model.posedirs),
        exprdirs=interp(model.exprdirs),
        weights=weights / weights.sum(-1, keepdim=True),
        regions=model.regions[ids_t.gather(1, bary_t.argmax(1, keepdim=True))[:, 0]],
        embed_vertex_ids=ids_t,
        embed_bary=bary_t,
    )
