"""Every loss term against hand-computed values on tiny tensors."""

from __future__ import annotations

import math

import pytest
import torch

from delta import losses
from delta.body.model import REGION
from delta.loss_weights import LossWeights

D = torch.float64


def t(*values):
    return torch.tensor(values, dtype=D)


def close(actual, expected, atol=1e-14):
    torch.testing.assert_close(actual, torch.tensor(expected, dtype=D), rtol=0, atol=atol)


def test_huber_quadratic_regime():
    # 0.5 (0.05² + 0.08² + 0²) / 3 = 0.5 (0.0025 + 0.0064) / 3
    close(losses.huber(t(0.05, -0.08, 0.0), 0.1), 0.5 * 0.0089 / 3)


def test_huber_linear_regime():
    # δ (|x| - δ/2): 0.1 (0.3 - 0.05) = 0.025, 0.1 (2 - 0.05) = 0.195
    close(losses.huber(t(0.3, -2.0), 0.1), (0.025 + 0.195) / 2)


def test_huber_mixed_and_continuous_at_delta():
    close(losses.huber(t(0.05, -0.3), 0.1), (0.00125 + 0.025) / 2)
    close(losses.huber(t(0.1), 0.1), 0.005)  # both branches give δ²/2 at |x| = δ
    close(losses.huber(t(0.1 + 1e-9), 0.1), 0.005 + 1e-10, atol=1e-15)
    # other δ: 1.0 (|3| - 0.5) = 2.5
    close(losses.huber(t(3.0), 1.0), 2.5)


def test_huber_gradient_is_clipped():
    x = t(0.05, -0.3, 2.0).requires_grad_()
    losses.huber(x, 0.1).backward()
    close(x.grad, [0.05 / 3, -0.1 / 3, 0.1 / 3])


def test_huber_empty_is_zero_and_differentiable():
    x = torch.zeros(0, 3, dtype=D, requires_grad=True)
    out = losses.huber(x, 0.1)
    assert out.shape == () and out.item() == 0.0
    out.backward()
    assert x.grad is not None and x.grad.shape == (0, 3)
    # pixel on empty batches too
    assert losses.pixel(torch.zeros(0, 3), torch.zeros(0, 3)).item() == 0.0


def test_pixel():
    rgb = t([0.5, 0.5, 0.5], [1.0, 0.0, 0.2])
    target = t([0.45, 0.5, 0.8], [1.0, 0.1, 0.2])
    # residuals 0.05, 0, -0.3, 0, -0.1, 0 -> 0.00125, 0, 0.025, 0, 0.005, 0
    close(losses.pixel(rgb, target, 0.1), (0.00125 + 0.025 + 0.005) / 6, atol=1e-12)


def test_exterior():
    close(losses.exterior(t(0.2, 1.0, 0.0, 0.5), t(0.0, 1.0, 1.0, 0.25)), (0.2 + 0.0 + 1.0 + 0.25) / 4)


def test_exterior_layers():
    """Hair's opacity against the hair mask, clothing's against the rest of the exterior, averaged."""
    masks = torch.tensor([[0.5, 0.1], [0.0, 1.0], [0.2, 0.2]], dtype=torch.float64)
    exterior, hair = t(1.0, 1.0, 0.0), t(0.25, 1.0, 0.0)
    clothing_err = (abs(0.5 - 0.75) + abs(0.0 - 0.0) + abs(0.2 - 0.0)) / 3
    hair_err = (abs(0.1 - 0.25) + abs(1.0 - 1.0) + abs(0.2 - 0.0)) / 3
    close(losses.exterior_layers(masks, ("clothing", "hair"), exterior, hair), (clothing_err + hair_err) / 2)
    close(losses.exterior_layers(masks[:, [1, 0]], ("hair", "clothing"), exterior, hair), (clothing_err + hair_err) / 2)
    with pytest.raises(ValueError, match="hair mask"):
        losses.exterior_layers(masks, ("clothing", "hair"), exterior, None)


