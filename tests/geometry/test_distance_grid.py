"""The voxel distance field used to cull samples far from the body."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from delta.geometry import distance_grid


def test_distances_match_exact_nearest_neighbours_to_a_cell():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(500, 3)) * [0.3, 0.8, 0.1]
    cell = 0.02
    grid = distance_grid.build(pts, cell, pad=0.2)
    q = rng.uniform(pts.min(0) - 0.15, pts.max(0) + 0.15, size=(2000, 3))
    exact = cKDTree(pts).query(q)[0]
    got = distance_grid.lookup(grid, q)
    # the voxel centre of the query and of each point are each within √3/2 cell of them
    assert np.abs(got - exact).max() <= np.sqrt(3) * cell + 1e-6
    assert np.all(distance_grid.lookup(grid, pts) <= np.sqrt(3) / 2 * cell + 1e-6)


def test_outside_the_grid_is_infinitely_far():
    grid = distance_grid.build(np.zeros((1, 3)), 0.1, pad=0.2)
    d = distance_grid.lookup(grid, np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, -1e9, 0.0]]))
    assert d[0] == 0.0 and np.isinf(d[1]) and np.isinf(d[2])


def test_nearest_index_names_a_point_at_the_voxel_distance():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(400, 3)) * [0.3, 0.8, 0.1]
    cell = 0.02
    grid = distance_grid.build(pts, cell, pad=0.2, nearest=True)
    np.testing.assert_array_equal(grid.distance, distance_grid.build(pts, cell, pad=0.2).distance)
    q = rng.uniform(pts.min(0) - 0.15, pts.max(0) + 0.15, size=(2000, 3))
    dist, who = distance_grid.lookup_nearest(grid, q)
    exact = cKDTree(pts).query(q)[0]
    named = np.linalg.norm(q - pts[who], axis=1)
    # the named point is a nearest one up to the two voxel snaps (√3/2 cell each) ...
    assert np.all(named <= exact + np.sqrt(3) * cell + 1e-9)
    # ... and lies at the grid's distance up to the same slack
    assert np.abs(named - dist).max() <= np.sqrt(3) * cell + 1e-6
    # each point is named in its own voxel when it is alone there
    assert np.unique(np.floor((pts - grid.origin) / cell + 0.5), axis=0, return_counts=True)[1].max() == 1
    np.testing.assert_array_equal(distance_grid.lookup_nearest(grid, pts)[1], np.arange(len(pts)))


def test_nearest_lookup_outside_and_without_the_index():
    grid = distance_grid.build(np.zeros((2, 3)) + [[0, 0, 0], [0.5, 0, 0]], 0.1, pad=0.2, nearest=True)
    dist, who = distance_grid.lookup_nearest(grid, np.array([[0.45, 0.0, 0.0], [9.0, 0.0, 0.0]]))
    assert who.tolist() == [1, -1] and np.isinf(dist[1])
    with pytest.raises(ValueError, match="nearest=True"):
        distance_grid.lookup_nearest(distance_grid.build(np.zeros((1, 3)), 0.1, pad=0.2), np.zeros((1, 3)))
