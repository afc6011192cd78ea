"""Nearest-point search: the tensor search over the box hierarchy against SciPy's KD-tree."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from delta.geometry import clusters, nearest
from delta.geometry.nearest import PointIndex

D = torch.float64


def _cloud(n: int, dim: int, seed: int) -> torch.Tensor:
    """A surface-like cloud: points on a few curved sheets, denser in places, as a posed body is."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, dim, generator=g, dtype=D)
    x = x / x.norm(dim=1, keepdim=True) * (0.3 + 0.5 * (torch.arange(n) % 3)[:, None])
    return x * torch.tensor([0.4, 1.0, 0.2][:dim], dtype=D) + 0.003 * torch.randn(n, dim, generator=g, dtype=D)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("k", [1, 6, 16])
def test_tensor_search_matches_the_kdtree(dim, k):
    pts = _cloud(3000, dim, dim)
    g = torch.Generator().manual_seed(k)
    near = pts[torch.randint(len(pts), (1500,), generator=g)] + 0.05 * torch.randn(1500, dim, generator=g, dtype=D)
    far = 3 * torch.randn(300, dim, generator=g, dtype=D)  # metres from the cloud
    q = torch.cat([near, far, pts[:50]])  # and queries exactly on points
    want_d, want_i = cKDTree(pts.numpy()).query(q.numpy(), k=k)
    got_d, got_i = PointIndex(pts, "torch").query(q, k)
    np.testing.assert_allclose(got_d.numpy(), np.asarray(want_d).reshape(len(q), k), rtol=1e-12, atol=1e-15)
    assert torch.equal(got_i, torch.from_numpy(np.asarray(want_i).reshape(len(q), k)))
    kd_d, kd_i = PointIndex(pts, "kdtree").query(q, k)
    assert torch.equal(kd_i, got_i) and kd_d.dtype == D


def test_float32_points_and_queries_far_out():
    pts = _cloud(800, 3, 5).float()
    q = torch.tensor([[1e18, 0, 0], [0, -1e17, 3e17], [0.1, 0.2, 0.0]])
    dist, idx = PointIndex(pts, "torch").query(q, 6)
    want = torch.cdist(q.double(), pts.double()).topk(6, largest=False).values
    assert float((dist.double() / want - 1).abs().max()) < 1e-6
    # squares beyond float32's range: real indices (never the padding's -1), finite distances
    dist, idx = PointIndex(pts, "torch").query(torch.tensor([[1e20, 0, 0], [0, -3e25, 1e30]]), 6)
    assert bool((idx >= 0).all()) and bool((idx < len(pts)).all()) and bool(torch.isfinite(dist).all())


def test_fewer_points_than_k_and_one_point():
    pts = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0, 2.0, 0]], dtype=D)
    for backend in ("torch", "kdtree"):
        dist, idx = PointIndex(pts, backend).query(torch.tensor([[0.9, 0, 0]], dtype=D), 6)
        assert idx.tolist() == [[1, 0, 2]]
        torch.testing.assert_close(dist, torch.tensor([[0.1, 0.9, (0.81 + 4) ** 0.5]], dtype=D))
        dist, idx = PointIndex(pts[:1], backend).query(torch.zeros(4, 3, dtype=D), 2)
        assert idx.shape == (4, 1) and bool((dist == 0).all())
        empty = PointIndex(pts, backend).query(torch.zeros(0, 3, dtype=D), 2)
        assert empty[0].shape == (0, 2) and empty[1].shape == (0, 2)


def test_bad_construction_is_refused():
    with pytest.raises(ValueError, match="at least one point"):
        PointIndex(torch.zeros(0, 3))
    with pytest.raises(ValueError, match="unknown backend"):
        PointIndex(torch.zeros(2, 3), "faiss")


def test_large_queries_use_the_jobs_threads_and_agree_with_one_thread(monkeypatch):
    pts = _cloud(500, 3, 9)
    x = torch.randn(3000, 3, generator=torch.Generator().manual_seed(4), dtype=D)
    index = PointIndex(pts, "kdtree")
    monkeypatch.setattr(nearest, "PARALLEL_QUERY", len(x) + 1)  # one thread
    one = index.query(x, 6)
    monkeypatch.setattr(nearest, "PARALLEL_QUERY", 100)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        two = index.query(x, 6)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one[0], two[0]) and torch.equal(one[1], two[1])


