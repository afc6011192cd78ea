"""The voxel distance field used to cull samples far from the body, built by SciPy's distance transform
(CPU) and by the same transform in torch (any device)."""

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from delta.geometry import distance_grid

METHODS = ["scipy", "torch"]


def _points(seed: int, n: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    return torch.from_numpy(rng.normal(size=(n, 3)) * [0.3, 0.8, 0.1])


def _queries(pts: torch.Tensor, seed: int) -> torch.Tensor:
    p = pts.numpy()
    return torch.from_numpy(np.random.default_rng(seed).uniform(p.min(0) - 0.15, p.max(0) + 0.15, size=(2000, 3)))


@pytest.mark.parametrize("method", METHODS)
def test_distances_match_exact_nearest_neighbours_to_a_cell(method):
    pts = _points(0, 500)
    cell = 0.02
    grid = distance_grid.build(pts, cell, pad=0.2, method=method)
    q = _queries(pts, 10)
    exact = cKDTree(pts.numpy()).query(q.numpy())[0]
    got = distance_grid.lookup(grid, q).numpy()
    # the voxel centre of the query and of each point are each within √3/2 cell of them
    assert np.abs(got - exact).max() <= np.sqrt(3) * cell + 1e-6
    assert np.all(distance_grid.lookup(grid, pts).numpy() <= np.sqrt(3) / 2 * cell + 1e-6)


def test_the_torch_transform_is_scipys():
    pts = _points(2, 3000)
    for cell, pad in ((0.03, 0.2), (0.05, 0.0), (0.021, 0.11)):
        a = distance_grid.build(pts, cell, pad, nearest=True, method="scipy")
        b = distance_grid.build(pts, cell, pad, nearest=True, method="torch")
        assert a.distance.shape == b.distance.shape and torch.equal(a.origin, b.origin)
        torch.testing.assert_close(b.distance, a.distance, rtol=1e-6, atol=0)
        # the named points may differ only between equally near occupied voxels
        centres = a.origin + cell * torch.stack(torch.meshgrid(*[torch.arange(n) for n in a.distance.shape],
                                                                indexing="ij"), -1).double()  # fmt: skip
        snap = lambda who: a.origin + cell * torch.floor((pts[who] - a.origin) / cell + 0.5)  # noqa: E731
        da, db = ((centres - snap(w)).norm(dim=-1) for w in (a.nearest, b.nearest))
        torch.testing.assert_close(db, da, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("method", METHODS)
def test_outside_the_grid_is_infinitely_far(method):
    grid = distance_grid.build(torch.zeros((1, 3)), 0.1, pad=0.2, method=method)
    d = distance_grid.lookup(grid, torch.tensor([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, -1e9, 0.0]]))
    assert d[0] == 0.0 and torch.isinf(d[1]) and torch.isinf(d[2])


@pytest.mark.parametrize("method", METHODS)
def test_nearest_index_names_a_point_at_the_voxel_distance(method):
    pts = _points(1, 400)
    cell = 0.02
    grid = distance_grid.build(pts, cell, pad=0.2, nearest=True, method=method)
    assert torch.equal(grid.distance, distance_grid.build(pts, cell, pad=0.2, method=method).distance)
    q = _queries(pts, 11)
    dist, who = distance_grid.lookup_nearest(grid, q)
    exact = cKDTree(pts.numpy()).query(q.numpy())[0]
    named = np.linalg.norm(q.numpy() - pts.numpy()[who.numpy()], axis=1)
    # the named point is a nearest one up to the two voxel snaps (√3/2 cell each) ...
    assert np.all(named <= exact + np.sqrt(3) * cell + 1e-9)
    # ... and lies at the grid's distance up to the same slack
    assert np.abs(named - dist.numpy()).max() <= np.sqrt(3) * cell + 1e-6
    # each point is named in its own voxel when it is alone there
    snapped = np.floor((pts.numpy() - grid.origin.numpy()) / cell + 0.5)
    assert np.unique(snapped, axis=0, return_counts=True)[1].max() == 1
    assert torch.equal(distance_grid.lookup_nearest(grid, pts)[1], torch.arange(len(pts)))


@pytest.mark.parametrize("method", METHODS)
def test_nearest_lookup_outside_and_without_the_index(method):
    pts = torch.tensor([[0.0, 0, 0], [0.5, 0, 0]])
    grid = distance_grid.build(pts, 0.1, pad=0.2, nearest=True, method=method)
    dist, who = distance_grid.lookup_nearest(grid, torch.tensor([[0.45, 0.0, 0.0], [9.0, 0.0, 0.0]]))
    assert who.tolist() == [1, -1] and torch.isinf(dist[1])
    with pytest.raises(ValueError, match="nearest=True"):
        distance_grid.lookup_nearest(distance_grid.build(torch.zeros((1, 3)), 0.1, pad=0.2), torch.zeros((1, 3)))
    with pytest.raises(ValueError, match="unknown method"):
        distance_grid.build(pts, 0.1, pad=0.2, method="octree")
