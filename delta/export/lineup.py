"""Do the exported meshes line up with the renders? Rasterise projected triangles, compare masks by IoU."""

from __future__ import annotations

import numpy as np


def _candidates(tri: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangle index, row and column of every pixel centre in each triangle's bounding box."""
    lo = np.ceil(tri.min(1) - 0.5).astype(np.int64)  # first pixel whose centre j + 0.5 >= u_min
    hi = np.floor(tri.max(1) - 0.5).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [width - 1, height - 1])
    nj, ni = np.maximum(hi[:, 0] - lo[:, 0] + 1, 0), np.maximum(hi[:, 1] - lo[:, 1] + 1, 0)
    count = nj * ni
    t = np.repeat(np.arange(len(tri)), count)
    k = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)  # index within the box
    return t, lo[t, 1] + k // nj[t], lo[t, 0] + k % nj[t]


def _edge(o: np.ndarray, e: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(N,) z of (e - o) × (q - o): the side of edge o -> e that q lies on."""
    return (e[:, 0] - o[:, 0]) * (q[:, 1] - o[:, 1]) - (e[:, 1] - o[:, 1]) * (q[:, 0] - o[:, 0])


def rasterize(uv: np.ndarray, depth: np.ndarray, faces: np.ndarray, height: int, width: int,
              batch: int = 200_000) -> np.ndarray:  # fmt: skip
    """(H, W) bool coverage of triangles with projected vertices ``uv`` (V, 2) in pixels.

    Pixel (i, j) is covered when its centre (u, v) = (j + 0.5, i + 0.5) (the cameras' convention)
    lies inside or on a triangle, whatever its winding. Faces with a vertex behind the camera
    (depth ≤ 0) are skipped.
    """
    mask = np.zeros((height, width), dtype=bool)
    faces = faces[(depth[faces] > 0).all(1)] if len(faces) else faces
    for s in range(0, len(faces), batch):
        tri = uv[faces[s : s + batch]]  # (T, 3, 2)
        t, i, j = _candidates(tri, height, width)
        if len(t) == 0:
            continue
        p = np.stack([j + 0.5, i + 0.5], -1)
        a, b, c = tri[t, 0], tri[t, 1], tri[t, 2]
        e0, e1, e2 = _edge(a, b, p), _edge(b, c, p), _edge(c, a, p)
        inside = ((e0 >= 0) & (e1 >= 0) & (e2 >= 0)) | ((e0 <= 0) & (e1 <= 0) & (e2 <= 0))
        mask[i[inside], j[inside]] = True
    return mask


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks (1 when both are empty)."""
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)