def test_layer_shares():
    """The cross-entropy of each seen sample's layer shares against its pixel's layers, the samples weighted
    by their share of the ray's weight: by hand on two exterior rays; a ray off the exterior and one that
    sees no density add nothing."""
    shares = torch.tensor([[[0.5, 0.5], [0.9, 0.1]], [[0.2, 0.8], [0.6, 0.4]], [[0.5, 0.5], [0.5, 0.5]],
                           [[0.3, 0.7], [0.3, 0.7]]], dtype=D)  # fmt: skip
    weights = torch.tensor([[0.2, 0.6], [0.5, 0.0], [0.4, 0.4], [0.0, 0.0]], dtype=D)
    exterior, hair = t(1.0, 1.0, 0.0, 1.0), t(0.25, 1.0, 0.0, 1.0)
    # ray 0: q = (0.75, 0.25), ŵ = (0.25, 0.75); ray 1: q = (0, 1), ŵ = (1, 0)
    ray0 = -(
        0.25 * (0.75 * math.log(0.5) + 0.25 * math.log(0.5)) + 0.75 * (0.75 * math.log(0.9) + 0.25 * math.log(0.1))
    )
    ray1 = -math.log(0.8)
    close(losses.layer_shares(shares.log(), weights, ("clothing", "hair"), exterior, hair), (ray0 + ray1) / 2)
    flipped = losses.layer_shares(shares.log()[..., [1, 0]], weights, ("hair", "clothing"), exterior, hair)
    close(flipped, (ray0 + ray1) / 2)
    close(losses.layer_shares(shares.log(), weights, ("clothing", "hair"), t(0, 0, 0, 0), hair), 0.0)
    with pytest.raises(ValueError, match="hair mask"):
        losses.layer_shares(shares.log(), weights, ("clothing", "hair"), exterior, None)


def test_layer_shares_gradient_wins_back_a_lost_layer():
    """Densities e^raw make a share the softmax of the raws: the term's gradient at a raw is ŵ (share - q)
    (autograd against the closed form), and at a hair share of e^-30 on a hair pixel it is -ŵ, where the
    hair layer's opacity L1 (exterior_layers) gives it nothing to climb."""
    raw = torch.tensor([[[0.0, -30.0], [1.0, -29.0]]], dtype=D, requires_grad=True)  # (1 ray, 2 samples, 2)
    weights = torch.tensor([[0.25, 0.75]], dtype=D)
    exterior, hair = t(1.0), t(1.0)
    losses.layer_shares(torch.log_softmax(raw, -1), weights, ("clothing", "hair"), exterior, hair).backward()
    share = torch.softmax(raw.detach(), -1)
    expected = weights[..., None] * (share - torch.tensor([0.0, 1.0], dtype=D))
    torch.testing.assert_close(raw.grad, expected, rtol=1e-12, atol=1e-15)
    assert float(raw.grad[0, :, 1].sum()) < -0.999
    raw.grad = None
    opacity = (weights[..., None] * torch.softmax(raw, -1)).sum(1)  # (1, 2) each layer's opacity
    losses.exterior_layers(opacity, ("clothing", "hair"), exterior, hair).backward()
    assert float(raw.grad[0, :, 1].abs().max()) < 1e-12


def test_silhouette():
    # residuals 0.05, -1.0, 0 -> 0.00125, 0.095, 0
    close(losses.silhouette(t(0.05, 0.0, 1.0), t(0.0, 1.0, 1.0), 0.1), (0.00125 + 0.095) / 3, atol=1e-12)


def test_interior_mask():
    sil = t(0.5, 0.0, 0.95, 0.0)
    interior = t(1.0, 1.0, 1.0, 0.0)
    # interior * sil - interior: -0.5, -1, -0.05, 0 -> 0.045, 0.095, 0.00125, 0 (outside the body: free)
    close(losses.interior_mask(sil, interior, 0.1), (0.045 + 0.095 + 0.00125) / 4, atol=1e-12)


