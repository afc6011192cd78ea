"""Backward skinning over the k nearest posed vertices: round trips, blend weights, extremes, gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from delta.body.lbs import lbs
from delta.deformers import knn as knn_module
from delta.deformers.knn import affine_inverse, blend_weights, compose, deform, knn, prepare, weight_distance
from tests.conftest import soft_tree_model

D = torch.float64


def homogeneous(T: torch.Tensor) -> torch.Tensor:
    """(..., 3, 4) -> (..., 4, 4)."""
    bottom = torch.zeros_like(T[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([T, bottom], dim=-2)


def apply(T: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """(..., 3, 4) affine applied to (..., 3) points."""
    return (T[..., :3] @ x[..., None]).squeeze(-1) + T[..., 3]


def posed_setup(seed: int = 0):
    """The soft tree model posed with a random pose, betas, offsets and translation, and a
    non-zero canonical pose; returns (model, posed LBSOutput, canonical transforms, frame)."""
    model = soft_tree_model()
    model.canonical_pose = torch.tensor([[0, 0, 0.3], [0, 0, -0.4], [0.2, 0, 0], [0, 0.5, 0]], dtype=D)
    gen = torch.Generator().manual_seed(seed)
    pose = 0.6 * torch.randn(1, 4, 3, generator=gen, dtype=D)
    betas = torch.randn(1, 2, generator=gen, dtype=D)
    offsets = 0.02 * torch.randn(model.num_vertices, 3, generator=gen, dtype=D)
    transl = torch.randn(1, 3, generator=gen, dtype=D)
    out = lbs(model, betas, pose, offsets=offsets, transl=transl)
    canonical_T = lbs(model, torch.zeros(1, 2, dtype=D), model.canonical_pose[None]).vertex_transforms_3x4[0]
    frame = prepare(out.vertices[0], out.vertex_transforms_3x4[0], out.rest_vertices[0] - model.v_template,
                    canonical_T, model.weights)  # fmt: skip
    return model, out, canonical_T, frame


# ----------------------------------------------------------------- round trips
def test_posed_vertices_map_to_canonical_template_vertices():
    model, out, canonical_T, frame = posed_setup()
    # canonical space: the template in the canonical pose, G^c_i template_i
    canonical_vertices = apply(canonical_T, model.v_template)
    assert (canonical_vertices - model.v_template).abs().max() > 0.1  # the canonical pose is not the identity
    posed = out.vertices[0]
    torch.testing.assert_close(deform(frame, posed, k=1).canonical, canonical_vertices, rtol=0, atol=1e-5)
    # with k = 6, a small σ makes the neighbours with other skinning weights negligible
    torch.testing.assert_close(deform(frame, posed, k=6, sigma=0.01).canonical, canonical_vertices, rtol=0, atol=1e-5)
    # every per-vertex map sends its own posed vertex to its canonical vertex
    torch.testing.assert_close(apply(frame.to_canonical, posed), canonical_vertices, rtol=0, atol=1e-10)
    d = deform(frame, posed)
    assert bool(d.valid.all())
    torch.testing.assert_close(d.distance, torch.full_like(d.distance, 1e-6), rtol=1e-6, atol=0)  # sqrt floor


def test_per_vertex_maps_are_the_inverses_of_the_forward_maps():
    """affine_inverse(to_canonical_i) = G_i ∘ translate(d_i) ∘ (G^c_i)^-1, built here from 4x4 matrices."""
    model, out, canonical_T, frame = posed_setup(1)
    G = homogeneous(out.vertex_transforms_3x4[0])
    Gc = homogeneous(canonical_T)
    shift = torch.eye(4, dtype=D).repeat(model.num_vertices, 1, 1)
    shift[:, :3, 3] = out.rest_vertices[0] - model.v_template
    forward = G @ shift @ torch.linalg.inv(Gc)
    torch.testing.assert_close(homogeneous(affine_inverse(frame.to_canonical)), forward, rtol=0, atol=1e-10)
    torch.testing.assert_close(apply(forward[:, :3], apply(canonical_T, model.v_template)), out.vertices[0],
                               rtol=0, atol=1e-10)  # fmt: skip


def test_points_near_the_body_round_trip():
    model, out, canonical_T, frame = posed_setup(2)
    gen = torch.Generator().manual_seed(5)
    posed = out.vertices[0]
    x = posed[torch.randint(0, model.num_vertices, (40,), generator=gen)] + 0.08 * torch.randn(40, 3, generator=gen,
                                                                                              dtype=D)  # fmt: skip
    k, sigma = 6, 0.1
    d = deform(frame, x, k=k, sigma=sigma)

    # independent oracle: brute-force kNN, α from the formula, maps from 4x4 matrices
    dist_all = torch.cdist(x, posed)
    dist, idx = dist_all.topk(k, largest=False)
    w = model.weights[idx]
    logits = -dist * (w - w[:, :1]).norm(dim=-1) / (2 * sigma**2)
    alpha = torch.softmax(logits, -1)
    G_inv = torch.linalg.inv(homogeneous(out.vertex_transforms_3x4[0]))[:, :3]  # (V, 3, 4)
    disp = out.rest_vertices[0] - model.v_template
    per_vertex = apply(canonical_T[idx], apply(G_inv[idx], x[:, None].expand(-1, k, -1)) - disp[idx])
    expected = (alpha[..., None] * per_vertex).sum(1)
    torch.testing.assert_close(d.canonical, expected, rtol=0, atol=1e-9)
    torch.testing.assert_close(d.posed_ref, (alpha[..., None] * posed[idx]).sum(1), rtol=0, atol=1e-9)
    torch.testing.assert_close(d.distance, dist[:, 0], rtol=0, atol=1e-9)
    assert d.valid.tolist() == (dist[:, 0] < 0.2).tolist()

    # forward again with the inverse of the same α-weighted blend of the per-vertex maps
    M = (alpha[..., None, None] * frame.to_canonical[idx]).sum(1)
    back = apply(affine_inverse(M), d.canonical)
    torch.testing.assert_close(back, x, rtol=0, atol=1e-4)
    canonical_h = np.concatenate([d.canonical.numpy(), np.ones((40, 1))], 1)[..., None]
    back_np = np.linalg.solve(homogeneous(M).numpy(), canonical_h)
    np.testing.assert_allclose(back_np[:, :3, 0], x.numpy(), rtol=0, atol=1e-4)


# ----------------------------------------------------------------- extremes
@pytest.mark.parametrize("far", [1e3, 1e6])
def test_far_points_are_finite_and_invalid(far):
    model, out, canonical_T, frame = posed_setup(3)
    posed = out.vertices[0].detach().clone().requires_grad_()
    frame.posed = posed
    x = torch.tensor([[far, 0.0, 0.0], [0.0, -far, far], [far, far, far]], dtype=D, requires_grad=True)
    d = deform(frame, x)
    assert d.valid.tolist() == [False, False, False]
    assert bool(torch.isfinite(d.canonical).all()) and bool(torch.isfinite(d.posed_ref).all())
    assert bool((d.distance > 0.9 * far).all())
    (d.canonical.sum() + d.posed_ref.sum() + d.distance.sum()).backward()
    assert bool(torch.isfinite(x.grad).all()) and bool(torch.isfinite(posed.grad).all())


def test_point_exactly_on_a_vertex_has_finite_gradients():
    model, out, canonical_T, frame = posed_setup(4)
    posed = out.vertices[0].detach().clone().requires_grad_()
    frame.posed = posed
    x = posed.detach()[[0, 7, 13]].clone().requires_grad_()
    d = deform(frame, x)
    (d.canonical.sum() + d.distance.sum() + d.posed_ref.sum()).backward()
    assert bool(torch.isfinite(x.grad).all()) and bool(torch.isfinite(posed.grad).all())
    assert bool(d.valid.all())


def test_empty_query():
    _, _, _, frame = posed_setup()
    d = deform(frame, torch.zeros(0, 3, dtype=D))
    assert d.canonical.shape == (0, 3) and d.valid.shape == (0,) and d.valid.dtype == torch.bool


# ----------------------------------------------------------------- the rough map (culling before the kNN)
def test_rough_canonical_is_exact_where_every_vertex_moves_alike():
    """One rigid motion for every vertex: any blend of the maps is that motion, so the nearest vertex's is too."""
    gen = torch.Generator().manual_seed(7)
    v = torch.randn(300, 3, generator=gen, dtype=D) * 0.3
    R = torch.linalg.matrix_exp(torch.tensor([[0, -0.4, 0.2], [0.4, 0, -0.7], [-0.2, 0.7, 0]], dtype=D))
    G = torch.cat([R, torch.tensor([[0.1], [-0.3], [0.5]], dtype=D)], 1).expand(300, 3, 4)
    posed = apply(G, v)
    frame = prepare(posed, G, torch.zeros_like(v), torch.eye(3, 4, dtype=D).expand(300, 3, 4), torch.ones(300, 1, dtype=D),
                    near_cell=0.02, near_pad=0.2)  # fmt: skip
    x = posed[:50] + 0.05 * torch.randn(50, 3, generator=gen, dtype=D)
    rough, dist = knn_module.rough_canonical(frame, x)
    torch.testing.assert_close(rough, deform(frame, x).canonical, rtol=0, atol=1e-10)
    torch.testing.assert_close(rough, apply(affine_inverse(G[:1]), x), rtol=0, atol=1e-10)
    exact = deform(frame, x).distance
    assert float((dist - exact).abs().max()) <= math.sqrt(3) * 0.02 + 1e-6


