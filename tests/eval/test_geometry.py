"""Geometry scores against analytic surfaces."""

import numpy as np
import pytest
import trimesh

from delta.eval.geometry import mesh_distance, vertex_error


def plane(z, size=1.0, n=20):
    xs = np.linspace(-size / 2, size / 2, n)
    xx, yy = np.meshgrid(xs, xs)
    v = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)], 1)
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            f += [[a, a + 1, a + n], [a + 1, a + n + 1, a + n]]
    return trimesh.Trimesh(v, np.array(f), process=False)


def test_parallel_planes_are_their_gap_apart():
    d = mesh_distance(plane(0.0), plane(0.03), count=20000)
    # every point's nearest neighbour is (nearly) straight across: the gap, plus the sampling's spacing
    assert d.accuracy == pytest.approx(0.03, abs=0.003)
    assert d.completeness == pytest.approx(0.03, abs=0.003)
    assert d.normal_consistency == pytest.approx(1.0, abs=1e-9)


def test_concentric_spheres_and_normals():
    inner = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    outer = trimesh.creation.icosphere(subdivisions=4, radius=0.52)
    d = mesh_distance(inner, outer, count=30000)
    assert d.chamfer == pytest.approx(0.02, abs=0.003)
    assert d.normal_consistency > 0.99
    same = mesh_distance(inner, inner, count=30000)
    assert same.chamfer < 0.007  # two independent samplings (~1 cm apart) of one surface


def test_perpendicular_normals_score_zero():
    a = plane(0.0)
    b = a.copy()
    b.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    b.apply_translation([0, 0, 5.0])  # far away: each point's neighbour has a perpendicular normal
    assert mesh_distance(a, b, count=2000).normal_consistency == pytest.approx(0.0, abs=1e-9)


def test_vertex_error_alignment():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(100, 3))
    moved = v + np.array([0.1, -0.2, 0.3])
    assert vertex_error(moved, v, "none") == pytest.approx(np.linalg.norm([0.1, -0.2, 0.3]))
    assert vertex_error(moved, v) == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="topologies"):
        vertex_error(v[:10], v)
