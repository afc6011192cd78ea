"""Is anybody there? Per-frame evidence of a person (confident keypoints, a plausible mask) and the
one-line error when no frame of a capture has it (a grey or noise video, a detector that found nobody).

The keypoint thresholds are the init fit's defaults (``FitConfig.min_keypoints``, ``conf_threshold``):
a frame the fit would flag for its keypoints is not evidence of a person here either.
"""

from __future__ import annotations

import cv2
import numpy as np

MIN_KEYPOINTS = 4
"""Confident keypoints a frame needs (of OpenPose-18)."""
CONF_THRESHOLD = 0.3
"""Detection confidence a keypoint needs to count."""
MASK_AREA = (0.001, 0.95)
"""Share of the image a plausible person mask (alpha > 127) covers."""
MASK_DOMINANT = 0.5
"""Share of a plausible mask's pixels its largest connected region holds (a person, not speckle)."""


def confident_keypoints(keypoints: np.ndarray, threshold: float = CONF_THRESHOLD) -> np.ndarray:
    """(..., K, 3) keypoints (u, v, confidence) -> (...,) count of keypoints with confidence >= threshold
    (0 and NaN: not detected), as the init fit counts them."""
    conf = np.nan_to_num(np.asarray(keypoints, dtype=np.float64)[..., 2], nan=0.0)
    return ((conf >= threshold) & (conf > 0)).sum(-1)


def plausible_mask(mask: np.ndarray) -> bool:
    """Whether an (H, W) person mask (0-255) looks like one person: its area (alpha > 127) within
    ``MASK_AREA`` of the image and its largest 8-connected region ``MASK_DOMINANT`` of it or more."""
    on = (np.asarray(mask) > 127).astype(np.uint8)
    area = int(on.sum())
    if not MASK_AREA[0] * on.size <= area <= MASK_AREA[1] * on.size:
        return False
    _, _, stats, _ = cv2.connectedComponentsWithStats(on, connectivity=8)
    return bool(stats[1:, cv2.CC_STAT_AREA].max() >= MASK_DOMINANT * area)


PLAUSIBLE = (
    f"{MASK_AREA[0]:.1%}-{MASK_AREA[1]:.0%} of the image, {MASK_DOMINANT:.0%} or more of it in one connected region"
)
"""What a plausible mask is, for messages."""


def no_person_message(where, frames: int, keypoints: np.ndarray | None, masks: np.ndarray, mask_kind: str,
                      mask_note: str = "", min_keypoints: int = MIN_KEYPOINTS,
                      threshold: float = CONF_THRESHOLD) -> str:  # fmt: skip
    """The one-line reason a capture shows nobody: ``keypoints`` (F,) counts of confident keypoints
    (None: the capture has no keypoints), ``masks`` (F,) bool, whether a frame's mask is ``mask_kind``
    ("plausible", "non-empty"; ``mask_note`` says what that means)."""
    masks = np.asarray(masks, dtype=bool)
    note = f": {mask_note}" if mask_note else ""
    if keypoints is None:
        return f"{where}: no person found: 0 of {frames} frames have a {mask_kind} person mask{note}"
    keypoints = np.asarray(keypoints)
    most = int(keypoints.max()) if len(keypoints) else 0
    return (f"{where}: no person found: 0 of {frames} frames have >= {min_keypoints} keypoints with confidence "
            f">= {threshold:g} and a {mask_kind} person mask ({int((keypoints >= min_keypoints).sum())} have the "
            f"keypoints, at most {most} in a frame; {int(masks.sum())} have a {mask_kind} mask{note})")  # fmt: skip


OTHER_PERSON = 0.1
"""A connected region of the person mask without a keypoint of the tracked person, at least this share of
the tracked person's region: somebody else."""


def one_person(mask: np.ndarray, keypoints: np.ndarray | None,
               threshold: float = CONF_THRESHOLD) -> tuple[np.ndarray, int]:  # fmt: skip
    """The (H, W) person mask (0-255) with everybody but the tracked person removed, and how many others
    were removed.

    The tracked person is the 8-connected region (alpha > 127) holding most of the (K, 3) keypoints'
    confident points (the largest of those); without a confident keypoint on the mask nothing tells who
    is tracked, and the mask is left as it is (the frame is flagged for its keypoints). Other regions that
    hold a keypoint stay (a hand the matting cut off at the wrist); so do small ones (speckle, a bag);
    regions of ``OTHER_PERSON`` of the tracked region's area or more without a keypoint are other
    people, and go.
    """
    on = (np.asarray(mask) > 127).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(on, connectivity=8)
    if count <= 2:
        return mask, 0
    area = stats[:, cv2.CC_STAT_AREA].copy()
    area[0] = 0
    held = np.zeros(count, np.int64)
    if keypoints is not None:
        kp = np.nan_to_num(np.asarray(keypoints, dtype=np.float64))
        good = (kp[:, 2] >= threshold) & (kp[:, 2] > 0)
        H, W = on.shape
        u = np.clip(np.floor(kp[good, 0]).astype(int), 0, W - 1)
        v = np.clip(np.floor(kp[good, 1]).astype(int), 0, H - 1)
        inside = (kp[good, 0] >= 0) & (kp[good, 0] < W) & (kp[good, 1] >= 0) & (kp[good, 1] < H)
        np.add.at(held, labels[v[inside], u[inside]], 1)
        held[0] = 0
    if held.max() == 0:  # no keypoint tells who is tracked (a frame the fit flags): nothing to go by
        return mask, 0
    main = int(np.lexsort((area, held))[-1])  # most keypoints, then the largest
    others = [k for k in range(1, count) if k != main and held[k] == 0 and area[k] >= OTHER_PERSON * area[main]]
    if not others:
        return mask, 0
    out = np.array(mask, copy=True)
    out[np.isin(labels, others)] = 0
    return out, len(others)
