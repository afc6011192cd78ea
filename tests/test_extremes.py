"""Stability at the extremes (issue #8): each numerical component driven to its edges through the
public functions training uses, asserting finite values and gradients and, where there is an
oracle, the right values. The component modules test each piece on its own; here the pieces are
pushed together (a ray box entry of 1e18 reaching the distance grid, a body translated onto the
camera reaching the silhouette, a 1e-6 camera scale reaching every gradient of the avatar).
"""

from __future__ import annotations

import math

import pytest
import torch
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from delta import losses as L
from delta.body.lbs import batch_rodrigues, lbs
from delta.body.model import BodyModel
from delta.cameras.models import MIN_DEPTH, OrthographicCamera, PinholeCamera, look_at
from delta.data.frames import RayBatch
from delta.deformers import knn as deformer
from delta.fields.networks import NeRFField
from delta.fields.spec import FieldSpec
from delta.geometry import distance_grid
from delta.geometry.raymesh import embree_available, moller_trumbore, ray_mesh_hits
from delta.models.avatar import HybridAvatar, InitParams
from delta.models.spec import AvatarSpec
from delta.render.hybrid import PosedMesh, render_rays
from delta.render.settings import RenderSettings
from delta.render.silhouette import soft_silhouette
from delta.render.volume import composite, nerf_weights, ray_box, stratified_samples
from delta.training.presets import resolve
from delta.training.trainer import loss_terms
from tests.conftest import soft_tree_model

D = torch.float64
BACKENDS = ["torch", pytest.param("embree", marks=pytest.mark.skipif(not embree_available(), reason="no embreex"))]
ANGLES = [2 * math.pi, 3 * math.pi, -3 * math.pi, 1e3, -1e3]
"""Joint angles beyond π (rad)."""


def finite(*tensors) -> bool:
    return all(bool(torch.isfinite(x).all()) for x in tensors if x is not None)


def grads(out: torch.Tensor, inputs: list[torch.Tensor]) -> list[torch.Tensor]:
    return [g for g in torch.autograd.grad(out, inputs, allow_unused=True, retain_graph=True) if g is not None]


# ----------------------------------------------------------------- volume rendering
_SIGMA = st.one_of(st.sampled_from([0.0, 1e-12, 1e6]), st.floats(0.0, 1e6))
_DELTA = st.one_of(st.sampled_from([0.0, 1e-30, 1e-7, 1e3]), st.floats(0.0, 10.0))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(_SIGMA, _DELTA), min_size=1, max_size=16))
def test_weights_are_a_partition_in_both_precisions(samples):
    """Any σ in [0, 1e6] and Δ ≥ 0: NeRF weights in [0, 1] summing to ≤ 1, finite gradients, fp32 ≈ fp64."""
    out = {}
    for dtype in (torch.float32, D):
        sigma = torch.tensor([[s for s, _ in samples]], dtype=dtype, requires_grad=True)
        delta = torch.tensor([[d for _, d in samples]], dtype=dtype, requires_grad=True)
        w = nerf_weights(sigma, delta)
        assert finite(w) and bool((w >= 0).all()) and bool((w <= 1).all())
        assert float(w[0, :-1].detach().sum()) <= 1 + 1e-6
        torch.testing.assert_close(w.sum(-1), torch.ones(1, dtype=dtype), rtol=0, atol=1e-5)
        assert finite(*grads((w * torch.arange(1.0, w.shape[1] + 1, dtype=dtype)).sum(), [sigma, delta]))
        out[dtype] = w.detach()
    torch.testing.assert_close(out[torch.float32].double(), out[D], rtol=0, atol=2e-5)


