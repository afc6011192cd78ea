"""How far a capture's exterior (clothing, hair) reaches beyond the fitted body, per body region.

In each analysed frame the fitted body is ray-cast into the image: its silhouette and, per pixel,
the body region it shows. Every person pixel outside that silhouette lies beyond the body; its
distance to the silhouette (pixels, then metres at the depth of the body there) is a lower bound
of how far the exterior reaches from the body in 3D (the exterior may also reach toward or away
from the camera, which a later frame of a turn shows from the side). It is charged to the region
of the nearest silhouette pixel. A high percentile over the frames is the region's reach: the
fit's own error puts a thin fringe of person pixels beside a tight body, which the percentile
counts at its true (small) width, while a skirt's hem is many pixels at the far end.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np


@dataclasses.dataclass
class Beyond:
    """Person pixels beyond the body in one frame."""

    metres: np.ndarray
    """(P,) distance of each to the body's silhouette, in metres."""
    region: np.ndarray
    """(P,) int64 body region of the nearest silhouette pixel."""


def beyond_body(body: np.ndarray, regions: np.ndarray, person: np.ndarray, metres_per_pixel: np.ndarray) -> Beyond:
    """Person pixels outside the body silhouette with their distance to it and the nearest region.

    ``body`` (H, W) bool: the body's silhouette; ``regions`` (H, W) int: its region per pixel (read
    where ``body``); ``person`` (H, W) bool; ``metres_per_pixel`` (H, W): the image's scale at the
    body's depth per pixel (read where ``body``). A pixel's distance is from its centre to the nearest
    silhouette pixel's centre (exact Euclidean distance transform), scaled at that silhouette pixel.
    """
    if not body.any():
        return Beyond(np.zeros(0), np.zeros(0, dtype=np.int64))
    outside = (~body).astype(np.uint8)
    dist, labels = cv2.distanceTransformWithLabels(outside, cv2.DIST_L2, cv2.DIST_MASK_PRECISE,
                                                   labelType=cv2.DIST_LABEL_PIXEL)  # fmt: skip
    ys, xs = np.nonzero(body)  # label k (1-based) is the k-th zero pixel of `outside` in row-major order
    where = person & ~body
    nearest = labels[where] - 1
    scale = metres_per_pixel[ys[nearest], xs[nearest]]
    return Beyond(dist[where].astype(np.float64) * scale, regions[ys[nearest], xs[nearest]].astype(np.int64))


def region_reach(frames: list[Beyond], names: dict[int, str], percentile: float, min_share: float) -> dict[str, dict]:
    """``{region: {"reach_m", "pixels"}}`` over all frames: the ``percentile`` of the distances charged to
    each region that holds at least ``min_share`` of the beyond pixels (fewer are noise: a stray pixel
    of the mask)."""
    metres = np.concatenate([f.metres for f in frames]) if frames else np.zeros(0)
    region = np.concatenate([f.region for f in frames]) if frames else np.zeros(0, dtype=np.int64)
    out = {}
    for r in np.unique(region):
        d = metres[region == r]
        if len(d) >= max(min_share * len(metres), 1):
            out[names.get(int(r), str(int(r)))] = {"reach_m": round(float(np.percentile(d, percentile)), 4),
                                                   "pixels": int(len(d))}  # fmt: skip
    return out
