"""A camera's rays (one origin, or an orthographic camera's one direction) take their candidate faces from bins in their image: the first hits are
the brute-force first hits, the hierarchy walk's and Embree's, including faces beside and behind the
camera, grazing rays and batches split across chunks."""

from __future__ import annotations

from fractions import Fraction

import pytest
import torch
import trimesh

from delta.geometry import pencil, raymesh
from delta.geometry.raymesh import embree_available, moller_trumbore, ray_mesh_hits
from tests.geometry.test_raymesh import _bubbles as bubbles

D = torch.float64


def _bubbles(seed: int = 0):
    """Six overlapping spheres of 1280 faces each."""
    return bubbles(seed, subdivisions=3)


def _camera_rays(v, origin, n, seed=1, spread=0.05):
    """n rays from ``origin`` towards points near the vertices."""
    g = torch.Generator().manual_seed(seed)
    target = v[torch.randint(len(v), (n,), generator=g)] + spread * torch.randn(n, 3, generator=g, dtype=D)
    return origin.expand(n, 3).clone(), target - origin


def _brute(v, f, origins, dirs):
    tri = v[f]
    t, u, w, det = moller_trumbore(origins[:, None], dirs[:, None], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
    inside = (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0) & (det.abs() > 1e-12)
    return torch.where(inside, t, torch.inf).amin(1)


def _walk(monkeypatch, *args):
    """The hierarchy walk's answer for the same rays (binning switched off)."""
    with monkeypatch.context() as m:
        m.setattr(pencil, "shared_origin", lambda origins: False)
        m.setattr(pencil, "shared_direction", lambda dirs: False)
        return ray_mesh_hits(*args, backend="torch")


def test_camera_rays_are_binned_and_match_the_brute_force_first_hit():
    v, f = _bubbles()
    o, d = _camera_rays(v, torch.tensor([0.4, -0.3, 4.0], dtype=D), 1500)
    assert pencil.shared_origin(o) and pencil.bin_faces(v[f], o[0], d) is not None
    got = ray_mesh_hits(v, f, o, d, backend="torch")
    want = _brute(v, f, o, d)
    assert 0.3 * len(o) < int(got.hit.sum()) < len(o)
    assert torch.equal(got.hit, torch.isfinite(want))
    torch.testing.assert_close(got.t[got.hit], want[got.hit], rtol=1e-12, atol=0)


def test_parallel_rays_are_binned_and_match_the_brute_force_first_hit(monkeypatch):
    """An orthographic camera's rays: one direction, origins spread over its image plane, some of them
    inside the scene (faces behind a ray's origin are not hit)."""
    v, f = _bubbles(2)
    g = torch.Generator().manual_seed(4)
    direction = torch.nn.functional.normalize(torch.tensor([0.2, -0.1, -1.0], dtype=D), dim=0)
    o = v[torch.randint(len(v), (1200,), generator=g)] + 0.05 * torch.randn(1200, 3, generator=g, dtype=D)
    o[:800] -= 6.0 * direction  # in front of the scene; the rest start inside it
    d = direction.expand(1200, 3).clone()
    assert pencil.shared_direction(d) and not pencil.shared_origin(o)
    bins = pencil.bin_faces_parallel(v[f], o, d[0])
    assert bins is not None and bins.everywhere.numel() == 0
    got = ray_mesh_hits(v, f, o, d, backend="torch")
    want = _brute(v, f, o, d)
    assert 0.3 * len(o) < int(got.hit.sum()) < len(o)
    assert torch.equal(got.hit, torch.isfinite(want))
    torch.testing.assert_close(got.t[got.hit], want[got.hit], rtol=1e-12, atol=0)
    walk = _walk(monkeypatch, v, f, o, d)
    assert torch.equal(walk.face, got.face)
    d2 = d.clone()
    d2[5, 0] += 1e-12
    assert not pencil.shared_direction(d2) and not pencil.shared_direction(d[:0])


@pytest.mark.skipif(not embree_available(), reason="no embreex")
def test_auto_casts_a_training_steps_rays_in_torch_and_a_whole_image_in_embree():
    """A fresh mesh and a camera's rays up to TORCH_RAYS: the torch search (no scene to build); more rays, rays
    from no camera, or a mesh Embree has already built: Embree. Either way the same first hits."""
    v, f = _bubbles(3)
    o, d = _camera_rays(v, torch.tensor([0.1, 0.2, 4.0], dtype=D), 600, seed=2)
    v = v.clone()
    assert raymesh._auto_backend(v, f, o, d) == "torch"
    ortho = d[0].expand(600, 3).clone()
    assert raymesh._auto_backend(v, f, o + torch.randn(600, 3, dtype=D), ortho) == "torch"
    scattered = o + torch.randn(600, 3, dtype=D)
    assert raymesh._auto_backend(v, f, scattered, d) == "embree"
    many = raymesh.TORCH_RAYS + 1
    assert raymesh._auto_backend(v, f, o[:1].expand(many, 3), d[:1].expand(many, 3)) == "embree"
    auto = ray_mesh_hits(v, f, o, d)
    embree = ray_mesh_hits(v, f, o, d, backend="embree")  # builds v's scene
    assert raymesh._auto_backend(v, f, o, d) == "embree"
    assert torch.equal(auto.hit, embree.hit)
    torch.testing.assert_close(auto.t[auto.hit], embree.t[auto.hit], rtol=1e-6, atol=0)
    v.add_(0.0)  # modified in place: the scene no longer holds
    assert raymesh._auto_backend(v, f, o, d) == "torch"


@pytest.mark.skipif(not embree_available(), reason="no embreex")
def test_a_mesh_kept_for_many_chunks_is_cast_in_embree_with_the_same_hits():
    """A whole image's chunks: once ``keep_scene`` has built the mesh's scene, a chunk of a training step's
    size goes to Embree too, with the torch search's first hits; another mesh goes back to torch."""
    v, f = _bubbles(3)
    o, d = _camera_rays(v, torch.tensor([0.1, 0.2, 4.0], dtype=D), 600, seed=4)
    v = v.clone()
    torch_hits = ray_mesh_hits(v, f, o, d, backend="torch")
    assert raymesh._auto_backend(v, f, o, d) == "torch"
    raymesh.keep_scene(v, f)
    assert raymesh._auto_backend(v, f, o, d) == "embree"
    kept = ray_mesh_hits(v, f, o, d)
    assert torch.equal(kept.hit, torch_hits.hit) and torch.equal(kept.face, torch_hits.face)
    torch.testing.assert_close(kept.t[kept.hit], torch_hits.t[kept.hit], rtol=1e-6, atol=0)
    assert raymesh._auto_backend(v.clone(), f, o, d) == "torch"


def test_a_camera_inside_the_scene_sees_faces_beside_and_behind_its_plane(monkeypatch):
    """From inside the spheres, faces straddle the camera's plane and some lie behind it: a ray never
    meets a face behind it, and every straddling face is a candidate of every ray."""
    v, f = _bubbles(2)
    origin = v.mean(0)
    o, d = _camera_rays(v, origin, 800, seed=3, spread=0.3)
    d = torch.where((d[:, 2:] > 0), d, d * torch.tensor([1.0, 1.0, -1.0], dtype=D))  # all within 90° of +z
    d[:, 2] += 0.5 * d.norm(dim=1)  # and within the binnable cone
    bins = pencil.bin_faces(v[f], o[0], d)
    assert bins is not None and len(bins.everywhere) > 0
    got = ray_mesh_hits(v, f, o, d, backend="torch")
    want = _brute(v, f, o, d)
    assert torch.equal(got.hit, torch.isfinite(want))
    torch.testing.assert_close(got.t[got.hit], want[got.hit], rtol=1e-12, atol=0)
    walk = _walk(monkeypatch, v, f, o, d)
    assert torch.equal(walk.face, got.face)


def test_small_chunks_split_the_rays_and_change_nothing(monkeypatch):
    v, f = _bubbles(4)
    o, d = _camera_rays(v, torch.tensor([-3.0, 0.5, 1.0], dtype=D), 600, seed=5)
    whole = ray_mesh_hits(v, f, o, d, backend="torch")
    bins = pencil.bin_faces(v[f], o[0], d)
    batches = list(bins.pairs(5000))
    assert len(batches) > 3
    assert sum(len(r) for r, _ in batches) == int(bins.cell_count[bins.ray_cell].sum())
    monkeypatch.setattr(raymesh, "_CHUNK_PAIRS", 5000)
    assert torch.equal(ray_mesh_hits(v, f, o, d, backend="torch").face, whole.face)


def test_rays_wider_than_the_cone_or_from_several_points_walk_the_hierarchy():
    v, f = _bubbles(6)
    origin = torch.tensor([0.0, 0.0, 5.0], dtype=D)
    o, d = _camera_rays(v, origin, 300, seed=7)
    d[0] = torch.tensor([0.0, 0.0, 1.0], dtype=D)  # straight away from the scene: 180° from the others
    assert pencil.bin_faces(v[f], o[0], d) is None
    got = ray_mesh_hits(v, f, o, d, backend="torch")
    want = _brute(v, f, o, d)
    assert torch.equal(got.hit, torch.isfinite(want)) and not got.hit[0]
    o2 = o.clone()
    o2[1] += 1e-12
    assert pencil.shared_origin(o) and not pencil.shared_origin(o2)
    assert not pencil.shared_origin(o[:0])


@pytest.mark.skipif(not embree_available(), reason="no embreex")
def test_binned_camera_rays_agree_with_embree_on_a_body_sized_mesh(monkeypatch):
    """A dense mesh (20k faces) seen from 3 m, with rays through its vertices (edges shared by faces)."""
    ball = trimesh.creation.icosphere(subdivisions=5)
    v = torch.tensor(ball.vertices, dtype=D) * torch.tensor([0.3, 0.9, 0.2], dtype=D)
    f = torch.tensor(ball.faces)
    origin = torch.tensor([0.2, 0.4, 3.0], dtype=D)
    o, d = _camera_rays(v, origin, 4000, seed=9, spread=0.02)
    d[:200] = v[:200] - origin  # exactly through vertices
    a = ray_mesh_hits(v, f, o, d, backend="embree")
    b = ray_mesh_hits(v, f, o, d, backend="torch")
    same = (a.hit == b.hit) & (~a.hit | ((a.t - b.t).abs() <= 1e-9 * a.t.abs()))
    assert int((~same).sum()) <= 4  # Embree's float32 on rays through a vertex on the silhouette
    assert bool(b.hit.any()) and bool(same[200:].sum() >= len(o) - 200 - 1)
    walk = _walk(monkeypatch, v, f, o, d)  # through a vertex, faces at equal t: either may be named
    assert torch.equal(walk.hit, b.hit) and torch.equal(walk.t, b.t) and torch.equal(walk.face[200:], b.face[200:])


@pytest.mark.parametrize("height", [1e-3, 1e-6])
def test_grazing_camera_rays_match_exact_arithmetic(height):
    """A camera ``height`` above the plane of a 2 m quad, 3 m from it, its rays crossing the plane near the
    quad's edges at slopes down to 3e-7: hit or miss as exact rational arithmetic decides on the same
    float32 inputs, wherever the crossing is more than 1 mm from an edge."""
    g = torch.Generator().manual_seed(11)
    n = 2000
    target = torch.rand(n, 2, generator=g, dtype=D) * 2.2 - 1.1
    origin = torch.tensor([-4.0, 0.3, height], dtype=D)
    o = origin.expand(n, 3).clone()
    d = torch.cat([target, torch.zeros(n, 1, dtype=D)], 1) - origin
    quad = torch.tensor([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=D)
    o32, d32, v32 = o.float(), d.float(), quad.float()
    assert pencil.bin_faces(v32.double()[torch.tensor([[0, 1, 2], [0, 2, 3]])], o[0], d) is not None
    hits = ray_mesh_hits(v32, torch.tensor([[0, 1, 2], [0, 2, 3]]), o32, d32, backend="torch")
    checked = 0
    for i in range(n):
        ox, oy, oz = (Fraction(float(x)) for x in o32[i])
        dx, dy, dz = (Fraction(float(x)) for x in d32[i])
        t = -oz / dz
        px, py = ox + t * dx, oy + t * dy
        margin = float(max(abs(px), abs(py)) - 1)
        if t <= 0 or abs(margin) < 1e-3:
            continue
        checked += 1
        assert bool(hits.hit[i]) == (margin < 0), (i, margin)
    assert checked > 0.8 * n


def test_a_face_touching_the_camera_centre_is_a_candidate_of_every_ray():
    """Corners at the centre or a hair's breadth in front of it would project out of range: such faces
    are tested against every ray (seen from their own corner they are edge-on), and the answers are the
    brute-force ones."""
    origin = torch.tensor([0.1, -0.2, 2.0], dtype=D)
    v = torch.tensor([
        [-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0],  # a far quad the rays look at
        [0.1, -0.2, 2.0], [0.3, 0.1, 1.0], [-0.2, 0.2, 1.0],  # a corner at the centre
        [0.1, -0.2, 2.0 - 1e-30], [0.0, -0.3, 1.5], [0.4, -0.4, 1.5],  # a corner 1e-30 in front of it
    ], dtype=D)  # fmt: skip
    f = torch.tensor([[0, 1, 2], [0, 2, 3], [4, 5, 6], [7, 8, 9]])
    g = torch.Generator().manual_seed(13)
    target = torch.cat([torch.rand(400, 2, generator=g, dtype=D) * 2.4 - 1.2, torch.zeros(400, 1, dtype=D)], 1)
    o, d = origin.expand(400, 3).clone(), target - origin
    bins = pencil.bin_faces(v[f], o[0], d)
    assert bins is not None and sorted(bins.everywhere.tolist()) == [2, 3]
    got = ray_mesh_hits(v, f, o, d, backend="torch")
    want = _brute(v, f, o, d)
    assert torch.equal(got.hit, torch.isfinite(want)) and 0.5 * len(o) < int(got.hit.sum()) < len(o)
    torch.testing.assert_close(got.t[got.hit], want[got.hit], rtol=1e-12, atol=0)