@pytest.mark.parametrize("dtype", [torch.float32, D])
def test_zero_spacing_and_underflow_through_the_sampler(dtype):
    """Empty spans put all weight on the end sample; 1e6 density makes the first sample opaque."""
    near = torch.tensor([2.0, 2.0, 2.0, 1e6], dtype=dtype)
    far = torch.tensor([2.0, 2.0 + 1e-7, 5.0, 1e6 + 1.0], dtype=dtype)
    t = stratified_samples(near, far, 8, perturb=True, generator=torch.Generator().manual_seed(0))
    assert bool((t[:, 1:] >= t[:, :-1]).all()) and torch.equal(t[:, -1], far)
    sigma = torch.tensor([[5.0] * 7, [1e6] * 7, [1e6] * 7, [1e6] * 7], dtype=dtype, requires_grad=True)
    gen = torch.Generator().manual_seed(1)
    nerf_rgb = torch.rand(4, 7, 3, generator=gen, dtype=dtype).requires_grad_()
    end = torch.rand(4, 3, generator=gen, dtype=dtype).requires_grad_()
    out = composite(t, sigma, nerf_rgb, end)
    assert finite(out.rgb, out.weights, out.depth)
    torch.testing.assert_close(out.rgb[0], end[0], rtol=0, atol=0)  # Δ = 0: nothing in front of the end
    assert float(out.nerf_mask[0].detach()) == 0.0
    # 1e6 over Δ ≈ 0.43 and ≈ 0.14: transmittance underflows to exactly 0 after the first sample
    for r in (2, 3):
        w = out.weights.detach()
        assert float(w[r, 0]) == 1.0 and bool((w[r, 1:] == 0).all())
        torch.testing.assert_close(out.rgb[r], nerf_rgb[r, 0], rtol=0, atol=0)
    assert finite(*grads(out.rgb.sum() + out.depth.sum() / 1e6, [sigma, nerf_rgb, end]))


def test_ray_box_from_far_away_along_the_axes():
    """Axis-parallel rays from 1e6 away: clean hits with exact distances, clean misses, nothing NaN."""
    lo, hi = torch.tensor([-1.0, -1, -1]), torch.tensor([1.0, 1, 1])
    o = torch.tensor([[0.0, 0, 1e6], [0.0, 0, -1e6], [1e6, 0, 10], [-1e6, 0, 10], [0.0, 0, 1e-30]])
    d = torch.tensor([[0.0, 0, -1]] * 5)
    t_in, t_out, hit = ray_box(o, d, lo, hi)
    assert hit.tolist() == [True, False, False, False, True]
    assert finite(t_in, t_out)
    torch.testing.assert_close(t_in[0], torch.tensor(1e6 - 1), rtol=0, atol=0.1)
    assert float(t_in[4]) == 0.0 and float(t_out[4]) == pytest.approx(1.0)


# ----------------------------------------------------------------- ray-mesh hits
@settings(max_examples=40, deadline=None)
@given(
    corners=st.lists(st.floats(-2.0, 2.0), min_size=9, max_size=9),
    uv=st.tuples(st.floats(0.05, 0.9), st.floats(0.05, 0.9)),
    origin=st.tuples(st.floats(-3.0, 3.0), st.floats(-3.0, 3.0), st.floats(-3.0, 3.0)),
)
def test_hit_point_lies_on_the_triangle(corners, uv, origin):
    """A ray aimed at a point inside a random triangle hits it there, on its plane, in both backends."""
    v = torch.tensor(corners, dtype=D).view(3, 3).requires_grad_()
    n = torch.linalg.cross(v[1] - v[0], v[2] - v[0]).detach()
    u, w = uv[0], uv[1] * (1 - uv[0])  # inside, away from the edges
    target = ((1 - u - w) * v[0] + u * v[1] + w * v[2]).detach()
    o = torch.tensor([origin], dtype=D)
    d = (target - o).requires_grad_()
    ray_len, area = float(d.detach().norm()), float(n.norm()) / 2
    # skip near-degenerate triangles, rays in the plane and origins on the target
    if area < 1e-2 or ray_len < 1e-2 or abs(float((d.detach() @ n)[0])) < 1e-2 * ray_len * float(n.norm()):
        return
    for backend in ("torch", "embree") if embree_available() else ("torch",):
        hits = ray_mesh_hits(v, torch.tensor([[0, 1, 2]]), o, d, backend=backend)
        assert hits.hit.tolist() == [True]
        p = o + hits.t[:, None] * d
        assert abs(float(((p - v[0]) @ n).detach().squeeze())) <= 1e-9 * float(n.norm())  # on the plane
        torch.testing.assert_close(p.detach(), target[None], rtol=0, atol=1e-9)
        torch.testing.assert_close(hits.bary[0].detach(), torch.tensor([1 - u - w, u, w], dtype=D), rtol=0, atol=1e-9)
        assert finite(*grads(hits.t.sum() + hits.bary.square().sum(), [v, d]))


