"""A hair layer bound to the head: the nearest head vertex's map blended into the kNN's by d_body / d_head."""

from __future__ import annotations

import pytest
import torch

from delta.deformers.knn import deform, head_bound, prepare
from delta.fields.networks import LayeredNeRF
from delta.fields.spec import FieldSpec

D = torch.float64


def translations_frame(posed: torch.Tensor, shifts: torch.Tensor, weights: torch.Tensor, head: torch.Tensor,
                       span=None):  # fmt: skip
    """A frame whose vertex i maps posed space to canonical space by the translation ``shifts[i]`` (posed
    transforms the identity, canonical transforms translations, no displacement)."""
    V = len(posed)
    eye = torch.eye(3, dtype=D).expand(V, 3, 3)
    identity = torch.cat([eye, torch.zeros(V, 3, 1, dtype=D)], -1)
    canonical_T = torch.cat([eye, shifts[..., None]], -1)
    return prepare(posed, identity, torch.zeros(V, 3, dtype=D), canonical_T, weights, head=head, head_span=span)


def two_parts(span=None):
    """A 'head' of vertices around (0, 1, 0) moved by (0, 0, 1) and a 'shoulder' around the origin moved by
    (1, 0, 0); the two carry different skinning weights (``span``: the frame's head span)."""
    gen = torch.Generator().manual_seed(0)
    head = torch.tensor([0.0, 1.0, 0.0], dtype=D) + 0.01 * torch.randn(8, 3, generator=gen, dtype=D)
    shoulder = 0.01 * torch.randn(8, 3, generator=gen, dtype=D)
    posed = torch.cat([head, shoulder])
    shifts = torch.cat(
        [torch.tensor([[0.0, 0.0, 1.0]], dtype=D).expand(8, 3), torch.tensor([[1.0, 0.0, 0.0]], dtype=D).expand(8, 3)]
    )
    weights = torch.cat(
        [torch.tensor([[1.0, 0.0]], dtype=D).expand(8, 2), torch.tensor([[0.0, 1.0]], dtype=D).expand(8, 2)]
    )
    is_head = torch.cat([torch.ones(8, dtype=torch.bool), torch.zeros(8, dtype=torch.bool)])
    return translations_frame(posed, shifts, weights, is_head, span)


def test_a_point_nearest_the_head_goes_with_the_head():
    frame = two_parts()
    x = torch.tensor([[0.05, 1.1, 0.0], [-0.2, 0.9, 0.1]], dtype=D)
    d = deform(frame, x, k=6, sigma=0.1, max_dist=10.0)
    torch.testing.assert_close(
        head_bound(frame, x, d.canonical, d.distance), x + torch.tensor([0.0, 0.0, 1.0], dtype=D)
    )


def test_between_head_and_shoulder_the_share_is_the_ratio_of_the_distances():
    frame = two_parts()
    # on the shoulder's side, at distances a from the shoulder and b from the head: β = a / b
    x = torch.tensor([[0.3, 0.2, 0.0], [0.0, 0.1, 0.0], [0.6, 0.0, 0.0]], dtype=D)
    d = deform(frame, x, k=6, sigma=0.1, max_dist=10.0)
    torch.testing.assert_close(d.canonical, x + torch.tensor([1.0, 0.0, 0.0], dtype=D))  # kNN: the shoulder's
    a = (x[:, None] - frame.posed[8:]).norm(dim=-1).amin(1)
    b = (x[:, None] - frame.posed[:8]).norm(dim=-1).amin(1)
    beta = (a / b)[:, None]
    expected = x + beta * torch.tensor([0.0, 0.0, 1.0], dtype=D) + (1 - beta) * torch.tensor([1.0, 0.0, 0.0], dtype=D)
    torch.testing.assert_close(head_bound(frame, x, d.canonical, d.distance), expected)
    # lying on the shoulder, far from the head: within a few per cent of the shoulder's map
    on = torch.tensor([[0.0, 0.03, 0.0]], dtype=D)
    d = deform(frame, on, k=6, sigma=0.1, max_dist=10.0)
    shoulder = on + torch.tensor([1.0, 0.0, 0.0], dtype=D)
    assert float((head_bound(frame, on, d.canonical, d.distance) - shoulder).norm()) < 0.1


