"""A soft, differentiable silhouette over the k nearest projected triangles.

SoftRas-style coverage: each triangle j contributes a probability
p_j = sigmoid(delta_j * d_j^2 / sigma), with d_j the 2D distance from the
pixel to the triangle's boundary and delta_j = +1 inside, -1 outside, and the
coverage is D = 1 - prod_j (1 - p_j). Only the k triangles whose centroids are
nearest to the pixel take part (a KD-tree query on detached centroids, not
differentiable), which keeps a 100k-triangle mesh cheap for a few thousand
pixels.

Shapes: R pixels, V vertices, F faces, k candidates. Device and dtype follow
the inputs.
"""

from __future__ import annotations

import torch

from delta.devices import host_paths
from delta.geometry.nearest import PointIndex

_LOGIT_BOUND = 1.0e4
"""|delta d^2 / sigma| is clamped here; beyond it p is 0 or 1 to any float precision."""


def _cross2(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _segment_distance_sq(p, a, b) -> torch.Tensor:
    """(...,) squared distance from p to segment ab; a point when a == b (finite gradients)."""
    ab, ap = b - a, p - a
    den = (ab * ab).sum(-1)
    eps = torch.finfo(den.dtype).eps
    t = torch.where(den > eps, (ap * ab).sum(-1) / den.clamp_min(eps), torch.zeros_like(den))
    q = a + t.clamp(0, 1)[..., None] * ab
    return ((p - q) ** 2).sum(-1)


def _inside(p: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    a, b, c = corners[..., 0, :], corners[..., 1, :], corners[..., 2, :]
    w0, w1, w2 = _cross2(b - a, p - a), _cross2(c - b, p - b), _cross2(a - c, p - c)
    area2 = _cross2(b - a, c - a)
    scale = ((b - a) ** 2).sum(-1) + ((c - a) ** 2).sum(-1)
    nondegenerate = area2.abs() > torch.finfo(area2.dtype).eps * scale
    same = ((w0 >= 0) & (w1 >= 0) & (w2 >= 0)) | ((w0 <= 0) & (w1 <= 0) & (w2 <= 0))
    return same & nondegenerate


def point_triangle_distance_2d(p, a, b, c) -> tuple[torch.Tensor, torch.Tensor]:
    """Squared distance from 2D points to a triangle's boundary, and whether they lie inside.

    Args:
        p, a, b, c: (..., 2), broadcast together.
    Returns:
        dist_sq: (...,) squared distance to the nearest of the three edges (the
            distance to the filled triangle is ``where(inside, 0, dist_sq)``).
        inside: (...,) bool, p inside or on the triangle (either orientation).
            A zero-area triangle has no inside: it is treated as its segments.
    """
    dist_sq = torch.minimum(
        torch.minimum(_segment_distance_sq(p, a, b), _segment_distance_sq(p, b, c)),
        _segment_distance_sq(p, c, a),
    )
    with torch.no_grad():
        inside = _inside(p, torch.stack(torch.broadcast_tensors(a, b, c), -2))
    return dist_sq, inside


def nearest_faces(uv, faces, pixels, k: int) -> torch.Tensor:
    """(R, min(k, F)) indices of the faces whose (detached) projected centroids are nearest each pixel."""
    centroids = uv.detach()[faces].mean(1)
    if host_paths(centroids.device):
        centroids = centroids.double()  # the KD-tree's precision, as the projected uv may be float32
    return PointIndex(centroids).query(pixels, k)[1].to(faces.device)


def _edges(p: torch.Tensor, corners: torch.Tensor):
    """Nearest point of each triangle's boundary: (t, w, edge) for p (R, 1, 2) and corners (R, k, 3, 2).

    t (R, k) is the nearest point's place on its edge (0 at the edge's first corner), w = p - q (R, k, 2)
    and edge (R, k) which edge (0: ab, 1: bc, 2: ca). A zero-length edge is its first corner."""
    a = corners
    b = corners.roll(-1, dims=-2)  # (R, k, 3, 2): the edges ab, bc, ca
    ab, ap = b - a, p[..., None, :] - a
    den = (ab * ab).sum(-1)
    eps = torch.finfo(den.dtype).eps
    t = torch.where(den > eps, (ap * ab).sum(-1) / den.clamp_min(eps), torch.zeros_like(den)).clamp(0, 1)
    w = ap - t[..., None] * ab
    d = (w * w).sum(-1)  # (R, k, 3)
    edge = d.argmin(-1, keepdim=True)
    return t.gather(-1, edge)[..., 0], w.gather(-2, edge[..., None].expand(*edge.shape, 2))[..., 0, :], edge[..., 0]


class _Coverage(torch.autograd.Function):
    """The coverage of :func:`soft_silhouette` with its gradient wrt the corners in closed form.

    A pixel's squared distance to a triangle's boundary is |w|², w = p - q, q the nearest boundary point,
    on edge (u, v) at t: d(|w|²)/du = -2 w (1 - t), d/dv = -2 w t (q is the minimiser, so t's own change
    adds nothing). The chain through the sigmoid and the product is two multiplications. Autograd through
    the same expressions keeps a dozen (R, k, 3, 2) intermediates and walks them back; this keeps t, w and
    the logits (tests/render/test_silhouette.py holds the two to each other)."""

    @staticmethod
    def forward(ctx, uv, tri, pixels, sigma):
        corners = uv[tri]  # (R, k, 3, 2)
        p = pixels[:, None, :]
        t, w, edge = _edges(p, corners)
        sign = torch.where(_inside(p, corners), 1.0, -1.0).to(uv.dtype)
        raw = sign * (w * w).sum(-1) / sigma
        logit = raw.clamp(-_LOGIT_BOUND, _LOGIT_BOUND)
        log_empty = -torch.nn.functional.softplus(logit).sum(-1)
        ctx.save_for_backward(tri, t, w, edge, sign, raw, logit, log_empty)
        ctx.sigma, ctx.num_vertices = sigma, uv.shape[0]
        return (-torch.expm1(log_empty)).clamp(0, 1)

    @staticmethod
    def backward(ctx, grad):
        tri, t, w, edge, sign, raw, logit, log_empty = ctx.saved_tensors
        live = (raw >= -_LOGIT_BOUND) & (raw <= _LOGIT_BOUND)
        g_logit = (grad * torch.exp(log_empty))[:, None] * torch.sigmoid(logit) * live  # (R, k)
        g_w = (g_logit * sign * (2.0 / ctx.sigma))[..., None] * w  # d loss / d w, w = p - q
        # q = (1 - t) u + t v on edge (u, v) = corners (edge, edge + 1 mod 3); dw/du = -(1 - t), dw/dv = -t
        first = tri.gather(-1, edge[..., None])[..., 0]
        second = tri.gather(-1, ((edge + 1) % 3)[..., None])[..., 0]
        out = grad.new_zeros(ctx.num_vertices, 2)
        out.index_add_(0, first.reshape(-1), (-(1 - t)[..., None] * g_w).reshape(-1, 2))
        out.index_add_(0, second.reshape(-1), (-t[..., None] * g_w).reshape(-1, 2))
        return out, None, None, None


def soft_silhouette(uv, faces, pixels, sigma: float = 1.0, k: int = 16, face_mask=None) -> torch.Tensor:
    """Soft coverage of query pixels by projected triangles, differentiable wrt ``uv``.

    Args:
        uv: (V, 2) projected vertex positions in pixels (may require grad).
        faces: (F, 3) int64.
        pixels: (R, 2) query points in pixel coordinates (not differentiated).
        sigma: softness in pixels^2 (a pixel on an edge of one triangle gets 0.5;
            at distance d inside/outside, sigmoid(+-d^2 / sigma)).
        k: candidate triangles per pixel, nearest projected centroids first.
            The choice is not differentiable; a triangle much larger than its
            neighbours may be missed when its centroid is far from the pixel.
        face_mask: optional (F,) bool, faces that take part (e.g. front-facing).
    Returns:
        (R,) coverage in [0, 1]: 1 - prod_j (1 - p_j), summed in log space, so
        finite for thousands of overlapping triangles and tiny sigma.
    """
    if face_mask is not None:
        faces = faces[face_mask]
    R = pixels.shape[0]
    dtype = torch.promote_types(uv.dtype, pixels.dtype)
    if faces.shape[0] == 0 or R == 0:
        return (uv.sum() * 0).to(dtype).expand(R).clone()
    idx = nearest_faces(uv, faces, pixels, k)  # (R, k)
    sigma = max(float(sigma), torch.finfo(dtype).tiny)
    return _Coverage.apply(uv.to(dtype), faces[idx], pixels.detach().to(dtype), sigma)
