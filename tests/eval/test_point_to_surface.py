"""Exact point-to-surface distance against oracles written here: hand-computed distances to one
triangle, an all-pairs evaluation by another formulation (projection onto the plane, else the edges),
and concentric icospheres whose facets' planes give the distance."""

import numpy as np
import pytest
import trimesh

from delta.eval.geometry import mesh_distance, point_mesh_distance, point_to_surface
from delta.geometry.closest import closest_point_on_triangles

A, B, C = np.array([0.0, 0, 0]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0])
# (point in the triangle's plane, its closest point on ABC): one per Voronoi region, and on the boundary
REGIONS = {
    "vertex A": ((-1.0, -1.0), (0.0, 0.0)),
    "vertex B": ((2.0, -0.5), (1.0, 0.0)),
    "vertex C": ((-0.5, 2.0), (0.0, 1.0)),
    "edge AB": ((0.3, -0.7), (0.3, 0.0)),
    "edge AC": ((-0.4, 0.6), (0.0, 0.6)),
    "edge BC": ((1.0, 1.0), (0.5, 0.5)),
    "edge BC, near B": ((0.9, 0.4), (0.75, 0.25)),
    "face": ((0.2, 0.3), (0.2, 0.3)),
    "on edge BC": ((0.25, 0.75), (0.25, 0.75)),
    "on vertex B": ((1.0, 0.0), (1.0, 0.0)),
}


def rigid(seed):
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q, rng.normal(size=3)


@pytest.mark.parametrize("height", [0.5, -0.5, 0.0])
@pytest.mark.parametrize("region", list(REGIONS))
def test_one_triangle_every_region_both_sides(region, height):
    (x, y), (cx, cy) = REGIONS[region]
    p = np.array([[x, y, height]])
    expected = np.sqrt((x - cx) ** 2 + (y - cy) ** 2 + height**2)
    tri = np.stack([A, B, C])
    assert point_mesh_distance(p, tri, [[0, 1, 2]])[0] == pytest.approx(expected, abs=1e-12)
    q = closest_point_on_triangles(p, A[None], B[None], C[None])
    np.testing.assert_allclose(q[0], [cx, cy, 0.0], atol=1e-12)
    # the winding and a rigid motion change nothing
    rot, shift = rigid(len(region) + int(10 * height) + 10)
    for order in ([0, 1, 2], [2, 1, 0], [1, 2, 0]):
        d = point_mesh_distance(p @ rot.T + shift, tri @ rot.T + shift, [order])
        assert d[0] == pytest.approx(expected, abs=1e-12)


def oracle(points, vertices, faces):
    """All pairs, no pruning: the projection onto the triangle's plane when its barycentric coordinates
    (least squares on the two edge vectors) are all >= 0, else the nearest of the three segments."""
    best = np.full(len(points), np.inf)
    for a, b, c in vertices[faces]:
        e1, e2 = b - a, c - a
        gram = np.array([[e1 @ e1, e1 @ e2], [e1 @ e2, e2 @ e2]])
        cands = []
        if np.linalg.det(gram) > 1e-14 * (e1 @ e1) * (e2 @ e2):
            uv = np.linalg.solve(gram, np.stack([(points - a) @ e1, (points - a) @ e2]))
            inside = (uv[0] >= 0) & (uv[1] >= 0) & (uv.sum(0) <= 1)
            foot = a + uv[0][:, None] * e1 + uv[1][:, None] * e2
            cands.append(np.where(inside, np.linalg.norm(points - foot, axis=1), np.inf))
        for s, e in ((a, b), (b, c), (c, a)):
            t = np.clip((points - s) @ (e - s) / max((e - s) @ (e - s), 1e-300), 0, 1)
            cands.append(np.linalg.norm(points - (s + t[:, None] * (e - s)), axis=1))
        best = np.minimum(best, np.min(cands, axis=0))
    return best


