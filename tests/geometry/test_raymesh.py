"""Ray-mesh hits against analytic oracles; Embree and the torch hierarchy search agree."""

from __future__ import annotations

import pytest
import torch
import trimesh

from delta.geometry.raymesh import RayHits, embree_available, interpolate, moller_trumbore, ray_mesh_hits

BACKENDS = ["torch", pytest.param("embree", marks=pytest.mark.skipif(not embree_available(), reason="no embreex"))]
D = torch.float64


def unit_square():
    """Two triangles covering [0, 1]^2 at z = 0; face 0 holds x >= y, face 1 holds y >= x."""
    v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=D)
    f = torch.tensor([[0, 1, 2], [0, 2, 3]])
    return v, f


def down_rays(xy, height=3.0, speed=2.0):
    xy = torch.as_tensor(xy, dtype=D)
    origins = torch.cat([xy, torch.full((len(xy), 1), height, dtype=D)], 1)
    dirs = torch.tensor([[0.0, 0, -speed]], dtype=D).expand(len(xy), 3).clone()
    return origins, dirs


def square_bary(x, y):
    """Analytic (face, barycentrics) of (x, y) on :func:`unit_square`."""
    if x >= y:
        return 0, [1 - x, x - y, y]
    return 1, [1 - y, x, y - x]


@pytest.mark.parametrize("backend", BACKENDS)
def test_unit_square_t_and_barycentrics(backend):
    v, f = unit_square()
    xy = [[0.7, 0.2], [0.25, 0.6], [0.1, 0.05], [0.9, 0.95]]
    origins, dirs = down_rays(xy, height=3.0, speed=2.0)
    hits = ray_mesh_hits(v, f, origins, dirs, backend=backend)
    assert isinstance(hits, RayHits) and hits.hit.all()
    torch.testing.assert_close(hits.t, torch.full((4,), 1.5, dtype=D), rtol=0, atol=1e-12)
    for i, (x, y) in enumerate(xy):
        face, bary = square_bary(x, y)
        assert hits.face[i] == face
        torch.testing.assert_close(hits.bary[i], torch.tensor(bary, dtype=D), rtol=0, atol=1e-12)
    colour = interpolate(hits, f, v[:, :2] * 10)  # interpolating positions gives the hit point back
    torch.testing.assert_close(colour, torch.tensor(xy, dtype=D) * 10, rtol=0, atol=1e-10)


@pytest.mark.parametrize("backend", BACKENDS)
def test_misses_report_inf_and_minus_one(backend):
    v, f = unit_square()
    origins, dirs = down_rays([[2.0, 2.0], [0.5, 0.2]])
    dirs[1] = -dirs[1]  # points away from the square: the plane is behind it (t < 0)
    hits = ray_mesh_hits(v, f, origins, dirs, backend=backend)
    assert not hits.hit.any()
    assert torch.isinf(hits.t).all() and (hits.t > 0).all()
    assert (hits.face == -1).all() and (hits.bary == 0).all()
    assert (interpolate(hits, f, v) == 0).all()


def _sphere_rays(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    far = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=D), dim=1) * 3
    target = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=D), dim=1)
    target = target * 0.8 * torch.rand(n, 1, generator=g, dtype=D)  # inside the inscribed ball
    origins = torch.where(torch.arange(n)[:, None] % 4 == 0, 0.5 * target, far)  # a quarter start inside
    dirs = (target - origins) * (0.5 + torch.rand(n, 1, generator=g, dtype=D))
    dirs[::4] = torch.randn(len(dirs[::4]), 3, generator=g, dtype=D)
    return origins, dirs