def test_rough_canonical_names_the_nearest_vertex_map_on_a_posed_body():
    """On the posed tree model (bones bend: the maps differ), the rough point is mostly ``deform(k=1)``'s:
    the voxel's nearest vertex is the point's own nearest one."""
    model, out, canonical_T, _ = posed_setup(5)
    frame = prepare(out.vertices[0], out.vertex_transforms_3x4[0], out.rest_vertices[0] - model.v_template,
                    canonical_T, model.weights, near_cell=0.005, near_pad=0.1)  # fmt: skip
    gen = torch.Generator().manual_seed(8)
    x = out.vertices[0][torch.randint(model.num_vertices, (200,), generator=gen)]
    x = x + 0.02 * torch.randn(200, 3, generator=gen, dtype=D)
    rough, _ = knn_module.rough_canonical(frame, x)
    one = deform(frame, x, k=1).canonical
    same = (rough - one).norm(dim=-1) < 1e-9
    assert float(same.double().mean()) > 0.8  # the voxel's nearest vertex is mostly the true nearest
    assert not rough.requires_grad


def test_rough_canonical_needs_the_distance_grid():
    _, _, _, frame = posed_setup()
    with pytest.raises(ValueError, match="distance grid"):
        knn_module.rough_canonical(frame, torch.zeros(2, 3, dtype=D))