def test_skin():
    mesh_rgb = t([0.5, 0.5, 0.5], [0.0, 0.0, 0.0])
    target = t([0.45, 0.8, 0.5], [1.0, 1.0, 1.0])
    interior = t(1.0, 0.0)  # the second ray is not on the visible body
    # residuals 0.05, -0.3, 0 | 0, 0, 0 -> 0.00125, 0.025
    close(losses.skin(mesh_rgb, target, interior, 0.1), (0.00125 + 0.025) / 6, atol=1e-12)
    # a partial mask scales the residual: 0.5 * (-0.3) = -0.15 -> 0.01
    close(losses.skin(mesh_rgb[:1], target[:1], t(0.5), 0.1), (0.5 * 0.025**2 + 0.01) / 3, atol=1e-12)


def test_inside():
    sil = t(1.0, 0.3, 0.0, 0.04)
    person = t(0.0, 0.5, 1.0, 0.0)
    # relu(sil - person): 1, 0, 0, 0.04 -> 0.095, 0, 0, 0.0008
    close(losses.inside(sil, person, 0.1), (0.095 + 0.0008) / 4, atol=1e-12)


def test_empty_background():
    tau = t(2.0, 3.0, 5.0, 40.0)
    person = t(0.0, 0.25, 0.5, 1.0)
    # β = clamp(1 - 2 M): 1, 0.5, 0, 0 -> 2 + 1.5 + 0 + 0
    close(losses.empty_background(tau, person), 3.5 / 4)
    # its gradient in τ is β / R on every ray, however large τ is
    tau = tau.clone().requires_grad_(True)
    losses.empty_background(tau, person).backward()
    close(tau.grad, [0.25, 0.125, 0.0, 0.0])
    empty = torch.zeros(0, dtype=D, requires_grad=True)
    value = losses.empty_background(empty, torch.zeros(0, dtype=D))
    close(value, 0.0)
    value.backward()


def test_skin_inside():
    mesh_rgb = t([0.7, 0.5, 0.3], [0.0, 0.0, 0.0])
    skin_color = t(0.6, 0.5, 0.9)
    ext = t(1.0, 0.0)
    # residuals 0.1, 0, -0.6 | masked -> 0.005, 0, 0.055
    close(losses.skin_inside(mesh_rgb, skin_color, ext, 0.1), (0.005 + 0.055) / 6, atol=1e-12)


