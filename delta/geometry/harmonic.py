"""Values a mesh holds at some vertices carried to the rest: the harmonic fill.

Each unknown vertex takes the mean of its neighbours' values (the graph Laplacian's equation L x = 0 on the
unknown vertices, the known ones fixed), so the fill is smooth, meets the known values without a seam and never
leaves their range (the discrete maximum principle). The weights are uniform over the mesh's edges: a linear
function on a regular grid, whose neighbours come in opposite pairs, is filled exactly.

Shapes: V vertices, F faces, C channels.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch
from scipy.sparse.csgraph import connected_components


def vertex_graph(faces: np.ndarray, num_vertices: int) -> scipy.sparse.csr_matrix:
    """(V, V) symmetric 0/1 adjacency of a mesh's edges (faces (F, 3))."""
    f = np.asarray(faces, dtype=np.int64)
    a = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    b = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    adj = scipy.sparse.coo_matrix((np.ones(len(a)), (a, b)), shape=(num_vertices, num_vertices)).tocsr()
    adj = adj + adj.T
    adj.data[:] = 1.0
    return adj


def harmonic_fill(values: torch.Tensor, known: torch.Tensor, faces: torch.Tensor,
                  excluded: torch.Tensor | None = None) -> torch.Tensor:  # fmt: skip
    """(V, C) ``values`` with every vertex not ``known`` replaced by the harmonic fill of the known ones.

    Args:
        values: (V, C); only the known vertices' rows are read.
        known: (V,) bool.
        faces: (F, 3) int64.
        excluded: (V,) bool or None: vertices that neither give nor take (their rows stay as given and
            their edges are left out), e.g. a region with its own prior.
    Returns:
        (V, C) on ``values``' device and dtype. An unknown vertex whose part of the mesh reaches no known
        vertex takes the mean of all the known values (the whole of ``values``' mean where none is known).
    """
    v = values.detach().cpu().double().numpy()
    n = v.shape[0]
    known_np = known.detach().cpu().numpy().astype(bool)
    if known_np.shape != (n,):
        raise ValueError(f"known: shape {tuple(known_np.shape)}, expected ({n},)")
    skip = np.zeros(n, bool) if excluded is None else excluded.detach().cpu().numpy().astype(bool)
    fixed = known_np & ~skip
    free = ~known_np & ~skip
    out = v.copy()
    if not free.any():
        return values.clone()
    fallback = v[fixed].mean(0) if fixed.any() else v.mean(0)
    adj = vertex_graph(faces.detach().cpu().numpy(), n)
    keep = scipy.sparse.diags((~skip).astype(float))
    adj = keep @ adj @ keep  # the excluded vertices' edges gone
    free_ids, fixed_ids = np.flatnonzero(free), np.flatnonzero(fixed)
    a_ff = adj[free_ids][:, free_ids]
    a_fk = adj[free_ids][:, fixed_ids]
    degree = np.asarray(adj[free_ids].sum(1)).ravel()
    # a free part that touches no known vertex has no boundary: its system is singular, so it takes the fallback
    reach = _reaches_known(adj, free, fixed)
    solve = free_ids[reach[free_ids]]
    if len(solve):
        rows = np.flatnonzero(reach[free_ids])
        lap = scipy.sparse.diags(degree[rows]) - a_ff[rows][:, rows]
        rhs = a_fk[rows] @ v[fixed_ids]
        x = scipy.sparse.linalg.spsolve(lap.tocsc(), rhs)
        out[solve] = np.asarray(x).reshape(len(solve), -1)
    out[free_ids[~reach[free_ids]]] = fallback
    return torch.from_numpy(out).to(device=values.device, dtype=values.dtype)


def _reaches_known(adj: scipy.sparse.csr_matrix, free: np.ndarray, fixed: np.ndarray) -> np.ndarray:
    """(V,) bool: the free vertices whose connected part (through free vertices) touches a fixed one."""
    live = free | fixed
    ids = np.flatnonzero(live)
    _, labels = connected_components(adj[ids][:, ids], directed=False)
    touched = np.zeros(labels.max() + 1 if len(labels) else 0, bool)
    touched[labels[fixed[ids]]] = True
    out = np.zeros(len(free), bool)
    out[ids] = touched[labels]
    return out & free
