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
        w0, w1, w2 = _cross2(b - a, p - a), _cross2(c - b, p - b), _cross2(a - c, p - c)
        area2 = _cross2(b - a, c - a)
        eps = torch.finfo(area2.dtype).eps
        scale = ((b - a) ** 2).sum(-1) + ((c - a) ** 2).sum(-1)
        nondegenerate = area2.abs() > eps * scale
        same = ((w0 >= 0) & (w1 >= 0) & (w2 >= 0)) | ((w0 <= 0) & (w1 <= 0) & (w2 <= 0))
        inside = same & nondegenerate
    return dist_sq, inside


def nearest_faces(uv, faces, pixels, k: int) -> torch.Tensor:
    """(R, min(k, F)) indices of the faces whose (detached) projected centroids are nearest each pixel."""
    centroids = uv.detach()[faces].mean(1)
    if centroids.device.type == "cpu":
        centroids = centroids.double()  # the KD-tree's precision, as the projected uv may be float32
    return PointIndex(centroids).query(pixels, k)[1].to(faces.device)


def soft_silhouette(uv, faces, pixels, sigma: float = 1.0, k: int = 16, face_mask=None) -> torch.Tensor:
    """Soft coverage of query pixels by projected triangles, differentiable wrt ``uv``.

    Args:
        uv: (V, 2) projected vertex positions in pixels (may require grad).
        faces: (F, 3) int64.
        pixels: (R, 2) query points in pixel coordinates.
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
    corners = uv.to(dtype)[faces[idx]]  # (R, k, 3, 2)
    p = pixels.to(dtype)[:, None, :]
    dist_sq, inside = point_triangle_distance_2d(p, corners[..., 0, :], corners[..., 1, :], corners[..., 2, :])
    sigma = max(float(sigma), torch.finfo(dtype).tiny)
    logit = (torch.where(inside, dist_sq, -dist_sq) / sigma).clamp(-_LOGIT_BOUND, _LOGIT_BOUND)
    # log(1 - sigmoid(x)) = -softplus(x), exact and finite for every x.
    log_empty = -torch.nn.functional.softplus(logit).sum(-1)
    return (-torch.expm1(log_empty)).clamp(0, 1)
