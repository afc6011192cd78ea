"""The k nearest of a fixed point set, on the device that holds the points.

On the CPU a SciPy KD-tree answers (float64). On any other device the search is tensor work over a box
hierarchy of the points (:mod:`delta.geometry.clusters`): a query's distances to a few groups of k probe
points bound its k-th nearest distance from above, the walk lists the leaves whose boxes lie within that
bound, those leaves' first points tighten it, the leaves left are searched exhaustively and the k
smallest are kept. Exact in the points' precision; no gradient (callers recompute
differentiable distances from the indices).

Shapes: V points, N queries, D dimensions (2 or 3).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from delta.devices import host_paths
from delta.geometry import clusters

PARALLEL_QUERY = 1024
"""KD-tree queries of at least this many points use the job's threads (fewer: one thread). On two cores two
threads answer 2048-30 000 queries 1.3-1.9x sooner (110k points, k = 6; 55k 2-D points, k = 16: a training
step's kNN and silhouette candidates); tight's 8192-ray stage-1 step 0.57 -> 0.50-0.52 s
(``benchmarks/step_profile_tight_cpu.csv``)."""
POINT_LEAF = 128
"""Points per leaf of the tensor search's hierarchy: of 16-128, 128 was fastest for a step's searches on a
GPU (`benchmarks/device_geometry.csv`), where the walk's launches cost more than the extra distances."""
_CHUNK = 1 << 22
"""Query-leaf (and query-point) distances held at once by the tensor search on the CPU; other devices hold
:data:`DEVICE_CHUNKS` times as many (0.4 GB at most): there each chunk is a round of kernel launches and
waits, and a training step's 50k queries fit one."""
DEVICE_CHUNKS = 8


def _chunk(device: torch.device) -> int:
    return _CHUNK if host_paths(device) else _CHUNK * DEVICE_CHUNKS


class PointIndex:
    """Nearest-point queries against ``points`` (V, D), V >= 1, answered on the points' device."""

    def __init__(self, points: torch.Tensor, backend: str = "auto", leaf: int = POINT_LEAF):
        if points.shape[0] == 0:
            raise ValueError("a point index needs at least one point")
        if backend == "auto":
            backend = "kdtree" if host_paths(points.device) else "torch"
        if backend not in ("kdtree", "torch"):
            raise ValueError(f"unknown backend {backend!r}; expected 'auto', 'kdtree' or 'torch'")
        self.points = points.detach()
        self.backend = backend
        if backend == "kdtree":
            # a tree rebuilt every step: SciPy's sliding-midpoint build without balancing or node
            # compaction takes half the time (110k points: 28 -> 13 ms) and answers as fast
            pts = self.points.cpu().numpy().astype(np.float64)
            self.tree = cKDTree(pts, balanced_tree=False, compact_nodes=False)
        else:
            self.tree = clusters.build(self.points, self.points, leaf=leaf)

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
        if len(q) == 0:
            empty = q.new_zeros((0, k), device=queries.device)
            return empty, empty.long()
        probes = _probes(self.tree, k)
        step = max(1, _chunk(q.device) // self.tree.members.shape[0])
        out = [_search(self.points, self.tree, probes, q[s : s + step], k) for s in range(0, len(q), step)]
        return tuple(torch.cat(x).to(queries.device) for x in zip(*out))


GROUPS = 128
"""Groups of consecutive points (along the hierarchy's curve) whose first k points bound a query's k-th
nearest distance from above."""


def _probes(tree: clusters.Hierarchy, k: int) -> torch.Tensor:
    """(G, k) point indices: the first k points of G groups of consecutive points (G = 0: too few points)."""
    order = tree.members[tree.members >= 0]
    G = min(GROUPS, len(order) // k)
    if G == 0:
        return order.new_zeros((0, k))
    starts = torch.arange(G, device=order.device) * (len(order) // G)
    return order[starts[:, None] + torch.arange(k, device=order.device)]


def _packed(who: torch.Tensor, value: torch.Tensor, n: int, fill) -> torch.Tensor:
    """(n, width) table of each query's values packed to the left, ``fill`` after them; ``who`` (M,) groups
    the values by query in ascending order."""
    count, col = clusters.group_rank(who, n)
    table = torch.full((n, max(int(count.max()), 1) if n else 1), fill, dtype=value.dtype, device=who.device)
    table[who, col] = value
    return table


def _search(points: torch.Tensor, tree: clusters.Hierarchy, probes: torch.Tensor, q: torch.Tensor, k: int):
    """The k nearest of points for queries q (n, D) over the leaves of ``tree``: (n, k) distances, indices.

    A query's k-th nearest distance is at most the distance to the farthest of any group's k ``probes``
    (:func:`_probes`); every leaf whose box lies within that bound is searched (found by walking the
    hierarchy)."""
    n = len(q)
    bound = torch.full((n,), torch.inf, dtype=q.dtype, device=q.device)
    if len(probes):
        # differences, not cdist: its exact mode is slow on a GPU, its matmul mode may round below the truth
        d = (q[:, None, None] - points[probes]).norm(dim=-1)  # (n, G, k)
        bound = d.amax(-1).amin(-1)
    slack = 4 * torch.finfo(q.dtype).eps * (q.abs().amax() + points.abs().amax() + bound.clamp_max(1e30))
    who, leaf, gap = clusters.near_leaf_pairs(tree, q, bound + slack)
    members = tree.members
    if members.shape[0] >= k:  # tighter: the k-th nearest of the listed leaves' first points
        rep = (points[members[leaf, 0]] - q[who]).norm(dim=-1)
        reps = _packed(who, rep, n, torch.inf)
        if reps.shape[1] >= k:
            bound = torch.minimum(bound, reps.kthvalue(k, dim=1).values)
        keep = gap <= (bound + slack)[who]
        who, leaf = who[keep], leaf[keep]
    table = _packed(who, leaf, n, -1)
    # queries taken in order of how many leaves they search, each batch as wide as its widest query
    count = (table >= 0).sum(1)
    by_count = torch.argsort(count)
    widths = count[by_count].cpu().numpy()
    dist = torch.empty((n, k), dtype=q.dtype, device=q.device)
    idx = torch.empty((n, k), dtype=torch.int64, device=q.device)
    s, per_batch = 0, _chunk(q.device) // members.shape[1]
    while s < n:
        cost = np.arange(1, n - s + 1) * np.maximum(widths[s:], 1)
        rows = by_count[s : s + max(1, int(np.searchsorted(cost, per_batch, side="right")))]
        w = max(int(widths[s + len(rows) - 1]), 1)
        slots = table[rows, :w]
        cand = torch.where(slots[..., None] >= 0, members[slots.clamp_min(0)], -1)  # (m, w, S)
        diff = points[cand.clamp_min(0)] - q[rows, None, None]
        # a real distance stays finite (a query 1e20 away in float32) so padding never outranks it
        d2 = (diff * diff).sum(-1).clamp_max(torch.finfo(q.dtype).max).masked_fill(cand < 0, torch.inf).flatten(1)
        val, pos = torch.topk(d2, k, dim=1, largest=False, sorted=True)
        dist[rows], idx[rows] = val.sqrt(), cand.flatten(1).gather(1, pos)
        s += len(rows)
    return dist, idx