@pytest.mark.parametrize("backend", BACKENDS)
def test_degenerate_triangles_in_front_are_never_hit(backend):
    """Collinear and single-point triangles between the origins and a real triangle: the real one is hit."""
    v = torch.tensor([[0.0, 0, 2], [1, 0, 2], [2, 0, 2], [0.2, 0.2, 2], [0.2, 0.2, 2], [0.2, 0.2, 2],
                      [0.0, 0, 1], [1, 0, 1], [0, 1, 1]], dtype=D, requires_grad=True)  # fmt: skip
    f = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    o = torch.tensor([[0.5, 0.0, 3], [0.2, 0.2, 3], [0.0, 0.0, 3], [0.4, 0.4, 3]], dtype=D, requires_grad=True)
    d = torch.tensor([[0.0, 0, -1]] * 4, dtype=D)
    hits = ray_mesh_hits(v, f, o, d, backend=backend)
    assert hits.face.tolist() == [2, 2, 2, 2]  # through the segment, the point, a vertex, an edge
    torch.testing.assert_close(hits.t, torch.full((4,), 2.0, dtype=D), rtol=0, atol=1e-12)
    assert finite(*grads(hits.t.sum() + hits.bary.square().sum(), [v, o]))
    # the degenerate triangles' own Möller–Trumbore terms stay finite too
    for a, b, c in ((v[0], v[1], v[2]), (v[3], v[4], v[5])):
        t, u, w, det = moller_trumbore(o, d, a, b, c)
        assert float(det.detach().abs().max()) == 0.0 and finite(t, u, w)
        assert finite(*grads(t.sum() + u.sum() + w.sum(), [v, o]))


# ----------------------------------------------------------------- the hybrid renderer
def sphere_mesh(dtype=torch.float32, radius=0.3, degenerate=False) -> PosedMesh:
    """An icosphere 'body' with identity skinning (posed = canonical), optionally with degenerate faces."""
    s = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    v = torch.tensor(s.vertices, dtype=dtype)
    f = torch.tensor(s.faces, dtype=torch.int64)
    if degenerate:  # a zero-area sliver and a collapsed face on the near side
        f = torch.cat([f, torch.tensor([[0, 0, 1], [5, 5, 5]])])
    eye = torch.eye(3, 4, dtype=dtype).expand(len(v), 3, 4)
    skin = deformer.prepare(v, eye, torch.zeros_like(v), eye, torch.ones(len(v), 1, dtype=dtype), 0.01, 0.2)
    return PosedMesh(v, f, torch.full((len(v), 3), 0.5, dtype=dtype), v[:, :2] * 100, skin)


def shell(x: torch.Tensor):
    """Colour and density of a 5/m shell outside the sphere of radius 0.3."""
    r = x.norm(dim=-1)
    return torch.stack([r, 1 - r, 0.5 * r], -1).clamp(0, 1), torch.where(r > 0.3, 5.0 * (1 + r), 0.0 * r)


def extreme_rays(mesh: PosedMesh):
    """Rays along -z through a vertex, along an edge, tangent to the sphere, grazing it, from 1e6 away."""
    v = mesh.vertices.detach()
    top = v[v[:, 2].argmax()]
    front = mesh.faces[v[mesh.faces].mean(1)[:, 2].argmax()]  # the face nearest the camera, beside ``top``
    a, b = front.tolist()[:2]
    mid = (v[a] + v[b]) / 2
    rim = v[v[:, 0].argmax()]
    xy = torch.stack([top[:2], mid[:2], rim[:2], rim[:2] + torch.tensor([1e-7, 0], dtype=v.dtype),
                      torch.tensor([0.0, 0.0], dtype=v.dtype), torch.tensor([1e6, 0.0], dtype=v.dtype)])  # fmt: skip
    z = torch.tensor([2.0, 2.0, 2.0, 2.0, 1e6, 2.0], dtype=v.dtype)
    origins = torch.cat([xy, z[:, None]], -1)
    return origins, torch.tensor([[0.0, 0, -1]], dtype=v.dtype).expand(len(xy), 3).clone()


@pytest.mark.parametrize("degenerate", [False, True])
def test_render_rays_through_vertices_edges_and_tangents(degenerate):
    mesh = sphere_mesh(degenerate=degenerate)
    verts = mesh.vertices.clone().requires_grad_()
    mesh.vertices, mesh.uv = verts, verts[:, :2] * 100
    o, d = extreme_rays(mesh)
    o.requires_grad_()
    st_ = RenderSettings(samples=12, box_margin=0.3, max_dist=0.1, perturb=False)
    bg = torch.ones(3)
    out = render_rays(mesh, o, d, o.detach()[:, :2] * 100, bg, st_, shell)
    assert out.hit[[0, 1, 4]].tolist() == [True, True, True] and not bool(out.hit[5])
    assert finite(out.rgb, out.nerf_mask, out.silhouette, out.mesh_rgb)
    assert bool((out.nerf_mask >= 0).all()) and bool((out.nerf_mask <= 1).all())
    torch.testing.assert_close(out.rgb[5], bg, rtol=0, atol=0)  # 1e6 off to the side: the background
    torch.testing.assert_close(out.mesh_rgb[out.hit], torch.full((int(out.hit.sum()), 3), 0.5), rtol=0, atol=1e-6)
    assert finite(*grads(out.rgb.sum() + out.silhouette.sum(), [verts, o]))