@pytest.mark.skipif(not embree_available(), reason="no embreex")
def test_embree_and_torch_agree_on_icosphere():
    mesh = trimesh.creation.icosphere(subdivisions=2)
    v, f = torch.tensor(mesh.vertices, dtype=D), torch.tensor(mesh.faces)
    origins, dirs = _sphere_rays(500)
    a = ray_mesh_hits(v, f, origins, dirs, backend="embree")
    b = ray_mesh_hits(v, f, origins, dirs, backend="torch")
    assert a.hit.all() and b.hit.all()
    torch.testing.assert_close(a.t, b.t, rtol=1e-6, atol=0)
    differ = a.face != b.face  # only ties: rays through a shared edge or vertex
    assert differ.sum() <= 2
    # the exact hit: the interpolated position is on the ray at t
    for h in (a, b):
        torch.testing.assert_close(interpolate(h, f, v), origins + h.t[:, None] * dirs, rtol=0, atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_first_hit_on_sphere_is_the_near_side(backend):
    r, centre = 2.0, torch.tensor([0.5, -1.0, 2.0], dtype=D)
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=r)
    v, f = torch.tensor(mesh.vertices, dtype=D) + centre, torch.tensor(mesh.faces)
    # through a mesh vertex (on the sphere exactly) from distance d: t = d - r
    unit = torch.tensor(mesh.vertices[[5, 100, 400]], dtype=D) / r
    d = torch.tensor([5.0, 3.0, 10.0], dtype=D)
    hits = ray_mesh_hits(v, f, centre + d[:, None] * unit, -unit * 0.5, backend=backend)
    assert hits.hit.all()
    torch.testing.assert_close(hits.t * 0.5, d - r, rtol=1e-12, atol=0)
    # generic direction through the centre: near side within the tessellation error, not the far side
    u = torch.nn.functional.normalize(torch.tensor([[0.3, 0.5, -0.8]], dtype=D), dim=1)
    hits = ray_mesh_hits(v, f, centre + 6 * u, -u, backend=backend)
    assert hits.hit.all() and 6 - r <= hits.t.item() <= 6 - r + 0.02 * r


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradcheck_single_triangle(backend):
    tri = torch.tensor([[0.1, -0.2, 0.3], [1.2, 0.1, -0.1], [0.2, 1.1, 0.2]], dtype=D, requires_grad=True)
    origins = torch.tensor([[0.4, 0.3, 2.0], [0.2, 0.1, -1.5]], dtype=D, requires_grad=True)
    dirs = torch.tensor([[0.05, -0.1, -1.3], [0.1, 0.2, 0.9]], dtype=D, requires_grad=True)
    f = torch.tensor([[0, 1, 2]])

    def fn(vv, oo, dd):
        hits = ray_mesh_hits(vv, f, oo, dd, backend=backend)
        assert hits.hit.all()
        return hits.t, hits.bary

    assert torch.autograd.gradcheck(fn, (tri, origins, dirs))


def _assert_finite_grads(t, bary, *inputs):
    assert torch.isfinite(t).all() and torch.isfinite(bary).all()
    inputs = [x for x in inputs if x.requires_grad]
    grads = torch.autograd.grad((t.sum() + bary.sum() + (bary * bary).sum()), inputs, allow_unused=True)
    assert all(g is None or torch.isfinite(g).all() for g in grads)


def test_parallel_and_grazing_rays_stay_finite():
    a, b, c = (torch.tensor(x, dtype=D, requires_grad=True) for x in ([0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0]))
    origins = torch.tensor([[0.2, 0.2, 0.0], [-1.0, 0.0, 0.0], [-1.0, 0.3, 1e-9]], dtype=D, requires_grad=True)
    dirs = torch.tensor([[1.0, 0, 0], [1.0, 0, 0], [1.0, 0, -1e-12]], dtype=D, requires_grad=True)
    t, u, v, det = moller_trumbore(origins, dirs, a, b, c)
    assert det[0] == 0 and det[1] == 0
    _assert_finite_grads(t, torch.stack([u, v], -1), a, b, c, origins, dirs)
    verts = torch.stack([a, b, c])
    for backend in ["torch"] + (["embree"] if embree_available() else []):
        hits = ray_mesh_hits(verts, torch.tensor([[0, 1, 2]]), origins, dirs, backend=backend)
        assert not hits.hit[:2].any()  # exactly parallel (in the plane): no hit, no NaN
        assert not torch.isnan(hits.t).any() and torch.isfinite(hits.bary).all()
        _assert_finite_grads(hits.t[hits.hit], hits.bary, verts, origins, dirs)