def test_by_height_the_share_rises_from_the_shoulders_to_the_head():
    frame = two_parts(span=(0.2, 0.6))
    # beside the shoulder (its kNN point the shoulder's: canonical height = y) at heights 0, 0.2, 0.3, 0.4
    # (below the span, at its foot, a quarter and half way up) and one beside the head (above the span)
    x = torch.tensor([[0.6, 0.0, 0.0], [0.6, 0.2, 0.0], [0.6, 0.3, 0.0], [0.6, 0.4, 0.0], [0.05, 1.1, 0.0]], dtype=D)
    d = deform(frame, x, k=6, sigma=0.1, max_dist=10.0)
    torch.testing.assert_close(d.canonical[:4], x[:4] + torch.tensor([1.0, 0.0, 0.0], dtype=D))
    beta = torch.tensor([0.0, 0.0, 0.25, 0.5, 1.0], dtype=D)[:, None]
    by_head = x + torch.tensor([0.0, 0.0, 1.0], dtype=D)
    expected = d.canonical + beta * (by_head - d.canonical)
    torch.testing.assert_close(head_bound(frame, x, d.canonical, d.distance), expected)
    # the distances play no part: the same heights farther out give the same shares
    far = x[:4] + torch.tensor([0.3, 0.0, 0.0], dtype=D)
    d = deform(frame, far, k=6, sigma=0.1, max_dist=10.0)
    # (the head's map moves a point by 1 along z, the shoulder's by none: the z moved is the head's share)
    torch.testing.assert_close((head_bound(frame, far, d.canonical, d.distance) - d.canonical)[:, 2], beta[:4, 0])


def test_continuous_where_the_nearest_vertex_changes_part():
    frame = two_parts()
    # along the segment from the shoulder to the head the nearest part switches near y = 0.5
    y = torch.linspace(0.3, 0.7, 401, dtype=D)
    x = torch.stack([torch.full_like(y, 0.2), y, torch.zeros_like(y)], -1)
    d = deform(frame, x, k=6, sigma=0.1, max_dist=10.0)
    c = head_bound(frame, x, d.canonical, d.distance)
    jumps = (c[1:] - c[:-1]).norm(dim=-1)
    assert float(jumps.max()) < 0.02  # steps of 1 mm in y: the map moves by centimetres at most, no jump
    kn = (d.canonical[1:] - d.canonical[:-1]).norm(dim=-1)
    assert float(kn.max()) > 0.5  # the kNN alone jumps from one part's map to the other's


def test_gradients_reach_the_maps_and_the_points():
    frame = two_parts()
    frame.to_canonical = frame.to_canonical.clone().requires_grad_(True)
    x = torch.tensor([[0.3, 0.4, 0.05]], dtype=D, requires_grad=True)
    d = deform(frame, x, k=6, sigma=0.1, max_dist=10.0)
    head_bound(frame, x, d.canonical, d.distance).sum().backward()
    assert frame.to_canonical.grad is not None and float(frame.to_canonical.grad[:8].abs().sum()) > 0
    assert x.grad is not None and torch.isfinite(x.grad).all()


def test_a_frame_without_the_head_says_so():
    frame = two_parts()
    plain = prepare(frame.posed, frame.to_canonical, torch.zeros_like(frame.posed), frame.to_canonical, frame.weights)
    x = torch.zeros(2, 3, dtype=D)
    with pytest.raises(ValueError, match="head"):
        head_bound(plain, x, x, x[:, 0])
    with pytest.raises(ValueError, match="no vertex"):
        translations_frame(frame.posed, torch.zeros(16, 3, dtype=D), frame.weights, torch.zeros(16, dtype=torch.bool))


def test_a_layer_reads_its_own_points():
    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    nerf = LayeredNeRF(FieldSpec(), box, ("clothing", "hair"))
    x = torch.rand(32, 3) - 0.5
    moved = x + 0.3
    with torch.no_grad():
        _, _, plain = nerf.with_layers(x)
        _, _, bound = nerf.with_layers(x, at={"hair": moved})
        _, _, hair_alone = nerf.with_layers(moved)
    torch.testing.assert_close(bound[:, 0], plain[:, 0])  # the clothing reads x
    torch.testing.assert_close(bound[:, 1], hair_alone[:, 1])  # the hair reads its own points
    assert float((bound[:, 1] - plain[:, 1]).abs().max()) > 0