def test_render_rays_float32_agrees_with_float64():
    res = {}
    for dtype in (torch.float32, D):
        mesh = sphere_mesh(dtype)
        o, d = extreme_rays(mesh)
        gen = torch.Generator().manual_seed(0)
        o = torch.cat([o[:4], torch.cat([0.6 * torch.rand(40, 2, generator=gen) - 0.3, torch.full((40, 1), 2.0)], 1)
                       .to(dtype)])  # fmt: skip
        d = d[:1].expand(len(o), 3)
        st_ = RenderSettings(samples=16, box_margin=0.3, max_dist=0.1, perturb=False)
        res[dtype] = render_rays(mesh, o, d, o[:, :2] * 100, torch.ones(3, dtype=dtype), st_, shell)
    a, b = res[torch.float32], res[D]
    assert torch.equal(a.hit, b.hit)
    torch.testing.assert_close(a.rgb.double(), b.rgb, rtol=0, atol=1e-4)
    torch.testing.assert_close(a.nerf_mask.double(), b.nerf_mask, rtol=0, atol=1e-4)


def test_no_rays_render_and_cost_nothing():
    mesh = sphere_mesh()
    none = torch.zeros(0, 3)
    out = render_rays(mesh, none, none, none[:, :2], torch.ones(3), RenderSettings(samples=8), shell)
    assert out.rgb.shape == (0, 3) and out.samples_evaluated == 0


@pytest.mark.parametrize("dtype", [torch.float32, D])
def test_silhouette_of_triangles_collapsed_to_a_point(dtype):
    """A camera scale near 0 collapses the mesh onto one pixel: p = 1/2 per (zero-area) triangle there."""
    uv = torch.full((6, 2), 16.0, dtype=dtype) + 1e-9 * torch.arange(12, dtype=dtype).view(6, 2)
    uv.requires_grad_()
    faces = torch.tensor([[0, 1, 2], [3, 4, 5], [0, 2, 4]])
    pixels = torch.tensor([[16.0, 16.0], [16.0, 18.0], [1e6, -1e6]], dtype=dtype)
    cov = soft_silhouette(uv, faces, pixels, sigma=0.5, k=16)
    assert finite(*grads(cov.sum(), [uv]))
    torch.testing.assert_close(cov[0], torch.tensor(1 - 0.5**3, dtype=dtype), rtol=0, atol=1e-6)
    cov = cov.detach()
    p_far = 1 / (1 + math.exp(8.0))  # 2 px away: sigmoid(-2² / 0.5) each
    assert float(cov[1]) == pytest.approx(1 - (1 - p_far) ** 3, rel=1e-4)
    assert float(cov[2]) == 0.0


# ----------------------------------------------------------------- distance grid
def test_distance_grid_lookup_far_and_non_finite_points_is_inf_without_overflow():
    """Points 1e18 away (a box entry of an axis-parallel ray) used to overflow the int64 voxel index."""
    for method in ("scipy", "torch"):
        grid = distance_grid.build(torch.tensor([[0.0, 0, 0]], dtype=D), cell=0.02, pad=0.1, method=method)
        pts = torch.tensor([[0.0, 0, 0], [0.04, 0, 0], [1e18, 0, 0], [0, -1e18, 0], [math.inf, 0, 0],
                            [math.nan, 0, 0], [-math.inf, 0, 0], [0, 0, 1e300]], dtype=D)  # fmt: skip
        out = distance_grid.lookup(grid, pts)
        assert out[0] == 0.0 and float(out[1]) == pytest.approx(0.04)
        assert torch.isinf(out[2:]).all()


# ----------------------------------------------------------------- backward skinning
def posed_tree(pose_angle: float, dtype=D):
    model = soft_tree_model().to(dtype=dtype)
    gen = torch.Generator().manual_seed(0)
    axes = torch.nn.functional.normalize(torch.randn(1, 4, 3, generator=gen, dtype=D), dim=-1)
    out = lbs(model, torch.tensor([[5.0, -5.0]], dtype=dtype), (pose_angle * axes).to(dtype))
    canon = lbs(model, torch.zeros(1, 2, dtype=dtype), model.canonical_pose[None]).vertex_transforms_3x4[0]
    frame = deformer.prepare(out.vertices[0], out.vertex_transforms_3x4[0], out.rest_vertices[0] - model.v_template,
                             canon, model.weights)  # fmt: skip
    return model, out, frame


