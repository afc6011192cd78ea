"""The harmonic fill: exact on linear functions, within the known values' range, each filled vertex its
neighbours' mean, parts that reach nothing known and vertices left out."""

from __future__ import annotations

import numpy as np
import torch
import trimesh

from delta.geometry.harmonic import harmonic_fill, vertex_graph


def grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """An n × n grid of vertices on [0, 1]², each square cut along the same diagonal."""
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="xy")
    verts = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], -1)
    faces = []
    for r in range(n - 1):
        for c in range(n - 1):
            a, b, d, e = r * n + c, r * n + c + 1, (r + 1) * n + c, (r + 1) * n + c + 1
            faces += [[a, b, e], [a, e, d]]
    return verts, np.array(faces, dtype=np.int64)


def test_a_linear_function_known_on_the_border_is_filled_exactly_inside():
    verts, faces = grid(12)
    values = np.stack([2 * verts[:, 0] - 3 * verts[:, 1] + 1, verts[:, 1], 0.5 - verts[:, 0]], -1)
    border = (verts[:, 0] == 0) | (verts[:, 0] == 1) | (verts[:, 1] == 0) | (verts[:, 1] == 1)
    given = values.copy()
    given[~border] = 7.0  # what the unknown vertices held is not read
    out = harmonic_fill(torch.from_numpy(given), torch.from_numpy(border), torch.from_numpy(faces))
    np.testing.assert_allclose(out.numpy(), values, atol=1e-9)


def test_known_values_stay_and_each_filled_vertex_is_its_neighbours_mean_within_their_range():
    mesh = trimesh.creation.icosphere(subdivisions=3)
    n = len(mesh.vertices)
    rng = np.random.default_rng(0)
    known = mesh.vertices[:, 2] > 0.3  # a cap known, the rest filled
    values = rng.uniform(0.1, 0.9, (n, 3))
    out = harmonic_fill(torch.from_numpy(values).float(), torch.from_numpy(known), torch.from_numpy(mesh.faces))
    assert out.dtype == torch.float32
    got = out.double().numpy()
    np.testing.assert_array_equal(out.numpy()[known], values[known].astype(np.float32))
    adj = vertex_graph(mesh.faces, n)
    mean = (adj @ got) / np.asarray(adj.sum(1))
    np.testing.assert_allclose(got[~known], mean[~known], atol=1e-6)
    lo, hi = values[known].min(0), values[known].max(0)
    assert (got[~known] >= lo - 1e-6).all() and (got[~known] <= hi + 1e-6).all()
    assert got[~known].std(0).max() > 1e-3  # a fill, not one constant


def test_a_part_that_reaches_nothing_known_takes_the_known_values_mean():
    a = trimesh.creation.icosphere(subdivisions=1)
    b = trimesh.creation.icosphere(subdivisions=1)
    b.apply_translation([5, 0, 0])
    both = trimesh.util.concatenate([a, b])
    n_a = len(a.vertices)
    known = np.zeros(len(both.vertices), bool)
    known[: n_a // 2] = True
    values = np.zeros((len(both.vertices), 1))
    values[: n_a // 2, 0] = np.linspace(0, 1, n_a // 2)
    out = harmonic_fill(torch.from_numpy(values), torch.from_numpy(known), torch.from_numpy(both.faces)).numpy()
    np.testing.assert_allclose(out[n_a:, 0], values[: n_a // 2, 0].mean())


def test_an_excluded_vertex_keeps_its_value_and_gives_none_to_its_neighbours():
    verts, faces = grid(9)
    values = np.stack([verts[:, 0] + verts[:, 1]], -1)
    border = (verts[:, 0] == 0) | (verts[:, 0] == 1) | (verts[:, 1] == 0) | (verts[:, 1] == 1)
    centre = 4 * 9 + 4
    excluded = np.zeros(len(verts), bool)
    excluded[centre] = True
    given = values.copy()
    given[centre] = 100.0
    out = harmonic_fill(torch.from_numpy(given), torch.from_numpy(border), torch.from_numpy(faces),
                        torch.from_numpy(excluded)).numpy()  # fmt: skip
    assert out[centre, 0] == 100.0
    # the same as the grid without the centre's faces: an independent solve of that smaller system
    cut = faces[~(faces == centre).any(1)]
    alone = harmonic_fill(torch.from_numpy(values), torch.from_numpy(border | excluded), torch.from_numpy(cut)).numpy()
    keep = ~excluded
    np.testing.assert_allclose(out[keep], alone[keep], atol=1e-9)
    assert (out[keep] < 3).all()


def test_nothing_to_fill_returns_the_values():
    verts, faces = grid(4)
    values = torch.rand(len(verts), 3)
    out = harmonic_fill(values, torch.ones(len(verts), dtype=torch.bool), torch.from_numpy(faces))
    assert torch.equal(out, values)
