"""Mirror planes through a body and the grid that reads points at their mirror image."""

from __future__ import annotations

import math

import numpy as np
import torch
import trimesh

from delta.geometry.mirror import MirrorGrid, through_planes


def _box(lo, hi):
    b = trimesh.creation.box(bounds=[lo, hi])
    return torch.tensor(b.vertices, dtype=torch.float64), torch.tensor(b.faces, dtype=torch.int64)


def test_the_plane_through_a_box_is_where_the_line_enters_plus_where_it_leaves():
    v, f = _box([0, 0, 2], [1, 1, 5])
    pts = torch.tensor([[0.5, 0.5, 0.0], [0.3, 0.7, 1.5], [0.5, 0.5, 3.0], [2.0, 0.5, 0.0], [0.5, 0.5, 7.0]],
                       dtype=torch.float64)  # fmt: skip
    got = through_planes(pts, v, f, 2, 1.0).numpy()
    np.testing.assert_allclose(got[:2], [7.0, 7.0], atol=1e-5)  # enters at 2, leaves at 5
    assert np.isnan(got[2]) and np.isnan(got[3]) and np.isnan(got[4])  # inside; beside it; past it
    back = through_planes(pts[4:], v, f, 2, -1.0).numpy()  # from beyond the front, looking back
    np.testing.assert_allclose(back, [7.0], atol=1e-5)
    # the mirror keeps the distance from the surface: 2 behind the back (z = 0) goes 2 before the front (z = 7)
    assert abs((got[0] - 0.0) - 7.0) < 1e-5


def test_a_sphere_mirrors_through_its_centre_plane():
    s = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    v, f = torch.tensor(s.vertices), torch.tensor(s.faces)
    pts = torch.tensor([[0.3, 0.2, -2.0], [-0.5, 0.1, -1.5], [0.0, 0.0, -3.0]], dtype=torch.float64)
    np.testing.assert_allclose(through_planes(pts, v, f, 2, 1.0).numpy(), 0.0, atol=2e-3)


def test_the_grid_flips_points_in_cells_with_a_plane_and_leaves_the_rest():
    planes = torch.full((2, 2, 2), float("nan"))
    planes[0, :, :] = 1.0  # x in [0, 1): mirrored about z = 0.5
    grid = MirrorGrid(torch.zeros(3), 1.0, planes)
    x = torch.tensor([[0.5, 0.5, 0.2], [1.5, 0.5, 0.2], [0.5, 0.5, 5.0], [-0.5, 0.5, 0.2]], requires_grad=True)
    out = grid(x)
    torch.testing.assert_close(out.detach(), torch.tensor([[0.5, 0.5, 0.8], [1.5, 0.5, 0.2], [0.5, 0.5, 5.0],
                                                           [-0.5, 0.5, 0.2]]))  # fmt: skip
    out[:, 2].sum().backward()
    torch.testing.assert_close(x.grad[:, 2], torch.tensor([-1.0, 1.0, 1.0, 1.0]))  # a flip reverses the axis
    nothing = MirrorGrid(torch.zeros(3), 1.0, torch.full((2, 2, 2), math.nan))
    assert nothing(x) is x