@settings(max_examples=30, deadline=None)
@given(
    angle=st.sampled_from(ANGLES + [0.5]),
    vertex=st.integers(0, 19),
    offset=st.tuples(*[st.floats(-0.1, 0.1)] * 3),
)
def test_backward_then_forward_skinning_returns_the_point(angle, vertex, offset):
    model, out, frame = posed_tree(angle)
    x = out.vertices[0, vertex].detach() + torch.tensor(offset, dtype=D)
    x = x[None].requires_grad_()
    d = deformer.deform(frame, x, k=6, sigma=0.1, max_dist=0.2)
    assert bool(d.valid.all()) and finite(d.canonical)
    idx, dist = deformer.knn(frame, x.detach(), 6)
    alpha = deformer.blend_weights(frame, idx, dist, 0.1)
    M_inv = deformer.affine_inverse((alpha[..., None, None] * frame.to_canonical[idx]).sum(1))  # forward map
    back = (M_inv[..., :3] @ d.canonical[..., None]).squeeze(-1) + M_inv[..., 3]
    torch.testing.assert_close(back.detach(), x.detach(), rtol=0, atol=1e-9)
    assert finite(*grads(d.canonical.sum(), [x]))


@pytest.mark.parametrize("far", [1e6, 1e18])
def test_points_far_from_every_vertex_in_float32(far):
    _, _, frame = posed_tree(1e3, torch.float32)
    x = torch.tensor([[far, 0, 0], [0, -far, far], [far, far, far]], requires_grad=True)
    d = deformer.deform(frame, x)
    assert d.valid.tolist() == [False] * 3 and finite(d.distance, d.posed_ref)
    assert bool((d.distance > 0.5 * far).all())
    assert finite(*grads(d.distance.sum() + d.posed_ref.sum(), [x]))


# ----------------------------------------------------------------- LBS
@pytest.mark.parametrize("angle", ANGLES)
def test_lbs_beyond_pi_is_finite_periodic_and_precision_independent(angle):
    model = soft_tree_model()
    axis = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8], dtype=D), dim=0)
    pose = (angle * axis).expand(1, 4, 3).float().double()  # the same angle in both precisions
    betas = torch.tensor([[5.0, -5.0]], dtype=D)  # ±5σ
    res = {}
    for dtype in (torch.float32, D):
        p = pose.to(dtype).clone().requires_grad_()
        b = betas.to(dtype).clone().requires_grad_()
        out = lbs(model.to(dtype=dtype), b, p)
        assert finite(out.vertices, out.joints, *grads(out.vertices.square().sum(), [p, b]))
        res[dtype] = out.vertices.detach()
    # at 1e3 rad float32 resolves the angle's norm to ~6e-5 rad (its ulp): measured errors ~9e-5 m there, ~6e-7 below
    torch.testing.assert_close(res[torch.float32].double(), res[D], rtol=0, atol=2e-4 if abs(angle) > 100 else 2e-6)
    # the rotation only depends on the angle modulo 2π
    a = float(pose[0, 0].norm())
    R = batch_rodrigues(pose[0, :1])
    wrapped = math.remainder(a, 2 * math.pi) * pose[0, :1] / a
    torch.testing.assert_close(R, batch_rodrigues(wrapped), rtol=0, atol=1e-12 * max(1.0, abs(angle)))


def test_lbs_at_plus_minus_5_sigma_is_exactly_linear():
    model = soft_tree_model()
    zero = torch.zeros(1, 4, 3, dtype=D)
    for betas in ([[5.0, 5.0]], [[-5.0, -5.0]], [[5.0, -5.0]]):
        b = torch.tensor(betas, dtype=D)
        out = lbs(model, b, zero)
        torch.testing.assert_close(out.vertices[0], model.v_template + model.shapedirs @ b[0], rtol=0, atol=1e-12)