# ----------------------------------------------------------------- blend weights
def three_vertex_frame(weights: torch.Tensor):
    posed = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]], dtype=D)
    eye = torch.eye(3, 4, dtype=D).expand(3, 3, 4)
    return prepare(posed, eye, torch.zeros(3, 3, dtype=D), eye, weights)


def test_blend_weights_against_the_formula():
    weights = torch.tensor([[1.0, 0.0], [0.5, 0.5], [0.2, 0.8]], dtype=D)
    frame = three_vertex_frame(weights)
    x = torch.tensor([[0.2, 0.1, 0.0]], dtype=D)
    idx, dist = knn(frame, x, 3)
    assert idx.tolist() == [[0, 1, 2]]  # nearest first
    d = [math.sqrt(0.05), math.sqrt(0.65), math.sqrt(3.65)]
    torch.testing.assert_close(dist[0], torch.tensor(d, dtype=D), rtol=0, atol=1e-11)
    sigma = 0.5
    # ‖w_nn - w_i‖ = 0, √0.5, √1.28 (nn = vertex 0)
    wd = [0.0, math.sqrt(0.5), math.sqrt(1.28)]
    e = [math.exp(-di * wi / (2 * sigma**2)) for di, wi in zip(d, wd)]
    alpha = blend_weights(frame, idx, dist, sigma)
    torch.testing.assert_close(alpha[0], torch.tensor([v / sum(e) for v in e], dtype=D), rtol=0, atol=1e-10)
    torch.testing.assert_close(alpha.sum(-1), torch.ones(1, dtype=D), rtol=0, atol=1e-15)
    # identity maps: canonical = posed point; posed_ref = Σ α v_i
    out = deform(frame, x, k=3, sigma=sigma, max_dist=0.2)
    torch.testing.assert_close(out.canonical, x, rtol=0, atol=1e-14)
    ref = torch.tensor([e[1] / sum(e), 2 * e[2] / sum(e), 0.0], dtype=D)
    torch.testing.assert_close(out.posed_ref[0], ref, rtol=0, atol=1e-10)
    assert out.valid.tolist() == [False]  # 0.2236 > max_dist


