"""How usable a frame of a real video is: motion blur, and a person running off the image.

A hand-held or dancing capture has frames smeared by motion: trained on, they teach the avatar a
blurred texture. A frame's sharpness is measured on the person alone (inside the person's mask, away
from its edge; the person's box brought down to a fixed size so that a far and a near person compare)
as the variance of the grey image's second difference in the direction where it is weakest: motion
blurs along its own direction and leaves the others (a striped shirt moved along its stripes looks as
sharp as ever). A frame far below the capture's median is blurred.

A person runs off the image at an edge their mask crosses; a sliver of contact (the tip of a heel on
the last row, a fingertip) cuts off nothing the avatar needs and does not count. Contact is looked for in
a thin band along each edge, not on its outermost row alone: a matte made at a model's resolution and
brought up to the frame's fades out over the last few pixels (MediaPipe's 256-pixel mask over a
1080-pixel frame: 70, 122, 174, 226 of 255 on the four outermost columns under a hand that crosses
the edge), so its last row alone says little about what crosses it.
"""

from __future__ import annotations

import cv2
import numpy as np

#: a frame is blurred below this share of the capture's median sharpness
BLUR_RATIO = 0.3
#: long side (pixels) the person's box is resized to before measuring
SHARPNESS_SIZE = 512
#: band along the silhouette left out of the measure, as a share of the box's long side
EDGE_MARGIN = 0.03
EDGES = ("left", "top", "right", "bottom")
#: a mask runs off an edge where its contact there spans at least this share of the person's long side
CUT_CONTACT = 0.015
#: the band along an edge where contact is looked for, as a share of the image's long side (4 px at 1080)
CUT_BAND = 0.004


_DIRECTIONS = tuple(
    np.array(k, np.float32)
    for k in (
        [[0, 0, 0], [1, -2, 1], [0, 0, 0]],  # along x
        [[0, 1, 0], [0, -2, 0], [0, 1, 0]],  # along y
        [[1, 0, 0], [0, -2, 0], [0, 0, 1]],  # the diagonals
        [[0, 0, 1], [0, -2, 0], [1, 0, 0]],
    )
)


def sharpness(rgb: np.ndarray, mask: np.ndarray) -> float:
    """The variance of the grey values' second difference, in the direction where it is weakest (motion
    blurs along one), inside the (H, W) person mask (0-255) of the (H, W, 3) uint8 frame less a band along
    its edge, on the person's box brought down to ``SHARPNESS_SIZE`` on its long
    side; NaN without a person."""
    on = np.asarray(mask) > 127
    ys, xs = np.nonzero(on)
    if len(xs) < 16:
        return float("nan")
    v0, v1, u0, u1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    grey = cv2.cvtColor(np.ascontiguousarray(rgb[v0:v1, u0:u1]), cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    inside = on[v0:v1, u0:u1].astype(np.uint8)
    scale = min(1.0, SHARPNESS_SIZE / max(grey.shape))  # never upsampled: that would blur it
    size = (max(1, round(grey.shape[1] * scale)), max(1, round(grey.shape[0] * scale)))
    grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    # the silhouette's own edge (person against background) is left out: motion along it keeps it sharp
    r = max(1, round(EDGE_MARGIN * max(size)))
    inside = cv2.erode(
        cv2.resize(inside, size, interpolation=cv2.INTER_NEAREST), np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    )
    inside = inside > 0
    if inside.sum() < 16:
        return float("nan")
    # motion blurs along its direction only: the weakest of four directional second differences
    return float(min(cv2.filter2D(grey, cv2.CV_32F, k)[inside].var() for k in _DIRECTIONS))


def blurred(scores: dict[int, float], ratio: float = BLUR_RATIO) -> list[int]:
    """Frames whose sharpness is below ``ratio`` of the median over the frames measured (sorted)."""
    values = np.array([s for s in scores.values() if np.isfinite(s)])
    if len(values) < 3:
        return []
    floor = ratio * float(np.median(values))
    return sorted(i for i, s in scores.items() if np.isfinite(s) and s < floor)


def cut_edges(mask: np.ndarray, contact: float = CUT_CONTACT, band: float = CUT_BAND) -> tuple[str, ...]:
    """The image edges the (H, W) person mask (0-255) runs off: those it touches over at least ``contact``
    of the long side of its box (at least one pixel), a row or column touching where the mask is on within
    ``band`` of the image's long side (at least one pixel) of that edge."""
    on = np.asarray(mask) > 127
    rows, cols = np.flatnonzero(on.any(1)), np.flatnonzero(on.any(0))
    if not rows.size:
        return ()
    floor = max(1.0, contact * max(rows[-1] - rows[0] + 1, cols[-1] - cols[0] + 1))
    b = max(1, round(band * max(on.shape)))
    touch = (on[:, :b].any(1).sum(), on[:b].any(0).sum(), on[:, -b:].any(1).sum(), on[-b:].any(0).sum())
    return tuple(e for e, t in zip(EDGES, touch) if t >= floor)