# ----------------------------------------------------------------- cameras
@pytest.mark.parametrize("scale", [1e-8, 1e-6])
def test_orthographic_scale_near_zero(scale):
    s = torch.tensor(scale, dtype=D, requires_grad=True)
    t = torch.tensor([0.1, -0.2], dtype=D, requires_grad=True)
    cam = OrthographicCamera(s, t, 32, 32)
    uv = torch.tensor([[0.5, 0.5], [31.5, 31.5], [16.0, 16.0], [16.0, 31.5]], dtype=D)
    o, d = cam.rays(uv)
    ndc = 2 * uv / 32 - 1
    torch.testing.assert_close(o[:, 0], ndc[:, 0] / scale - 0.1, rtol=1e-12, atol=1e-9)
    assert finite(o, d)
    (g_s,) = torch.autograd.grad(o[:, 0].sum(), [s])
    torch.testing.assert_close(g_s, -ndc[:, 0].sum() / scale**2, rtol=1e-12, atol=0)
    back, _ = cam.project(o)  # and back onto the pixels
    torch.testing.assert_close(back, uv, rtol=0, atol=1e-6)
    pts = torch.tensor([[0.3, 1.2, 0.0], [-1e3, 1e3, 5.0]], dtype=D)
    uv2, _ = cam.project(pts)
    assert finite(uv2, *grads(uv2.sum(), [s, t]))
    torch.testing.assert_close(uv2[0], torch.full((2,), 16.0, dtype=D), rtol=0, atol=1e-3)  # all near the centre


def test_pinhole_points_on_the_camera_plane_and_far_away():
    """A point at depth 0 used to project to NaN (and crash the silhouette's KD-tree)."""
    R, t = look_at(torch.tensor([0.0, 0, 3]), torch.zeros(3), torch.tensor([0.0, 1, 0]))
    K = torch.tensor([[40.0, 0, 16], [0, 40, 16], [0, 0, 1]])
    for dist in (torch.zeros(5), torch.tensor([-0.04, 0.01, 0.0, 0.0, 0.0])):
        cam = PinholeCamera(K, R, t, dist, 32, 32)
        pts = torch.tensor([[0.1, 0.2, 3.0], [0.0, 0.0, 3.0], [0.0, 0, -1e6], [0.0, 0, 2.0]], requires_grad=True)
        uv, z = cam.project(pts)
        assert finite(uv, *grads(uv.sum(), [pts]))
        assert z[:2].tolist() == [0.0, 0.0]
        torch.testing.assert_close(uv[1:3], torch.full((2, 2), 16.0), rtol=0, atol=1e-4)  # on the axis, far
        if not dist.any():  # 0.1 m right of the axis on the camera plane: f · 0.1 / MIN_DEPTH px right
            assert float(uv[0, 0].detach()) == pytest.approx(40 * 0.1 / MIN_DEPTH + 16, rel=1e-6)
    # rays through the image corners stay unit and finite
    o, d = cam.rays(torch.tensor([[0.0, 0.0], [32.0, 32.0], [0.0, 32.0]]))
    assert finite(o, d)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(3))


# ----------------------------------------------------------------- losses with empty and one-pixel masks
HUBER_1 = 0.1 * (1 - 0.05)
"""Huber(δ = 0.1) of a unit residual."""