def test_hierarchy_holds_every_primitive_once_inside_its_boxes():
    pts = _cloud(5000, 3, 2)
    tree = clusters.build(pts, pts, leaf=8, fanout=4)
    members = tree.members[tree.members >= 0]
    assert torch.equal(members.sort().values, torch.arange(len(pts)))
    inside = (pts[tree.members.clamp_min(0)] >= tree.leaf_lo[:, None]) & (
        pts[tree.members.clamp_min(0)] <= tree.leaf_hi[:, None]
    )
    assert bool(inside.all(-1)[tree.members >= 0].all())
    below_lo, below_hi = tree.leaf_lo, tree.leaf_hi
    for lo, hi, children in reversed(tree.levels):  # every child box lies in its parent's
        real = children >= 0
        c = children.clamp_min(0)
        assert bool(((below_lo[c] >= lo[:, None]) & (below_hi[c] <= hi[:, None])).all(-1)[real].all())
        assert torch.equal(children[real].sort().values, torch.arange(len(below_lo)))
        below_lo, below_hi = lo, hi
    assert len(tree.levels) >= 2 and tree.levels[0][0].shape[0] <= 4


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_flat_search_lists_the_walks_pairs_in_its_order(monkeypatch, dtype):
    """A GPU tests every leaf at once (clusters.descend's flat search); the pairs, their order and values must
    be the walk's, also across chunks of queries (a chunk here is a few queries) and for rays."""
    pts = _cloud(4000, 3, 5).to(dtype)
    tree = clusters.build(pts, pts, leaf=16, fanout=4)
    g = torch.Generator().manual_seed(1)
    q = (pts[torch.randint(len(pts), (700,), generator=g)] + 0.05 * torch.randn(700, 3, generator=g, dtype=D)).to(dtype)
    reach = (0.2 * torch.rand(700, generator=g, dtype=D)).to(dtype)
    reach[:5] = 0.0  # queries that reach no leaf
    dirs = torch.nn.functional.normalize(torch.randn(700, 3, generator=g, dtype=D), dim=1).to(dtype)
    dirs[:20, 1:] = 0.0  # axis-aligned rays: slabs they lie in
    monkeypatch.setattr(clusters, "FLAT_PAIRS", 7 * tree.leaf_lo.shape[0] + 3)
    for walk, flat in [
        (clusters.near_leaf_pairs(tree, q, reach, flat=False), clusters.near_leaf_pairs(tree, q, reach, flat=True)),
        (clusters.ray_leaf_pairs(tree, 2 * q, dirs, 1e-6, flat=False),
         clusters.ray_leaf_pairs(tree, 2 * q, dirs, 1e-6, flat=True)),
    ]:  # fmt: skip
        assert len(walk[0]) > 1000 and torch.equal(walk[0], flat[0]) and torch.equal(walk[1], flat[1])
        assert torch.equal(walk[2], flat[2])
    none = q[:0], reach[:0]  # no query at all: empty lists of the walk's dtypes
    for a, b in zip(
        clusters.near_leaf_pairs(tree, *none, flat=False), clusters.near_leaf_pairs(tree, *none, flat=True)
    ):
        assert a.shape == b.shape == (0,) and a.dtype == b.dtype
    leaves = clusters.build(pts, pts, leaf=16, fanout=4, levels=False)  # as a GPU builds it
    assert leaves.levels == [] and torch.equal(leaves.members, tree.members)
    for flat in (False, True):
        got = clusters.near_leaf_pairs(leaves, q, reach, flat=flat)
        assert all(torch.equal(a, b) for a, b in zip(got, clusters.near_leaf_pairs(tree, q, reach, flat=False)))


def test_the_flat_search_finds_the_kdtrees_neighbours(monkeypatch):
    pts = _cloud(3000, 3, 7)
    g = torch.Generator().manual_seed(2)
    q = torch.cat([pts[torch.randint(len(pts), (900,), generator=g)] + 0.05 * torch.randn(900, 3, generator=g, dtype=D),
                   3 * torch.randn(100, 3, generator=g, dtype=D)])  # fmt: skip
    walk = clusters.descend
    monkeypatch.setattr(clusters, "descend", lambda h, n, test, flat=None: walk(h, n, test, True))
    got_d, got_i = PointIndex(pts, "torch").query(q, 6)
    want_d, want_i = cKDTree(pts.numpy()).query(q.numpy(), k=6)
    np.testing.assert_allclose(got_d.numpy(), want_d, rtol=1e-12, atol=1e-15)
    assert torch.equal(got_i, torch.from_numpy(want_i))
