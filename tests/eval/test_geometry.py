"""Geometry scores against analytic surfaces."""

import numpy as np
import pytest
import torch
import trimesh

from delta.cameras.models import OrthographicCamera
from delta.eval.geometry import mesh_distance, similarity_transform, vertex_error, vertex_errors


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


def test_similarity_alignment_leaves_out_size_and_orientation_only():
    """Umeyama: a scaled, turned and moved copy aligns exactly; a shape error survives it, and the
    aligned copy is closer (least squares) than the centroid-aligned one, never farther."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    v = rng.normal(size=(200, 3))
    rot = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    copy = 1.17 * v @ rot.T + np.array([0.4, 1.0, -2.0])
    assert vertex_error(copy, v, "similarity") == pytest.approx(0.0, abs=1e-10)
    assert vertex_error(copy, v, "centroid") > 0.1
    bent = copy.copy()
    bent[:50] += rng.normal(scale=0.05, size=(50, 3))  # a part of the shape is wrong
    rms = lambda a: float(np.sqrt((vertex_errors(bent, v, a) ** 2).mean()))  # noqa: E731
    assert 0.005 < rms("similarity") < rms("centroid")
    # a mirror image is not a rotation: no reflection is taken
    mirror = v * np.array([-1.0, 1.0, 1.0])
    assert vertex_error(mirror, v, "similarity") > 0.1
    with pytest.raises(ValueError, match="similarity"):
        vertex_error(v, v, "affine")


def test_similarity_transform_is_the_one_that_made_the_copy():
    """The transform itself (what carries other points, say a garment, along with a body): a known scale,
    rotation and shift are recovered, and carry points that took no part in the fit to their copies."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(2)
    v, extra = rng.normal(size=(100, 3)), rng.normal(size=(7, 3))
    rot = Rotation.from_rotvec([-0.7, 0.1, 1.1]).as_matrix()
    move = lambda x: 0.83 * x @ rot.T + np.array([1.5, -0.2, 0.3])  # noqa: E731
    scale, r, shift = similarity_transform(v, move(v))
    assert scale == pytest.approx(0.83, rel=1e-12)
    np.testing.assert_allclose(r, rot, atol=1e-12)
    np.testing.assert_allclose(scale * extra @ r.T + shift, move(extra), atol=1e-12)
    scale, r, shift = similarity_transform(v, v)
    assert scale == pytest.approx(1.0) and np.allclose(r, np.eye(3)) and np.allclose(shift, 0.0)


def _sphere():
    s = trimesh.creation.icosphere(subdivisions=3)
    return torch.tensor(s.vertices, dtype=torch.float64), torch.tensor(s.faces, dtype=torch.int64)


def test_vertex_errors_of_a_subset_keep_the_whole_alignment():
    v, _ = _sphere()
    ref = v.numpy()
    pred = ref.copy()
    pred[ref[:, 2] > 0] += [0.0, 0.0, 0.01]  # the front half 1 cm forward
    e = vertex_errors(pred, ref)
    front = ref[:, 2] > 0
    shift = front.mean() * 0.01  # the centroid alignment moves everything back by this much
    np.testing.assert_allclose(e[front], 0.01 - shift, atol=1e-12)
    np.testing.assert_allclose(e[~front], shift, atol=1e-12)
    assert vertex_error(pred, ref) == pytest.approx(e.mean())


def test_body_error_apart_over_what_the_view_sees():
    """A cap of a sphere facing the camera 1 cm off: the error sits on the part the camera sees."""
    from types import SimpleNamespace

    from delta.eval.evaluate import body_errors

    v, f = _sphere()
    ref = v.numpy()
    pred = ref.copy()
    cap = ref[:, 2] > 0.5
    pred[cap] += [0.01, 0.0, 0.0]
    cam = OrthographicCamera(torch.tensor(0.8), torch.zeros(2), 64, 64)
    out = body_errors(SimpleNamespace(vertices=torch.tensor(pred), faces=f), ref, np.ones(len(ref), bool), cam)
    # independently: each vertex's error under the centroid alignment, split by the sphere's front (z > 0)
    err = 1000 * np.linalg.norm(pred - pred.mean(0) + ref.mean(0) - ref, axis=1)
    assert out["body_err_mm"] == pytest.approx(err.mean())
    front = ref[:, 2] > 0
    assert out["body_err_visible_mm"] == pytest.approx(err[front].mean(), abs=0.3)  # the rim may go either way
    assert out["body_err_hidden_mm"] == pytest.approx(err[~front].mean(), abs=0.3)
    assert err[front].mean() > err[~front].mean() + 2  # the split matters
    assert out["body_err_pa_mm"] == pytest.approx(1000 * vertex_error(pred, ref, "similarity"))
    assert out["body_err_pa_mm"] < out["body_err_mm"]
    # an upper-body capture: only the modelled vertices count
    upper = ref[:, 1] > 0
    part = body_errors(SimpleNamespace(vertices=torch.tensor(pred), faces=f), ref, upper, cam)
    assert part["body_err_mm"] == pytest.approx(1000 * vertex_error(pred[upper], ref[upper]))
