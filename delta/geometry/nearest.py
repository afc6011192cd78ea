"""The k nearest of a fixed point set, on the device that holds the points.

On the CPU a SciPy KD-tree answers (float64). On any other device the search is tensor work over a box
hierarchy of the points (:mod:`delta.geometry.clusters`): a query's distances to one point of every leaf
bound its k-th nearest distance from above, every leaf whose box lies within that bound is searched
exhaustively, and the k smallest are kept. Exact in the points' precision; no gradient (callers recompute
differentiable distances from the indices).

Shapes: V points, N queries, D dimensions (2 or 3).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from delta.geometry import clusters

PARALLEL_QUERY = 20_000
"""KD-tree queries of at least this many points use the job's threads (fewer: one thread is faster)."""
_CHUNK = 1 << 22
"""Query-leaf (and query-point) distances held at once by the tensor search."""


class PointIndex:
    """Nearest-point queries against ``points`` (V, D), V >= 1, answered on the points' device."""

    def __init__(self, points: torch.Tensor, backend: str = "auto"):
        if points.shape[0] == 0:
            raise ValueError("a point index needs at least one point")
        if backend == "auto":
            backend = "kdtree" if points.device.type == "cpu" else "torch"
        if backend not in ("kdtree", "torch"):
            raise ValueError(f"unknown backend {backend!r}; expected 'auto', 'kdtree' or 'torch'")
        self.points = points.detach()
        self.backend = backend
        if backend == "kdtree":
            self.tree = cKDTree(self.points.cpu().numpy().astype(np.float64))
        else:
            self.tree = clusters.build(self.points, self.points)

    def query(self, queries: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Distances (N, k) and indices (N, k) int64 of the k nearest points, nearest first, on the queries'
        device (k is capped at V)."""
        k = min(int(k), self.points.shape[0])
        if self.backend == "kdtree":
            pts = queries.detach().cpu().numpy().astype(np.float64)
            workers = torch.get_num_threads() if len(pts) >= PARALLEL_QUERY else 1
            dist, idx = self.tree.query(pts, k=k, workers=workers)
            dist = torch.from_numpy(np.asarray(dist).reshape(len(pts), k)).to(queries.device)
            return dist, torch.from_numpy(np.asarray(idx, dtype=np.int64).reshape(len(pts), k)).to(queries.device)
        q = queries.detach().to(self.points.device, self.points.dtype)
        out = [_search(self.points, self.tree, q[s : s + self._step()], k) for s in range(0, len(q), self._step())]
        if not out:
            empty = q.new_zeros((0, k))
            return empty.to(queries.device), empty.long().to(queries.device)
        dist, idx = (torch.cat(x).to(queries.device) for x in zip(*out))
        return dist, idx

    def _step(self) -> int:
        return max(1, _CHUNK // self.tree.members.shape[0])


def _search(points: torch.Tensor, tree: clusters.Hierarchy, q: torch.Tensor, k: int):
    """The k nearest of points for queries q (n, D) over the leaves of ``tree``: (n, k) distances, indices."""
    members = tree.members
    reps = points[members[:, 0]]  # one point of every leaf: its distance is a real point's
    bound = torch.full((len(q),), torch.inf, dtype=q.dtype, device=q.device)
    if members.shape[0] >= k:
        bound = torch.cdist(q, reps, compute_mode="donot_use_mm_for_euclid_dist").kthvalue(k, dim=1).values
    gap = clusters.box_distance(q, tree.leaf_lo, tree.leaf_hi)  # (n, L)
    slack = 4 * torch.finfo(q.dtype).eps * (q.abs().amax() + points.abs().amax() + bound.clamp_max(1e30))
    near = gap <= (bound + slack)[:, None]
    # queries taken in order of how many leaves they search, each batch as wide as its widest query
    count = near.sum(1)
    by_count = torch.argsort(count)
    dist = torch.empty((len(q), k), dtype=q.dtype, device=q.device)
    idx = torch.empty((len(q), k), dtype=torch.int64, device=q.device)
    widths = count[by_count].cpu().numpy()  # ascending: a batch is as wide as its last query
    s, per_batch = 0, _CHUNK // members.shape[1]
    while s < len(q):
        cost = np.arange(1, len(q) - s + 1) * np.maximum(widths[s:], 1)
        step = max(1, int(np.searchsorted(cost, per_batch, side="right")))
        rows = by_count[s : s + step]
        width = max(int(widths[s + len(rows) - 1]), 1)
        leaf = torch.argsort(torch.where(near[rows], gap[rows], torch.inf), dim=1)[:, :width]
        cand = members[leaf]  # (m, width, S), nearest box first
        ok = torch.gather(near[rows], 1, leaf)[..., None] & (cand >= 0)
        diff = points[cand.clamp_min(0)] - q[rows, None, None]
        # a real distance stays finite (a query 1e20 away in float32) so padding never outranks it
        d2 = (diff * diff).sum(-1).clamp_max(torch.finfo(q.dtype).max).masked_fill(~ok, torch.inf).flatten(1)
        val, pos = torch.topk(d2, k, dim=1, largest=False, sorted=True)
        dist[rows], idx[rows] = val.sqrt(), cand.flatten(1).gather(1, pos)
        s += step
    return dist, idx