@pytest.mark.parametrize("offset", [0.0, 1000.0])
@pytest.mark.parametrize("backend", BACKENDS)
def test_rays_through_vertices_and_edges_hit(backend, offset):
    v, f = unit_square()
    v = (v + offset).requires_grad_(True)
    xy = torch.tensor([[0.0, 0], [1, 1], [1, 0], [0.5, 0.5], [0.3, 0.3], [0.5, 0], [1, 0.25], [0, 0.75]], dtype=D)
    origins, dirs = down_rays(xy + offset, height=offset + 3)
    origins.requires_grad_(True)
    hits = ray_mesh_hits(v, f, origins, dirs, backend=backend)
    assert hits.hit.all()
    torch.testing.assert_close(hits.t, torch.full((len(xy),), 1.5, dtype=D), rtol=0, atol=1e-12)
    assert (hits.bary >= -1e-6).all() and (hits.bary <= 1 + 1e-6).all()
    torch.testing.assert_close(hits.bary.sum(1), torch.ones(len(xy), dtype=D))
    torch.testing.assert_close(interpolate(hits, f, v[:, :2]) - offset, xy, rtol=0, atol=1e-10)
    _assert_finite_grads(hits.t, hits.bary, v, origins, dirs)


def test_dtype_follows_inputs_and_unknown_backend():
    v, f = unit_square()
    origins, dirs = down_rays([[0.3, 0.1]])
    hits = ray_mesh_hits(v.float(), f, origins.float(), dirs.float(), backend="torch")
    assert hits.t.dtype == torch.float32 and hits.bary.dtype == torch.float32
    assert abs(hits.t.item() - 1.5) < 1e-6
    with pytest.raises(ValueError, match="backend"):
        ray_mesh_hits(v, f, origins, dirs, backend="optix")


@pytest.mark.parametrize("shift", [0.0, 1000.0])
def test_torch_search_matches_exact_arithmetic_on_near_parallel_rays(shift):
    """A 2 m quad in the plane z = 0, ``shift`` metres from the origin, and rays nearly parallel to it
    (slopes 1e-9 to 1e-2) crossing its plane near the edges: the torch search decides hit or miss as
    exact rational arithmetic on the same float32 inputs does, wherever the crossing lies more than
    1 mm from an edge. (The expanded products alone took such rays 1 km out for hits up to 5 cm outside.)"""
    import math
    from fractions import Fraction

    g = torch.Generator().manual_seed(7)
    n = 3000
    target = torch.rand(n, 2, generator=g, dtype=torch.float64) * 2.1 - 1.05
    angle = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    slope = 10 ** (torch.rand(n, generator=g, dtype=torch.float64) * 7 - 9)
    dist = 10 ** (torch.rand(n, generator=g, dtype=torch.float64) * 3)
    d = torch.stack([torch.cos(angle), torch.sin(angle), -slope], -1)
    o = torch.cat([target + shift, torch.zeros(n, 1, dtype=torch.float64)], -1) - d * dist[:, None]
    quad = torch.tensor([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=torch.float64) + torch.tensor(
        [shift, shift, 0]
    )
    o32, d32, v32 = o.float(), d.float(), quad.float()
    hits = ray_mesh_hits(v32, torch.tensor([[0, 1, 2], [0, 2, 3]]), o32, d32, backend="torch")
    s = Fraction(float(v32[0, 0]) + 1)  # the quad's centre as stored in float32 (exact: a whole number)
    checked = 0
    for i in range(n):
        ox, oy, oz = (Fraction(float(x)) for x in o32[i])
        dx, dy, dz = (Fraction(float(x)) for x in d32[i])
        t = -oz / dz
        px, py = ox + t * dx - s, oy + t * dy - s
        margin = float(max(abs(px), abs(py)) - 1)
        if t <= 0 or abs(margin) < 1e-3:
            continue
        checked += 1
        assert bool(hits.hit[i]) == (margin < 0), (i, margin, float(t))
    assert checked > 0.9 * n


@pytest.mark.skipif(not embree_available(), reason="Embree is not installed")
def test_the_embree_scene_is_reused_only_for_the_same_unmodified_mesh():
    """A whole-image render casts its chunks against one mesh: the scene is built once. A mesh moved in
    place, or a new tensor (even one that reuses freed memory), is cast against afresh."""
    from delta.geometry import raymesh

    v = torch.tensor([[-1.0, -1, 0], [1, -1, 0], [0, 1, 0]], dtype=torch.float64)
    f = torch.tensor([[0, 1, 2]])
    o = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.5, 1.0]], dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    first = ray_mesh_hits(v, f, o, d, backend="embree")
    scene = raymesh._SCENES.value
    again = ray_mesh_hits(v, f, o, d, backend="embree")
    assert raymesh._SCENES.value is scene and torch.equal(first.hit, again.hit)
    v[:, 1] -= 0.6  # moved in place: the top ray now passes above the triangle
    moved = ray_mesh_hits(v, f, o, d, backend="embree")
    assert raymesh._SCENES.value is not scene
    assert moved.hit.tolist() == [True, False]
    for shift in (0.0, 5.0):  # fresh tensors each time: never the scene of another mesh
        w = torch.tensor([[-1.0, -1, 0], [1, -1, 0], [0, 1, 0]], dtype=torch.float64) + torch.tensor([shift, 0, 0])
        assert ray_mesh_hits(w, f, o, d, backend="embree").hit.tolist() == (
            [True, True] if shift == 0 else [False, False]
        )


