"""Points of the exterior followed through the training frames (where the cloth goes from frame to frame).

The exterior is one canonical NeRF for every frame, so a point of a garment must land at one canonical
point in every frame, or the NeRF learns the average of the places it lands: a pattern smears. Nothing in
the photometric loss pulls a smeared pattern back (docs/method.md, "Where a skirt's hem goes"). A tracked
point says it directly: its pixels in two frames show the same point of the cloth, so the canonical
points their rays see should meet (``delta.losses.track``).

Tracks start at corners of the exterior (Shi–Tomasi, where the image has texture in two directions, so a
track does not slide along a stripe or over a plain patch) and are followed from each training frame to
the next by pyramidal Lucas–Kanade. A step is kept where tracking back returns within ``FB_TOLERANCE``
pixels, the patches about its two ends look alike (normalised correlation, which a consistent but wrong
match fails), the step agrees with its neighbours' (a repeating pattern matches the next dot or check as
well as its own) and both ends lie inside the exterior, away from its outline (an outline's pixels mix
in what lies behind the cloth); a track ends at the first step that is not, and new corners are taken up
where a frame's exterior has room. Consecutive frames move the cloth by a pixel or two, too little to tell
a garment's sway from the tracker's noise; a track followed over many frames spans its whole swing.
Pixels here are the rays' (``sample_rays``): a pixel's centre at (column + 0.5, row + 0.5).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import torch
from scipy.spatial import cKDTree

#: pixels a tracked point may land from its start when tracked back (forward-backward check)
FB_TOLERANCE = 0.5
#: pixels of the exterior mask's edge left out at both ends of a track
EDGE_MARGIN = 2
#: tracks a frame follows at most, their corners' smallest spacing (pixels) and quality (share of the best)
MAX_CORNERS = 2000
CORNER_SPACING = 3
CORNER_QUALITY = 0.01
#: Lucas–Kanade's window (pixels) and pyramid levels
LK_WINDOW = 15
LK_LEVELS = 3
#: the patches (pixels a side) about a track's two ends must correlate at least this much (normalised)
PATCH = 15
MIN_CORRELATION = 0.97
#: a step may move a point at most this many pixels from the median step of its ``NEIGHBOURS`` nearest
#: points: a cloth moves smoothly, a match on the next dot or check of a repeating pattern does not
COHERENCE = 1.0
NEIGHBOURS = 8


@dataclasses.dataclass
class Tracks:
    """Points of the exterior followed through the training frames (T tracks over the capture's N frames)."""

    pixels: torch.Tensor
    """(T, N, 2) float32: where each track lies in each frame (ray pixels), NaN where it is not followed."""
    shared: torch.Tensor
    """(N, N) int64: how many tracks two frames share."""

    def partners(self, frame: int, least: int = 1) -> torch.Tensor:
        """The frames sharing at least ``least`` tracks with ``frame`` (it excluded)."""
        row = self.shared[frame].clone()
        row[frame] = 0
        return torch.nonzero(row >= least).squeeze(1)

    def between(self, a: int, b: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(M, 2) pixels in frame a and (M, 2) in frame b of the tracks followed through both."""
        both = ~(self.pixels[:, a, 0].isnan() | self.pixels[:, b, 0].isnan())
        return self.pixels[both, a], self.pixels[both, b]

    @property
    def count(self) -> int:
        return int(self.pixels.shape[0])


def _grey(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.rint(np.clip(image, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def _inner(mask: np.ndarray) -> np.ndarray:
    """The mask (H, W) in [0, 1] above one half, without its outermost ``EDGE_MARGIN`` pixels (uint8 0/255)."""
    m = (mask > 0.5).astype(np.uint8) * 255
    return cv2.erode(m, np.ones((2 * EDGE_MARGIN + 1,) * 2, np.uint8)) if EDGE_MARGIN else m


def patch_correlation(grey_a: np.ndarray, a: np.ndarray, grey_b: np.ndarray, b: np.ndarray,
                      size: int = PATCH) -> np.ndarray:  # fmt: skip
    """(M,) normalised correlation of the ``size``² patches about the points ``a`` of one image and ``b``
    of another ((M, 2) in OpenCV's pixels, bilinear), 0 where either patch is flat."""
    r = np.arange(size, dtype=np.float32) - (size - 1) / 2
    dx, dy = np.meshgrid(r, r)
    offsets = np.stack([dx.ravel(), dy.ravel()], 1)  # (size², 2)

    def patches(img, pts):
        grid = (pts[:, None, :] + offsets[None]).astype(np.float32)  # (M, size², 2)
        out = cv2.remap(img.astype(np.float32), grid[..., 0], grid[..., 1], cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
        return out - out.mean(1, keepdims=True)

    pa, pb = patches(grey_a, a), patches(grey_b, b)
    norm = np.sqrt((pa**2).sum(1) * (pb**2).sum(1))
    return np.where(norm > 1e-6, (pa * pb).sum(1) / np.maximum(norm, 1e-6), 0.0)


@dataclasses.dataclass
class Frame:
    """What tracking reads of one frame, made once: its grey image and its exterior without the outline."""

    grey: np.ndarray
    """(H, W) uint8."""
    inner: np.ndarray
    """(H, W) uint8 0/255: the exterior mask above one half, its outermost ``EDGE_MARGIN`` pixels off."""

    @classmethod
    def of(cls, image: np.ndarray, mask: np.ndarray) -> "Frame":
        """From ``image`` (H, W, 3) and the exterior ``mask`` (H, W), both in [0, 1]."""
        return cls(_grey(image), _inner(mask))


def _pixel_of(points: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The column, row (the nearest pixel) of points (M, 2) in OpenCV's pixels, and (M,) bool: which lie in an
    image of ``shape`` (H, W)."""
    col, row = np.rint(points).astype(np.int64).T
    return col, row, (col >= 0) & (col < shape[1]) & (row >= 0) & (row < shape[0])


def corners(frame: Frame, count: int, avoid: np.ndarray | None = None) -> np.ndarray:
    """Up to ``count`` corners (M, 2) of the frame's exterior, at least ``CORNER_SPACING`` pixels from each
    point of ``avoid`` (K, 2); OpenCV's pixels."""
    inner = frame.inner
    if avoid is not None and len(avoid):  # a disc of the spacing about each point taken out
        taken = np.zeros_like(inner)
        col, row, on = _pixel_of(avoid, inner.shape)
        taken[row[on], col[on]] = 255
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * CORNER_SPACING + 1,) * 2)
        inner = np.where(cv2.dilate(taken, disc) > 0, 0, inner).astype(np.uint8)
    if count <= 0 or not inner.any():
        return np.zeros((0, 2), np.float32)
    found = cv2.goodFeaturesToTrack(frame.grey, count, CORNER_QUALITY, CORNER_SPACING, mask=inner)
    return np.zeros((0, 2), np.float32) if found is None else found.reshape(-1, 2).astype(np.float32)


def follow(frame_a: Frame, frame_b: Frame, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (M, 2) of frame a (OpenCV's pixels) followed into frame b: (M,) bool, which were, and (K, 2)
    where those lie in b."""
    kept = np.zeros(len(points), bool)
    if not len(points):
        return kept, np.zeros((0, 2), np.float32)
    ga, gb = frame_a.grey, frame_b.grey
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    lk = dict(winSize=(LK_WINDOW, LK_WINDOW), maxLevel=LK_LEVELS, criteria=criteria)
    a = np.ascontiguousarray(points, np.float32).reshape(-1, 1, 2)
    fwd, ok_f, _ = cv2.calcOpticalFlowPyrLK(ga, gb, a, None, **lk)
    back, ok_b, _ = cv2.calcOpticalFlowPyrLK(gb, ga, fwd, None, **lk)
    a, b = a.reshape(-1, 2), fwd.reshape(-1, 2)
    ok = (ok_f.ravel() == 1) & (ok_b.ravel() == 1)
    ok &= np.linalg.norm(back.reshape(-1, 2) - a, axis=1) < FB_TOLERANCE
    ok[ok] &= patch_correlation(ga, a[ok], gb, b[ok]) >= MIN_CORRELATION
    for img_mask, pts in ((frame_a.inner, a), (frame_b.inner, b)):
        col, row, inside = _pixel_of(pts, img_mask.shape)
        ok &= inside
        ok[inside] &= img_mask[row[inside], col[inside]] > 0
    ok[ok] &= coherent(a[ok], b[ok] - a[ok])
    return ok, b[ok]


def coherent(points: np.ndarray, steps: np.ndarray, k: int = NEIGHBOURS, tolerance: float = COHERENCE) -> np.ndarray:
    """(M,) bool: each point's step (M, 2) lies within ``tolerance`` pixels of the median step of its ``k``
    nearest other points (M, 2); all where there are too few points to tell."""
    if len(points) <= k:
        return np.ones(len(points), bool)
    _, near = cKDTree(points).query(points, k + 1)
    median = np.median(steps[near[:, 1:]], axis=1)
    return np.linalg.norm(steps - median, axis=1) <= tolerance


def frame_tracks(images, exterior, frame_ids: np.ndarray, train: np.ndarray, max_gap: int = 3,
                 max_corners: int = MAX_CORNERS) -> Tracks:  # fmt: skip
    """Points of the exterior followed from training frame to training frame through the capture (frames at
    most ``max_gap`` capture frames apart; a wider gap ends every track), new corners taken up where the
    frame's exterior has room; ``images`` (N, H, W, 3) and ``exterior`` (N, H, W) index as float tensors
    (``FrameData``'s). A track lives while each step passes :func:`follow`'s checks."""
    n = len(frame_ids)
    order = np.asarray(train)[np.argsort(np.asarray(frame_ids)[train], kind="stable")]
    done: list[np.ndarray] = []  # finished tracks, each (N, 2)
    live = np.full((0, n, 2), np.nan, np.float32)
    before = None
    for k, f in enumerate(order):
        f = int(f)
        here = Frame.of(images[f].numpy(), exterior[f].numpy())
        if k and 0 < frame_ids[f] - frame_ids[order[k - 1]] <= max_gap and len(live):
            kept, to = follow(before, here, live[:, int(order[k - 1])] - 0.5)
            done.extend(live[~kept])
            live = live[kept]
            live[:, f] = to + 0.5
        else:
            done.extend(live)
            live = live[:0]
        room = max_corners - len(live)
        if room > 0:
            new = corners(here, room, live[:, f] - 0.5)
            fresh = np.full((len(new), n, 2), np.nan, np.float32)
            fresh[:, f] = new + 0.5
            live = np.concatenate([live, fresh])
        before = here
    done.extend(live)
    pixels = np.stack(done) if done else np.zeros((0, n, 2), np.float32)
    pixels = pixels[(~np.isnan(pixels[..., 0])).sum(1) >= 2]  # a track seen once says nothing
    seen = torch.from_numpy((~np.isnan(pixels[..., 0])).astype(np.int64))
    return Tracks(torch.from_numpy(pixels), seen.T @ seen)