def test_blend_weights_sum_to_one_and_never_underflow():
    _, out, _, frame = posed_setup(6)
    gen = torch.Generator().manual_seed(6)
    scale = torch.tensor([1e-2, 1.0, 1e4], dtype=D)[torch.randint(0, 3, (100, 1), generator=gen)]
    x = torch.randn(100, 3, generator=gen, dtype=D) * scale
    for sigma in (1e-3, 0.1, 10.0):
        idx, dist = knn(frame, x, 6)
        alpha = blend_weights(frame, idx, dist, sigma)
        assert bool(torch.isfinite(alpha).all()) and bool((alpha >= 0).all())
        torch.testing.assert_close(alpha.sum(-1), torch.ones(100, dtype=D), rtol=0, atol=1e-12)
        assert bool((alpha[:, 0] >= alpha.max(-1).values - 1e-15).all())  # the nearest vertex weighs most


def test_identical_skinning_weights_give_uniform_blend():
    frame = three_vertex_frame(torch.tensor([[0.3, 0.7]], dtype=D).expand(3, 2))
    x = torch.tensor([[0.2, 0.1, 0.0], [5.0, -3.0, 1.0]], dtype=D)
    idx, dist = knn(frame, x, 3)
    alpha = blend_weights(frame, idx, dist, 0.01)
    assert torch.equal(alpha, torch.full((2, 3), 1 / 3, dtype=D))


def test_weight_distance_over_distinct_pairs_equals_every_pair():
    """The per-pair shortcut gives the dense ‖w[idx[:, 0]] - w[idx]‖ exactly, repeated pairs included."""
    gen = torch.Generator().manual_seed(3)
    weights = torch.rand(40, 7, generator=gen, dtype=D)
    weights = weights / weights.sum(1, keepdim=True)
    idx = torch.randint(0, 40, (500, 6), generator=gen)
    idx[:250] = idx[250:]  # every neighbour list twice
    idx[:, 1] = idx[:, 0]  # a vertex paired with itself: 0
    dense = (weights[idx] - weights[idx[:, :1]]).norm(dim=-1)
    got = weight_distance(weights, idx)
    assert torch.equal(got, dense)
    assert bool((got[:, :2] == 0).all())


# ----------------------------------------------------------------- affine algebra
def random_affines(n: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    T = torch.randn(n, 3, 4, generator=gen, dtype=D)
    T[..., :3] += 3 * torch.eye(3, dtype=D)
    return T


def test_affine_inverse_and_compose_against_numpy():
    P, Q = random_affines(7, 0), random_affines(7, 1)
    Pn, Qn = homogeneous(P).numpy(), homogeneous(Q).numpy()
    np.testing.assert_allclose(homogeneous(affine_inverse(P)).numpy(), np.linalg.inv(Pn), rtol=0, atol=1e-12)
    np.testing.assert_allclose(homogeneous(compose(P, Q)).numpy(), Pn @ Qn, rtol=0, atol=1e-12)
    ident = compose(P, affine_inverse(P))
    torch.testing.assert_close(ident, torch.eye(3, 4, dtype=D).expand(7, 3, 4), rtol=0, atol=1e-12)
    x = torch.randn(7, 3, generator=torch.Generator().manual_seed(2), dtype=D)
    torch.testing.assert_close(apply(compose(P, Q), x), apply(P, apply(Q, x)), rtol=0, atol=1e-12)


# ----------------------------------------------------------------- gradients
def test_deform_gradcheck_wrt_points_and_posed_vertices():
    model, out, canonical_T, _ = posed_setup(7)
    posed = out.vertices[0].detach().clone().requires_grad_()
    posed_T = out.vertex_transforms_3x4[0].detach()
    disp = (out.rest_vertices[0] - model.v_template).detach()
    gen = torch.Generator().manual_seed(8)
    x = (posed.detach()[[1, 6, 11, 16]] + 0.05 * torch.randn(4, 3, generator=gen, dtype=D)).requires_grad_()

    def canon(points, posed):
        frame = prepare(posed, posed_T, disp, canonical_T, model.weights)
        return deform(frame, points, k=4, sigma=0.3).canonical

    assert torch.autograd.gradcheck(canon, (x, posed))
