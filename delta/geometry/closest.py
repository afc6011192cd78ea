"""The closest point on a triangle to a point, for many pairs at once (Ericson's region tests)."""

from __future__ import annotations

import numpy as np


def closest_point_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The closest point to each p (M, 3) on triangle (a, b, c) (each (M, 3)), row by row.

    Ericson's region tests (Real-Time Collision Detection, 5.1.5), vectorised: the first of vertex A,
    B, edge AB, vertex C, edge AC, edge BC whose test holds, else the face's interior. A degenerate
    (zero-area) triangle is the union of its edges: the nearest point of its three segments.
    """
    ab, ac, ap = b - a, c - a, p - a
    bp, cp = p - b, p - c
    dot = lambda u, v: np.einsum("ij,ij->i", u, v)
    d1, d2 = dot(ab, ap), dot(ac, ap)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    safe = lambda x: np.where(x == 0, 1.0, x)
    t_ab = d1 / safe(d1 - d3)
    t_ac = d2 / safe(d2 - d6)
    t_bc = (d4 - d3) / safe((d4 - d3) + (d5 - d6))
    den = safe(va + vb + vc)
    v, w = vb / den, vc / den
    regions = [
        (d1 <= 0) & (d2 <= 0),  # vertex A
        (d3 >= 0) & (d4 <= d3),  # vertex B
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),  # edge AB
        (d6 >= 0) & (d5 <= d6),  # vertex C
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),  # edge AC
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),  # edge BC
    ]
    points = [a, b, a + t_ab[:, None] * ab, c, a + t_ac[:, None] * ac, b + t_bc[:, None] * (c - b)]
    out = a + v[:, None] * ab + w[:, None] * ac  # the face's interior
    for region, q in zip(regions[::-1], points[::-1]):  # the first region that holds wins
        out = np.where(region[:, None], q, out)
    n = np.cross(ab, ac)
    flat = (n * n).sum(1) <= 1e-24 * (ab * ab).sum(1) * (ac * ac).sum(1)
    flat |= ~np.isfinite(out).all(1)
    if flat.any():
        out[flat] = _closest_on_edges(p[flat], a[flat], b[flat], c[flat])
    return out


def _closest_on_edges(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The closest point to each p on the segments AB, BC, CA (for degenerate triangles)."""
    best, best_d2 = None, None
    for s, e in ((a, b), (b, c), (c, a)):
        se = e - s
        t = np.clip(np.einsum("ij,ij->i", p - s, se) / np.maximum((se * se).sum(1), 1e-300), 0.0, 1.0)
        q = s + t[:, None] * se
        d2 = ((p - q) ** 2).sum(1)
        if best is None:
            best, best_d2 = q, d2
        else:
            closer = d2 < best_d2
            best, best_d2 = np.where(closer[:, None], q, best), np.where(closer, d2, best_d2)
    return best
