"""The colour inside the open mouths of a capture, against frames painted with a known inside."""

from __future__ import annotations

import json

import cv2
import h5py
import numpy as np
import pytest

from delta.preprocess.face_tracking import INNER_LIP_CONTOUR
from delta.scene.mouth import MIN_AREA, MIN_FRAMES, MIN_SHADE, inside_lips, mouth_shade, open_mouths
from delta.scene.settings import scene_settings

SKIN = np.array([0.6, 0.4, 0.3])
INSIDE = np.array([0.24, 0.06, 0.03])


def lips(radius: float, centre=(32.0, 40.0)) -> np.ndarray:
    """(C, 2) the inner-lip contour as an ellipse (twice as wide as tall) around ``centre``."""
    a = np.linspace(0, 2 * np.pi, len(INNER_LIP_CONTOUR), endpoint=False)
    return np.stack([centre[0] + 2 * radius * np.cos(a), centre[1] + radius * np.sin(a)], 1)


def talking_record(path, radii) -> None:
    """A 64² record of ``len(radii)`` frames: skin everywhere, the inside of each frame's lips painted
    ``INSIDE`` (radius 0: a closed mouth; None: no face tracked in that frame)."""
    n = len(radii)
    images = np.empty((n, 64, 64, 3), np.uint8)
    marks = np.full((n, 468, 3), np.nan, np.float32)
    for i, r in enumerate(radii):
        image = np.broadcast_to(SKIN, (64, 64, 3)).copy()
        if r is not None:
            contour = lips(max(r, 0.1))
            marks[i, list(INNER_LIP_CONTOUR), :2] = contour
            marks[i, :, 2] = 1.0
            if r > 0:  # the mouth's pixels, one ring wider than the eroded inside that is measured
                mask = np.zeros((64, 64), np.uint8)
                cv2.fillPoly(mask, [np.round(contour).astype(np.int32)], 1)
                image[mask.astype(bool)] = INSIDE
        images[i] = np.round(image * 255)
    with h5py.File(path, "w") as h5:
        h5["images"] = images
        h5["face_landmarks"] = marks


def test_the_inside_of_the_lips_is_the_filled_contour_less_its_edge():
    inside = inside_lips(lips(5.0), (64, 64))
    assert inside[40, 32] and not inside[40, 45] and not inside[30, 32]
    # the ellipse's area (pi * 10 * 5) less about a pixel's ring around it
    assert np.pi * 9 * 4 * 0.9 < inside.sum() < np.pi * 10 * 5


def test_the_open_mouths_are_the_frames_whose_lips_enclose_enough_pixels(tmp_path):
    record = tmp_path / "frames.h5"
    talking_record(record, [0, 6.0, None, 1.0, 5.0, 7.0])
    found = open_mouths(record, range(6))
    assert [f for f, _, _ in found] == [1, 4, 5]  # closed, untracked and a slit are not open
    assert all(a >= MIN_AREA for _, a, _ in found)
    for _, _, colour in found:  # the painted inside, to the bytes' rounding
        np.testing.assert_allclose(colour, INSIDE, atol=1 / 255)
    assert [f for f, _, _ in open_mouths(record, [0, 1, 2])] == [1]  # only the frames asked for
    with h5py.File(tmp_path / "bare.h5", "w") as h5:
        h5["images"] = np.zeros((2, 8, 8, 3), np.uint8)
    assert open_mouths(tmp_path / "bare.h5", range(2)) == []


def test_the_shade_turns_the_skin_into_the_captured_inside_and_needs_enough_open_mouths(tmp_path):
    record = tmp_path / "frames.h5"
    talking_record(record, [6.0, 5.0, 7.0, 0, 0])
    shade, evidence = mouth_shade(record, range(5), SKIN)
    np.testing.assert_allclose(shade, INSIDE / SKIN, atol=0.01)
    assert evidence["open_frames"] == 3 and evidence["of_frames"] == 5
    # a channel the inside barely holds is floored
    dark, _ = mouth_shade(record, range(5), np.array([0.6, 0.4, 0.9]))
    assert dark[2] == pytest.approx(max(INSIDE[2] / 0.9, MIN_SHADE), abs=0.01)
    # too few open mouths: no shade, and the evidence says why
    none, why = mouth_shade(record, range(MIN_FRAMES - 1), SKIN)
    assert none is None and f"under {MIN_FRAMES}" in why["why"]


def test_the_shade_reaches_training_unless_the_config_sets_its_own(tmp_path):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps({"decisions": {"mouth_shade": [0.4, 0.15, 0.1]}}))
    assert scene_settings(path, {}, []) == {"mouth_shade": [0.4, 0.15, 0.1]}
    assert scene_settings(path, {}, ["mouth_shade"]) == {}
