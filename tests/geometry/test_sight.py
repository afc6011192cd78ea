"""What parallel views see of a surface: analytic spheres, one hiding another."""

from __future__ import annotations

import math

import numpy as np
import torch
import trimesh

from delta.cameras.models import OrthographicCamera, PinholeCamera, look_at
from delta.geometry.sight import seen_along, vertex_normals, view_ring, visible_vertices


def test_the_ring_of_views_turns_about_the_up_axis_and_looks_down_by_its_elevation():
    dirs = view_ring(8, (0.0, 30.0)).numpy()
    assert dirs.shape == (16, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0)
    np.testing.assert_allclose(dirs[:8, 1], 0.0, atol=1e-12)
    np.testing.assert_allclose(dirs[8:, 1], -0.5)
    turn = np.degrees(np.arctan2(dirs[:8, 0], dirs[:8, 2]))  # evenly spaced turns, 45 degrees apart
    np.testing.assert_allclose(np.diff(np.unwrap(np.radians(turn))), math.radians(45.0))
    about_z = view_ring(4, (90.0,), up=2).numpy()  # straight down another axis
    np.testing.assert_allclose(about_z, [[0, 0, -1.0]] * 4, atol=1e-12)


def test_a_sphere_seen_along_an_axis_shows_the_half_facing_the_view_less_what_a_nearer_sphere_hides():
    """Looking along -z at a unit sphere, with a sphere of radius 0.4 at z = 3 before it: a point is seen where
    its normal faces the view by more than ``facing`` (z > 0.2) and it lies outside the nearer sphere's disc
    (x² + y² > 0.16); away from both outlines the answer is exact."""
    big = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    small = trimesh.creation.icosphere(subdivisions=3, radius=0.4)
    v = torch.from_numpy(np.concatenate([big.vertices, small.vertices + [0.0, 0.0, 3.0]]))
    f = torch.from_numpy(np.concatenate([big.faces, small.faces + len(big.vertices)]).astype(np.int64))
    centres = big.vertices[big.faces].mean(1)
    normals = np.array(big.face_normals)
    seen = seen_along(torch.from_numpy(centres), torch.from_numpy(normals), v, f, torch.tensor([[0.0, 0, -2.0]]),
                      tol=1e-3, facing=0.2).numpy()  # fmt: skip
    z, rho = normals[:, 2], np.linalg.norm(centres[:, :2], axis=1)
    clear = (np.abs(z - 0.2) > 0.05) & (np.abs(rho - 0.4) > 0.05)
    expected = (z > 0.2) & (rho > 0.4)
    np.testing.assert_array_equal(seen[clear], expected[clear])
    assert expected[clear].sum() > 100 and (~expected[clear] & (z[clear] > 0.2)).sum() > 20  # both cases occur
    # turned all round, every point of the lone sphere is seen (none hides another)
    alone = seen_along(torch.from_numpy(centres), torch.from_numpy(normals), torch.from_numpy(big.vertices),
                       torch.from_numpy(big.faces), view_ring(12, (-60.0, 0.0, 60.0)), tol=1e-3)  # fmt: skip
    assert bool(alone.all())
    # points with no face of the mesh through them: seen where nothing lies before them
    free = torch.tensor([[0.0, 0.0, 5.0], [0.0, 0.0, -2.0]], dtype=torch.float64)
    up = torch.tensor([[0.0, 0.0, 1.0]] * 2, dtype=torch.float64)
    assert seen_along(free, up, v, f, torch.tensor([[0.0, 0, -1.0]]), tol=1e-3).tolist() == [True, False]


def _sphere():
    s = trimesh.creation.icosphere(subdivisions=3)
    return torch.tensor(s.vertices, dtype=torch.float64), torch.tensor(s.faces, dtype=torch.int64)


def test_visible_vertices_of_a_sphere_from_an_orthographic_camera():
    """Seen along -z, a unit sphere shows its z > 0 half (the rim, |z| < 0.1, is left undecided: the
    faceted sphere's outline passes through vertices a little behind the equator)."""
    v, f = _sphere()
    cam = OrthographicCamera(torch.tensor(0.8), torch.zeros(2), 64, 64)
    seen = visible_vertices(v, f, cam).numpy()
    z = v[:, 2].numpy()
    clear = np.abs(z) > 0.1
    np.testing.assert_array_equal(seen[clear], z[clear] > 0)
    # out of the image: nothing is seen
    far = OrthographicCamera(torch.tensor(0.8), torch.tensor([10.0, 0.0]), 64, 64)
    assert not visible_vertices(v, f, far).any()


def test_visible_vertices_of_a_sphere_from_a_pinhole_camera():
    """From a centre 5 m along +z, a unit sphere's visible cap is z > 1/5 (the tangent cone's rim)."""
    v, f = _sphere()
    R, t = look_at(torch.tensor([0.0, 0, 5]), torch.zeros(3), torch.tensor([0.0, 1, 0]))
    K = torch.tensor([[200.0, 0, 64], [0, 200, 64], [0, 0, 1]])
    cam = PinholeCamera(K.double(), R.double(), t.double(), torch.zeros(5, dtype=torch.float64), 128, 128)
    seen = visible_vertices(v, f, cam).numpy()
    z = v[:, 2].numpy()
    clear = np.abs(z - 0.2) > 0.1
    np.testing.assert_array_equal(seen[clear], z[clear] > 0.2)


def test_visible_vertices_turned_towards_the_camera_by_facing():
    """Along -z a unit sphere's vertex normal is its position: with ``facing`` 0.5 only z > 0.5 is seen
    (away from the threshold, where the faceted normals differ from the sphere's)."""
    v, f = _sphere()
    cam = OrthographicCamera(torch.tensor(0.8), torch.zeros(2), 64, 64)
    normals = vertex_normals(v, f).numpy()
    np.testing.assert_allclose(normals, v.numpy(), atol=0.015)  # area-weighted facets: within 1 %
    seen = visible_vertices(v, f, cam, facing=0.5).numpy()
    z = v[:, 2].numpy()
    clear = np.abs(z - 0.5) > 0.02
    np.testing.assert_array_equal(seen[clear], z[clear] > 0.5)