def test_random_mesh_against_all_pairs():
    rng = np.random.default_rng(3)
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    v = sphere.vertices + rng.normal(scale=0.02, size=sphere.vertices.shape)
    f = sphere.faces
    # triangles of very different sizes (one large, some tiny), two degenerate, and an unused vertex
    extra = np.array([[-2.0, -2, -1.5], [2, -2, -1.5], [0, 2, -1.5],  # large
                      [0.5, 0.5, 0.5], [0.5001, 0.5, 0.5], [0.5, 0.5001, 0.5],  # tiny
                      [0.0, 0, -0.6], [0.1, 0, -0.6], [0.3, 0, -0.6],  # collinear
                      [0.7, -0.7, -0.2], [0.7, -0.7, 0.3],  # a segment: a triangle with a repeated vertex
                      [0.01, 0.01, 0.0]])  # fmt: skip
    n = len(v)
    v = np.concatenate([v, extra])
    f = np.concatenate([f, [[n, n + 1, n + 2], [n + 3, n + 4, n + 5], [n + 6, n + 7, n + 8], [n + 9, n + 9, n + 10]]])
    points = np.concatenate(
        [
            rng.normal(scale=0.4, size=(300, 3)),  # around and inside the blob
            rng.uniform(-3, 3, size=(100, 3)),  # far, above and below the large triangle
            v[:50] + rng.normal(scale=1e-4, size=(50, 3)),  # next to vertices
            trimesh.sample.sample_surface(trimesh.Trimesh(v, f, process=False), 50, seed=1)[0],  # on it
            [[0.01, 0.01, 0.0], [0.7, -0.69, 0.05], [0.2, 0.001, -0.6], [0.50002, 0.50002, 0.7]],
        ]
    )
    expected = oracle(points, v, f)
    got = point_mesh_distance(points, v, f)
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(point_mesh_distance(points, v, f, chunk=7), got, rtol=0, atol=0)
    assert got[-1] == pytest.approx(0.2, abs=1e-9)  # above the tiny triangle
    assert got[-2] == pytest.approx(0.001, abs=1e-12)  # next to the collinear one
    assert got[-3] == pytest.approx(0.01, abs=1e-12)  # next to the one with a repeated vertex


def test_icospheres_one_centimetre_apart():
    inner = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    outer = inner.copy()
    outer.apply_scale(1.01)
    d = point_to_surface(inner, outer, count=20000, seed=0)
    assert d.accuracy == pytest.approx(0.01, abs=5e-4)
    assert d.completeness == pytest.approx(0.01, abs=5e-4)
    assert d.mean == pytest.approx((d.accuracy + d.completeness) / 2)
    # each sample sits on a facet whose copy is 0.01 x (its plane's distance to the centre) away: the flat
    # facets are a little inside the unit sphere
    offset = np.einsum("ij,ij->i", inner.face_normals, inner.triangles[:, 0])
    facets = 0.01 * np.average(offset, weights=inner.area_faces)
    assert facets < 0.01
    assert d.accuracy == pytest.approx(facets, abs=2e-5)
    assert d.completeness == pytest.approx(facets, abs=2e-5)

    same = point_to_surface(inner, inner, count=20000, seed=0)
    assert same.mean < 1e-9 and same.accuracy < 1e-9 and same.completeness < 1e-9
    sampled = mesh_distance(inner, inner, count=20000, seed=0)
    assert sampled.chamfer > 1e-3  # the floor of sample to sample: the samplings' spacing


def test_empty_meshes_are_nan():
    sphere = trimesh.creation.icosphere(subdivisions=1)
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=int))
    for a, b in ((empty, sphere), (sphere, empty), (empty, empty)):
        d = point_to_surface(a, b, count=100)
        assert np.isnan(d.mean) and np.isnan(d.accuracy) and np.isnan(d.completeness)
    assert np.isinf(point_mesh_distance(np.zeros((4, 3)), sphere.vertices, np.zeros((0, 3), dtype=int))).all()
    assert point_mesh_distance(np.zeros((0, 3)), sphere.vertices, sphere.faces).shape == (0,)
