"""A wide bounding-box hierarchy built from tensors: the acceleration structure of the torch ray caster
and nearest-point search, so that both run on whatever device holds the geometry.

Primitives (points, or triangles by their bounds) are sorted along a Morton curve of their centres and
cut into leaves of ``leaf`` consecutive primitives; leaves are grouped ``fanout`` at a time into nodes,
nodes into larger nodes, until one level has at most ``fanout`` nodes. Every node keeps its axis-aligned
box. Building is a sort and a few reductions (no Python loop over primitives), cheap enough to rebuild
for every posed mesh. Queries walk the levels breadth-first as lists of (query, node) pairs, which is
batched tensor work on a CPU and on a GPU alike.

Shapes: P primitives, D dimensions (2 or 3), L leaves, S = ``leaf``.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import torch

from delta.devices import host_paths

LEAF = 32
"""Primitives per leaf."""
FANOUT = 16
"""Children per inner node."""
FLAT_PAIRS = 1 << 24
"""(query, leaf) tests a flat search makes at once: on a GPU every query is tested against every leaf
(:func:`descend`), chunked to this many (boxes broadcast, so 0.2 GB of 3-D differences a chunk)."""


@dataclasses.dataclass
class Hierarchy:
    members: torch.Tensor
    """(L, S) int64 primitive index of each leaf slot, -1 for padding."""
    levels: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
    """Per level, top first: (lo (N, D), hi (N, D), children (N, FANOUT) int64 node index in the level
    below, -1 for padding); the level below the last is the leaves. The top level is tested whole."""
    leaf_lo: torch.Tensor
    """(L, D) leaf boxes."""
    leaf_hi: torch.Tensor


def morton_codes(centres: torch.Tensor) -> torch.Tensor:
    """(P,) int64 Morton codes of points (P, D) quantised in their bounding box (63 // D bits an axis)."""
    P, D = centres.shape
    bits = min(21, 63 // D)
    lo, hi = centres.amin(0), centres.amax(0)
    q = ((centres - lo) / (hi - lo).clamp_min(torch.finfo(centres.dtype).tiny) * ((1 << bits) - 1)).round()
    q = q.clamp(0, (1 << bits) - 1).to(torch.int64)
    b = torch.arange(bits, device=centres.device)
    bit = (q[:, :, None] >> b) & 1  # (P, D, bits)
    place = b * D + torch.arange(D, device=centres.device)[:, None]  # (D, bits): bit b of axis a
    return (bit << place).sum((1, 2))


def _group(lo: torch.Tensor, hi: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Consecutive items (N, D) grouped ``size`` at a time: (group lo, group hi, (G, size) item index, -1 pad)."""
    N, D = lo.shape
    G = -(-N // size)
    index = torch.arange(G * size, device=lo.device)
    index = torch.where(index < N, index, -1).view(G, size)
    pad = index < 0
    glo = lo[index.clamp_min(0)].masked_fill(pad[..., None], torch.inf).amin(1)
    ghi = hi[index.clamp_min(0)].masked_fill(pad[..., None], -torch.inf).amax(1)
    return glo, ghi, index


def build(lo: torch.Tensor, hi: torch.Tensor, leaf: int = LEAF, fanout: int = FANOUT,
          levels: bool | None = None) -> Hierarchy:  # fmt: skip
    """The hierarchy over primitives with boxes lo, hi (P, D), P >= 1 (a point: lo = hi). ``levels``
    (default: where queries walk them, on the host's paths) False: the leaves alone, for flat searches."""
    if lo.shape[0] == 0:
        raise ValueError("a hierarchy needs at least one primitive")
    order = torch.argsort(morton_codes((lo + hi) / 2))
    leaf_lo, leaf_hi, slots = _group(lo[order], hi[order], leaf)
    members = torch.where(slots >= 0, order[slots.clamp_min(0)], -1)
    above = []
    node_lo, node_hi = leaf_lo, leaf_hi
    levels = host_paths(lo.device) if levels is None else levels
    while levels and node_lo.shape[0] > fanout:
        node_lo, node_hi, children = _group(node_lo, node_hi, fanout)
        above.insert(0, (node_lo, node_hi, children))
    return Hierarchy(members, above, leaf_lo, leaf_hi)


def _ray_boxes(o, inv, zero, lo, hi) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab test of rays (M, 3) against boxes (M, 3) pairwise: (M,) entry and exit t (exit < entry: miss).

    ``inv`` = 1 / dir, ``zero`` = dir == 0 (such an axis is a slab the ray is in everywhere or nowhere)."""
    inside = (o >= lo) & (o <= hi)
    t0 = torch.where(zero, torch.where(inside, -torch.inf, torch.inf), (lo - o) * inv)
    t1 = torch.where(zero, torch.where(inside, torch.inf, -torch.inf), (hi - o) * inv)
    return torch.minimum(t0, t1).amax(-1), torch.maximum(t0, t1).amin(-1)


def descend(
    h: Hierarchy, n: int, test: Callable, flat: bool | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(query, leaf) pairs whose boxes pass ``test`` at every level, walking down from the top.

    ``test(query, lo, hi)`` takes query indices and their nodes' boxes, broadcastable ((M,) and (M, D), or
    (n, 1) and (1, L, D)), and returns a bool (kept) and a value of the broadcast shape. Returns (M,) query
    and leaf indices, grouped by query in ascending order (a query's leaves ascending), and the value of
    each pair's leaf.

    ``flat`` (default: off the host's paths, :func:`delta.devices.host_paths`: on a GPU) tests every leaf
    against every query instead of walking the levels: more arithmetic, but a fixed few operations, where
    the walk compacts its pairs at every level and a GPU waits for each. A test that passes a leaf passes
    every node above it (their boxes hold the leaf's), so both list the same pairs in the same order."""
    dev = h.leaf_lo.device
    if flat if flat is not None else not host_paths(dev):
        return _flat(h, n, test)
    top_lo, top_hi = h.levels[0][:2] if h.levels else (h.leaf_lo, h.leaf_hi)
    N = top_lo.shape[0]
    query = torch.arange(n, device=dev).repeat_interleave(N)
    node = torch.arange(N, device=dev).repeat(n)
    ok, value = test(query, top_lo[node], top_hi[node])
    query, node, value = query[ok], node[ok], value[ok]
    for depth, (_, _, children) in enumerate(h.levels):
        below_lo, below_hi = h.levels[depth + 1][:2] if depth + 1 < len(h.levels) else (h.leaf_lo, h.leaf_hi)
        child = children[node]  # (M, FANOUT)
        query = query[:, None].expand_as(child)[child >= 0]
        node = child[child >= 0]
        ok, value = test(query, below_lo[node], below_hi[node])
        query, node, value = query[ok], node[ok], value[ok]
    return query, node, value


def _flat(h: Hierarchy, n: int, test: Callable) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`descend`'s pairs from every query tested against every leaf, ``FLAT_PAIRS`` tests at a time."""
    L, dev = h.leaf_lo.shape[0], h.leaf_lo.device
    step = max(1, FLAT_PAIRS // L)
    out = []
    for s in range(0, max(n, 1), step):  # no query: one empty chunk, so the value keeps the test's dtype
        query = torch.arange(s, min(n, s + step), device=dev)[:, None]
        ok, value = test(query, h.leaf_lo[None], h.leaf_hi[None])  # (m, L)
        who, leaf = ok.nonzero(as_tuple=True)
        out.append((who + s, leaf, value[who, leaf]))
    if len(out) == 1:
        return out[0]
    return tuple(torch.cat(x) for x in zip(*out))  # type: ignore[return-value]


def ray_leaf_pairs(h: Hierarchy, origins: torch.Tensor, dirs: torch.Tensor, pad: float,
                   flat: bool | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # fmt: skip
    """(ray, leaf) pairs whose leaf box, grown by ``pad`` on every side, the ray (t >= 0) may pass through.

    Conservative: every leaf holding a primitive the ray meets at t >= 0 is listed (boxes grown by ``pad``
    absorb the rounding of the slab test). Returns (M,) ray and leaf indices and (M,) the t at which the
    ray enters the grown box (0 when it starts inside): no primitive of the leaf is met before it."""
    zero = dirs == 0
    inv = 1.0 / torch.where(zero, torch.ones_like(dirs), dirs)

    def enter(ray, lo, hi):
        near, far = _ray_boxes(origins[ray], inv[ray], zero[ray], lo - pad, hi + pad)
        near = near.clamp_min(0)
        return far >= near, near

    return descend(h, origins.shape[0], enter, flat)


def near_leaf_pairs(h: Hierarchy, points: torch.Tensor, reach: torch.Tensor,
                    flat: bool | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # fmt: skip
    """(point, leaf) pairs whose leaf box lies within ``reach`` (N,) of the point (N, D), and the (M,)
    distance from the point to the box."""

    def close(i, lo, hi):
        gap = torch.maximum(lo - points[i], points[i] - hi).clamp_min(0).norm(dim=-1)
        return gap <= reach[i], gap

    return descend(h, points.shape[0], close, flat)


def group_rank(group: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """For items (M,) labelled by ``group`` in ascending runs (as :func:`descend` returns them): each
    group's size (n,) and each item's place within its group (M,)."""
    count = torch.bincount(group, minlength=n)
    return count, torch.arange(len(group), device=group.device) - (torch.cumsum(count, 0) - count)[group]