@pytest.mark.parametrize("rays", [0, 1, 7])
@pytest.mark.parametrize("mask", ["empty", "one"])
def test_losses_with_empty_and_single_pixel_masks(rays, mask):
    m = torch.zeros(rays, dtype=D)
    if mask == "one" and rays:
        m[rays // 2] = 1.0
    sil = torch.ones(rays, dtype=D, requires_grad=True)  # the mesh covers every ray
    nerf = torch.zeros(rays, dtype=D, requires_grad=True)
    rgb = torch.full((rays, 3), 0.5, dtype=D, requires_grad=True)
    target = torch.zeros(rays, 3, dtype=D)
    skin_color = torch.tensor([0.5, 0.5, 0.5], dtype=D)
    terms = {
        "pixel": L.pixel(rgb, target), "exterior": L.exterior(nerf, m), "silhouette": L.silhouette(sil, m),
        "interior_mask": L.interior_mask(sil, m), "skin": L.skin(rgb, target, m), "inside": L.inside(sil, m),
        "skin_inside": L.skin_inside(rgb, skin_color, m),
    }  # fmt: skip
    for name, value in terms.items():
        assert finite(value, *grads(value, [rgb, nerf, sil])), name
    n, ones = max(rays, 1), float(m.sum())
    v = {name: float(value.detach()) for name, value in terms.items()}
    assert v["pixel"] == pytest.approx(0.1 * 0.45 * rays / n)  # residual 0.5 ≥ δ: δ (0.5 - δ / 2) each
    assert v["exterior"] == pytest.approx(ones / n)
    assert v["silhouette"] == pytest.approx(HUBER_1 * (rays - ones) / n)
    assert v["inside"] == pytest.approx(HUBER_1 * (rays - ones) / n)
    assert v["interior_mask"] == 0.0 and v["skin_inside"] == 0.0
    assert v["skin"] == pytest.approx(0.1 * 0.45 * ones / n)
    total = L.total(terms, L.LossWeights())
    assert finite(total, *grads(total, [rgb, nerf, sil]))


# ----------------------------------------------------------------- fields
@pytest.mark.parametrize("encoding", ["grid", "pe"])
def test_nerf_far_outside_its_box(encoding):
    torch.manual_seed(0)
    spec = FieldSpec(encoding=encoding, levels=2, features=2, base_res=4, max_res=8, num_freqs=4, depth=2, width=16)
    field = NeRFField(spec, torch.tensor([[-1.0, -1, -1], [1.0, 1, 1]]))
    rows = [[0.0, 0, 0], [5.0, 0, 0], [1e6, -1e6, 0], [1e30, 1e30, -1e30]]
    if encoding == "grid":  # zero padding reads 0 even at the float32 limit and at infinity
        rows += [[-3e38, 0, 3e38], [math.inf, 0, 0]]
    x = torch.tensor(rows, requires_grad=True)
    rgb, sigma = field(x)
    assert finite(rgb, sigma) and bool((sigma >= 0).all()) and bool(((rgb >= 0) & (rgb <= 1)).all())
    (rgb.sum() + sigma.sum()).backward()
    assert finite(x.grad, *[p.grad for p in field.parameters()])
    if encoding == "grid":  # beyond one cell outside, every point reads zero features: one value
        torch.testing.assert_close(sigma[1:], sigma[1].expand(len(rows) - 1), rtol=0, atol=0)
        assert float(x.grad[1:].abs().max()) == 0.0


# ----------------------------------------------------------------- end to end
def blob_body() -> BodyModel:
    """An ellipsoid 'body' (162 vertices) with a root and two child joints, soft weights, every region."""
    s = trimesh.creation.icosphere(subdivisions=2)
    v = torch.tensor(s.vertices, dtype=torch.float32) * torch.tensor([0.2, 0.5, 0.15])
    gen = torch.Generator().manual_seed(0)
    y = v[:, 1]
    w = torch.stack([torch.full_like(y, 0.2), 4 * torch.relu(y) + 1e-3, 4 * torch.relu(-y) + 1e-3], 1)
    V = len(v)
    return BodyModel(
        name="blob", v_template=v, faces=torch.tensor(s.faces, dtype=torch.int64),
        shapedirs=0.02 * torch.randn(V, 3, 4, generator=gen),
        joints_template=torch.tensor([[0.0, 0, 0], [0, 0.25, 0], [0, -0.25, 0]]),
        joints_shapedirs=0.02 * torch.randn(3, 3, 4, generator=gen), parents=torch.tensor([-1, 0, 0]),
        joint_names=["root", "up", "down"], weights=w / w.sum(1, keepdim=True), regions=torch.arange(V) % 6,
        canonical_pose=torch.zeros(3, 3), posedirs=0.005 * torch.randn(V, 3, 18, generator=gen),
    ).validate("blob")  # fmt: skip


def tiny_avatar(camera, poses, transl) -> tuple[HybridAvatar, object]:
    grid = FieldSpec(encoding="grid", levels=2, features=2, base_res=4, max_res=8, depth=1, width=8)
    st_ = resolve("fast", {"render": {"samples": 8}})
    spec = AvatarSpec(nerf=grid, offsets=grid, albedo=grid, render=st_.avatar.render,
                      deformation=FieldSpec(encoding="pe", num_freqs=2, depth=1, width=8))  # fmt: skip
    init = InitParams(betas=torch.tensor([5.0, -5.0, 5.0, -5.0]), poses=poses, transl=transl, camera=camera)
    torch.manual_seed(0)
    return HybridAvatar(blob_body(), spec, init, torch.tensor([0.8, 0.6, 0.5]), torch.ones(3), 32), st_


def _frame_losses(model, st_, frame: int, single_pixel: bool):
    jj, ii = torch.meshgrid(torch.arange(0, 32, 2), torch.arange(0, 32, 2), indexing="xy")  # every other pixel
    pixels = torch.stack([jj.reshape(-1) + 0.5, ii.reshape(-1) + 0.5], -1)
    R = len(pixels)
    person, exterior, interior = torch.zeros(R), torch.zeros(R), torch.zeros(R)
    if single_pixel:  # the image centre
        person[R // 2 + 8] = exterior[R // 2 + 8] = 1.0
    target = torch.rand(R, 3, generator=torch.Generator().manual_seed(frame))
    batch = RayBatch(frame, pixels, target, person, exterior, interior)
    model.zero_grad(set_to_none=True)
    terms, r = loss_terms(model, batch, st_, torch.tensor([0.8, 0.6, 0.5]))
    loss = L.total(terms, st_.weights)
    loss.backward()
    return terms, r, target


def _assert_every_gradient_finite(model, frame):
    for name, p in model.named_parameters():
        assert p.grad is None or finite(p.grad), f"frame {frame}: non-finite gradient of {name}"
    assert model.poses.grad is not None and model.betas.grad is not None


def test_avatar_at_extreme_orthographic_frames():
    """Frames: ordinary, joint angles beyond π, camera scale 1e-6, translated 1e3 m away."""
    N = 4
    poses = torch.zeros(N, 3, 3)
    poses[1] = torch.tensor([[0.0, 3 * math.pi, 0], [1e3, 0, 0], [0, 0, 2 * math.pi]])
    transl = torch.zeros(N, 3)
    transl[3] = torch.tensor([1e3, -1e3, 0.0])
    cam = OrthographicCamera(torch.tensor([1.5, 1.5, 1e-6, 1.5]), torch.zeros(N, 2), 32, 32)
    model, st_ = tiny_avatar(cam, poses, transl)
    for frame in range(N):
        terms, r, target = _frame_losses(model, st_, frame, single_pixel=frame % 2 == 1)
        assert all(finite(v) for v in terms.values()), terms
        _assert_every_gradient_finite(model, frame)
        assert finite(r.rgb, r.silhouette, r.nerf_mask)
        if frame == 2:  # the body collapsed into one pixel: no ray hits it, the silhouette (exact coverage) is 0
            assert float(r.silhouette.detach().abs().sum()) == 0.0 and finite(model.ortho_scale.grad[2])
        if frame <= 1:
            assert bool(r.hit.any()) and r.samples_evaluated > 0
        else:  # nothing is hit and nothing sampled: the pixel loss is the background's, exactly
            assert not bool(r.hit.any()) and r.samples_evaluated == 0
            torch.testing.assert_close(terms["pixel"].detach(), L.pixel(torch.ones_like(target), target))


def test_avatar_at_extreme_pinhole_frames():
    """Frames: ordinary, straddling the camera plane (vertices at depth 0), 1e4 m behind the subject."""
    R, t = look_at(torch.tensor([0.0, 0, 3]), torch.zeros(3), torch.tensor([0.0, 1, 0]))
    cam = PinholeCamera(torch.tensor([[40.0, 0, 16], [0, 40, 16], [0, 0, 1]]), R, t, torch.zeros(5), 32, 32)
    transl = torch.tensor([[0.0, 0, 0], [0.0, 0, 3], [0.0, 0, -1e4]])
    model, st_ = tiny_avatar(cam, torch.zeros(3, 3, 3), transl)
    with torch.no_grad():  # move the camera plane (z = t_z for this camera) exactly onto a vertex of frame 1
        model.cam_t[2] = model.posed_mesh(1)[0].vertices[0, 2]
        assert float(model.camera(1).project(model.posed_mesh(1)[0].vertices)[1].abs().min()) == 0.0
    for frame in range(3):
        terms, r, target = _frame_losses(model, st_, frame, single_pixel=True)
        assert all(finite(v) for v in terms.values()), terms
        _assert_every_gradient_finite(model, frame)
        assert finite(model.transl.grad[frame])
    assert not bool(r.hit.any()) and r.samples_evaluated == 0


def test_no_culling_builds_no_distance_grid_and_samples_everything_near():
    """max_dist 10 m (the paper's "no culling"): no metres-wide voxel grid; culling at 0.1 m keeps fewer samples."""
    import dataclasses

    from delta.models.avatar import GRID_REACH

    cam = OrthographicCamera(torch.tensor([1.5]), torch.zeros(1, 2), 32, 32)
    model, st_ = tiny_avatar(cam, torch.zeros(1, 3, 3), torch.zeros(1, 3))
    counts = {}
    for reach in (0.1, 10.0):
        model.spec = dataclasses.replace(model.spec, render=dataclasses.replace(model.spec.render, max_dist=reach))
        skin = model.posed_mesh(0)[0].skinning
        assert (skin.near is None) == (reach > GRID_REACH)
        _, r, _ = _frame_losses(model, st_, 0, single_pixel=False)
        counts[reach] = r.samples_evaluated
    assert counts[10.0] > counts[0.1] > 0