def test_edge_single_triangle():
    ref = t([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    verts = ref.clone()
    verts[2] = t(0.0, 2.0, 0.0)  # vertex 2 moved by (0, 1, 0)
    edges = torch.tensor([[0, 1], [1, 2], [0, 2]])
    # edge 0-1 unchanged; 1-2: (v1-v2) - (u1-u2) = (0,-1,0); 0-2: (0,-1,0) -> (0 + 1 + 1) / 3
    close(losses.edge(verts - ref, edges), 2.0 / 3)
    # a rigid translation costs nothing
    close(losses.edge(t(3.0, -1.0, 2.0).expand(3, 3), edges), 0.0)
    # scaling by 2: edge differences equal the reference edges: (1 + 2 + 1) / 3
    close(losses.edge(2 * ref - ref, edges), 4.0 / 3)
    # the textbook form from both meshes, on random ones: the same value
    g = torch.Generator().manual_seed(0)
    v, u = torch.randn(3, 3, generator=g, dtype=torch.float64), torch.randn(3, 3, generator=g, dtype=torch.float64)
    textbook = (((v[edges[:, 0]] - v[edges[:, 1]]) - (u[edges[:, 0]] - u[edges[:, 1]])) ** 2).sum(-1).mean()
    close(losses.edge(v - u, edges), float(textbook))


def test_offset_region_weights():
    offsets = t([0.1, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.3], [0.1, 0.1, 0.0])
    regions = torch.tensor([REGION["body"], REGION["hands"], REGION["eyes"], REGION["feet"]])
    weights = LossWeights().offset_region_weights
    # 2·0.01 + 12·0.04 + 3·0.09 + 2·0.02 = 0.02 + 0.48 + 0.27 + 0.04 = 0.81, over V = 4
    close(losses.offset(offsets, regions, weights), 0.81 / 4, atol=1e-12)
    # regions not named in the dict weigh 1
    close(losses.offset(offsets, regions, {"hands": 5.0}), (0.01 + 0.2 + 0.09 + 0.02) / 4, atol=1e-12)
    assert weights == {"body": 2.0, "face": 3.0, "hands": 12.0, "feet": 2.0, "eyes": 3.0, "mouth": 3.0}


def test_mesh_edges_two_triangles():
    faces = torch.tensor([[0, 1, 2], [2, 1, 3]])
    edges = losses.mesh_edges(faces)
    assert edges.tolist() == [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]
    assert losses.mesh_edges(torch.tensor([[0, 1, 2]])).tolist() == [[0, 1], [0, 2], [1, 2]]


def test_mesh_edges_are_every_faces_sides_once_in_order():
    faces = torch.randint(0, 300, (2000, 3), generator=torch.Generator().manual_seed(0))
    sides = {tuple(sorted((int(f[a]), int(f[b])))) for f in faces for a, b in ((0, 1), (1, 2), (2, 0))}
    assert losses.mesh_edges(faces).tolist() == [list(e) for e in sorted(sides)]


def test_total_weights_and_missing_terms():
    w = LossWeights(pixel=1.0, edge=500.0, inside=40.0)
    terms = {"pixel": torch.tensor(2.0, dtype=D), "edge": torch.tensor(0.01, dtype=D)}
    close(losses.total(terms, w), 2.0 + 5.0, atol=1e-12)
    close(losses.total({"inside": torch.tensor(0.5, dtype=D)}, w), 20.0)
    x = torch.tensor(0.3, dtype=D, requires_grad=True)
    losses.total({"pixel": x, "edge": 2 * x}, w).backward()
    close(x.grad, 1.0 + 1000.0)
    with pytest.raises(ValueError):
        losses.total({}, w)


def test_default_weights_match_the_paper():
    w = LossWeights()
    assert (w.pixel, w.exterior, w.silhouette, w.interior_mask, w.skin) == (1.0, 0.5, 0.001, 30.0, 1.0)
    assert (w.inside, w.skin_inside, w.edge, w.offset, w.huber_delta) == (40.0, 0.01, 500.0, 400.0, 0.1)


def test_face_points_hand_values():
    # 100-px image, δ 0.01 (1 px): 0.5 px off costs 0.5 (0.005)², 3-4-5 px off 0.01 (0.05 - 0.005)
    uv = t(10.0, 10.0, 20.0, 20.0, 30.0, 30.0).reshape(3, 2)
    target = t(10.5, 10.0, 23.0, 24.0, 0.0, 0.0).reshape(3, 2)
    near, far = 0.5 * 0.005**2, 0.01 * (0.05 - 0.005)
    close(losses.face_points(uv, target, t(1.0, 1.0, 0.0), 100), (near + far) / 2)  # the third: not seen
    close(losses.face_points(uv, target, t(1.0, 3.0, 0.0), 100), (near + 3 * far) / 4)
    close(losses.face_points(uv, target, t(0.0, 0.0, 0.0), 100), 0.0)  # no face in the frame: no term
    assert losses.face_points(uv, target, t(1.0, 1.0, 0.0), 100).isfinite()


def test_face_points_gradient_matches_finite_differences():
    uv = torch.tensor([[10.0, 10.0], [20.0, 21.0]], dtype=D, requires_grad=True)
    target, conf = t(10.6, 9.8, 23.0, 24.0).reshape(2, 2), t(1.0, 0.5)
    assert torch.autograd.gradcheck(lambda x: losses.face_points(x, target, conf, 100), (uv,))
