"""The voxel distance field used to cull samples far from the body."""

import numpy as np
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