def _bubbles(seed: int = 0, subdivisions: int = 4):
    """Six overlapping spheres of 5120 faces each (subdivisions 4: a hierarchy of three levels; rays cross
    many surfaces)."""
    g = torch.Generator().manual_seed(seed)
    ball = trimesh.creation.icosphere(subdivisions=subdivisions)
    parts = [(torch.tensor(ball.vertices, dtype=D) * (0.3 + 0.4 * torch.rand(1, generator=g, dtype=D))
              + 0.6 * torch.randn(1, 3, generator=g, dtype=D)) for _ in range(6)]  # fmt: skip
    faces = torch.cat([torch.tensor(ball.faces) + i * len(ball.vertices) for i in range(6)])
    return torch.cat(parts), faces


@pytest.mark.skipif(not embree_available(), reason="no embreex")
def test_embree_and_torch_agree_on_a_large_scene_with_grazing_and_axis_rays():
    v, f = _bubbles()
    g = torch.Generator().manual_seed(1)
    n = 4000
    origins = 4 * torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=D), dim=1)
    origins[: n // 4] = v[torch.randint(len(v), (n // 4,), generator=g)] * 0.5  # many start inside a sphere
    target = v[torch.randint(len(v), (n,), generator=g)] + 0.05 * torch.randn(n, 3, generator=g, dtype=D)
    dirs = target - origins
    dirs[n // 2 : n // 2 + 300, :2] = 0  # axis-parallel: two zero components
    dirs[n // 2 + 300 : n // 2 + 600, 0] = 0
    a = ray_mesh_hits(v, f, origins, dirs, backend="embree")
    b = ray_mesh_hits(v, f, origins, dirs, backend="torch")
    assert 0.3 * n < int(b.hit.sum()) < n
    assert int((a.hit != b.hit).sum()) <= 2  # Embree's float32 on a ray grazing an edge
    both = a.hit & b.hit
    torch.testing.assert_close(a.t[both], b.t[both], rtol=1e-9, atol=0)
    torch.testing.assert_close(interpolate(b, f, v)[b.hit], (origins + b.t[:, None] * dirs)[b.hit], rtol=0, atol=1e-9)


def test_torch_search_is_the_brute_force_first_hit():
    """Against an independent oracle: every ray tested against every face, nearest t kept."""
    v, f = _bubbles(2)
    g = torch.Generator().manual_seed(3)
    origins = 3 * torch.nn.functional.normalize(torch.randn(300, 3, generator=g, dtype=D), dim=1)
    tri = v[f]
    w = torch.rand(300, 3, generator=g, dtype=D) + 0.05  # aimed at face interiors: no ties at edges
    dirs = (w[:, :, None] * tri[torch.randint(len(f), (300,), generator=g)]).sum(1) / w.sum(1, keepdim=True) - origins
    got = ray_mesh_hits(v, f, origins, dirs, backend="torch")
    t, u, w, det = moller_trumbore(origins[:, None], dirs[:, None], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
    inside = (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0) & (det.abs() > 1e-12)
    want = torch.where(inside, t, torch.inf).amin(1)
    assert torch.equal(got.hit, torch.isfinite(want))
    torch.testing.assert_close(got.t[got.hit], want[got.hit], rtol=1e-12, atol=0)
