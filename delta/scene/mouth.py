"""The colour inside a talking face's open mouth, measured from the capture: where the albedo of the mouth's
inside starts (``training.mouth_shade``, :func:`delta.models.avatar.mouth_prior`).

Shapes: N frames, H × W record pixels.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import h5py
import numpy as np

from delta.preprocess.face_tracking import INNER_LIP_CONTOUR

#: record pixels inside the inner lips (the contour eroded by one pixel) for a frame's mouth to count as open
MIN_AREA = 30
#: open mouths the capture must show for its colour to be taken; fewer leave the preset's shade
MIN_FRAMES = 3
#: the darkest shade taken (a channel the skin barely holds would divide by almost nothing)
MIN_SHADE = 0.05


def inside_lips(points: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: the pixels inside the inner-lip contour ``points`` (C, 2) (u, v), eroded by one pixel
    (the lips' own edge pixels mix lip and mouth)."""
    mask = np.zeros(shape, np.uint8)
    cv2.fillPoly(mask, [np.round(points).astype(np.int32)], 1)
    return cv2.erode(mask, np.ones((3, 3), np.uint8)).astype(bool)


def open_mouths(record: str | Path, frames, min_area: int = MIN_AREA) -> list[tuple[int, int, np.ndarray]]:
    """``(frame, pixels, colour)`` of each of ``frames`` whose tracked inner lips enclose at least ``min_area``
    record pixels: how many, and their mean colour (3,) in [0, 1]. A record without face landmarks has none."""
    found = []
    with h5py.File(record, "r") as h5:
        if "face_landmarks" not in h5:
            return found
        marks, images = h5["face_landmarks"], h5["images"]
        for i in frames:
            points = marks[int(i)][list(INNER_LIP_CONTOUR), :2]
            if not np.isfinite(points).all():
                continue
            inside = inside_lips(points, images.shape[1:3])
            if inside.sum() < min_area:
                continue
            image = images[int(i)].astype(np.float32)
            image = image / 255.0 if images.dtype == np.uint8 else image
            found.append((int(i), int(inside.sum()), image[inside].mean(0)))
    return found


def mouth_shade(record: str | Path, frames, skin: np.ndarray) -> tuple[list[float] | None, dict]:
    """The shade (red, green, blue; each in [``MIN_SHADE``, 1]) that turns ``skin`` (3,), the colour the albedo
    starts at, into the median colour inside the open mouths of ``frames``, and the evidence; None where
    fewer than ``MIN_FRAMES`` frames open the mouth."""
    found = open_mouths(record, frames)
    evidence = {"open_frames": len(found), "of_frames": len(frames), "min_frames": MIN_FRAMES,
                "min_pixels": MIN_AREA}  # fmt: skip
    if len(found) < MIN_FRAMES:
        evidence["why"] = (f"{len(found)} of {len(frames)} training frames open the mouth ({MIN_AREA} px or more "
                           f"inside the inner lips), under {MIN_FRAMES}: the preset's shade")  # fmt: skip
        return None, evidence
    inside = np.median(np.stack([c for _, _, c in found]), 0).astype(np.float64)
    skin = np.asarray(skin, dtype=np.float64)
    shade = np.clip(inside / np.maximum(skin, 1e-6), MIN_SHADE, 1.0)
    colours = {k: [round(float(v), 3) for v in c] for k, c in (("inside", inside), ("skin", skin))}
    evidence |= {**colours, "median_pixels": float(np.median([a for _, a, _ in found])),
                 "why": f"the inside of {len(found)} open mouths of {len(frames)} training frames, "
                        f"{colours['inside']}, against the skin's {colours['skin']}"}  # fmt: skip
    return [round(float(v), 3) for v in shade], evidence
