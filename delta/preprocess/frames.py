"""Frame extraction: streamed decoding, undistortion, one square crop for all frames, resizing.

The crop is the union of the person's boxes over the selected frames plus a
margin, made square (SCARF crops once per video): the camera changes once, and
the person keeps its scale across frames.
"""

from __future__ import annotations

import json
import logging
from collections import Counter
from pathlib import Path
from typing import Iterator

import cv2
import h5py
import numpy as np
import torch

from delta import DeltaError
from delta.cameras.crop import CropBox, crop_camera
from delta.cameras.models import PinholeCamera
from delta.data.person import (
    CONF_THRESHOLD,
    MIN_KEYPOINTS,
    PLAUSIBLE,
    confident_keypoints,
    no_person_message,
    one_person,
    plausible_mask,
)
from delta.data.quality import BLUR_RATIO, EDGES, blurred, cut_edges, sharpness
from delta.data.record import MASKS, FullFrameWriter, RecordWriter, write_camera_attrs
from delta.data.sources import Source
from delta.data.video import iter_video
from delta.io import atomic_path

log = logging.getLogger(__name__)


class Undistorter:
    """Undistort images, masks and points of a pinhole camera; the camera keeps its K."""

    def __init__(self, camera):
        self.active = (
            isinstance(camera, PinholeCamera) and camera.dist is not None and bool(torch.any(camera.dist != 0))
        )
        if self.active:
            self.K, self.dist = camera.K.numpy(), camera.dist.numpy()
            size = (camera.width, camera.height)
            self.maps = cv2.initUndistortRectifyMap(self.K, self.dist, None, self.K, size, cv2.CV_32FC1)

    def image(self, img: np.ndarray, mask: bool = False, nearest: bool = False) -> np.ndarray:
        """Undistort a frame (border pixels repeated) or a mask (zero outside)."""
        if not self.active:
            return img
        interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        border = cv2.BORDER_CONSTANT if mask else cv2.BORDER_REPLICATE
        return cv2.remap(img, self.maps[0], self.maps[1], interp, borderMode=border)

    def points(self, uv: np.ndarray) -> np.ndarray:
        """(K, 2) pixel coordinates (centres at +0.5) in the distorted image -> undistorted."""
        if not self.active or not len(uv):
            return uv
        idx = uv - 0.5  # OpenCV works in pixel-index coordinates
        out = cv2.undistortPoints(idx.reshape(-1, 1, 2).astype(np.float64), self.K, self.dist, P=self.K)
        return out.reshape(-1, 2) + 0.5

    def camera(self, camera):
        if not self.active:
            return camera
        return PinholeCamera(camera.K, camera.R, camera.t, torch.zeros(5, dtype=torch.float64),
                             camera.width, camera.height)  # fmt: skip


def square_box(masks: Iterator[np.ndarray], margin: float, out: int) -> CropBox:
    """The square around the union of the masks' boxes, grown by ``margin`` of its side on each side.

    Where the person is cut by an image edge (a head-and-shoulders capture: the chest runs off the
    bottom), the square ends at that edge: beyond it the body goes on but the image holds no pixel
    of it, and a padded strip would teach the avatar background where the body is.
    """
    lo, hi = np.array([np.inf, np.inf]), np.array([-np.inf, -np.inf])
    size = None
    for m in masks:
        size = m.shape[1::-1]  # (W, H)
        ys, xs = np.nonzero(m > 127)
        if len(xs):
            lo = np.minimum(lo, [xs.min(), ys.min()])
            hi = np.maximum(hi, [xs.max() + 1, ys.max() + 1])
    if not np.isfinite(lo).all():
        raise DeltaError("no frame shows a person: every mask is empty")
    centre = (lo + hi) / 2
    side = int(np.ceil((hi - lo).max() * (1 + 2 * margin)))
    corner = np.round(centre - side / 2).astype(int)
    for axis in (0, 1):
        cut_low, cut_high = lo[axis] <= 0, hi[axis] >= size[axis]
        if cut_high and not cut_low:
            corner[axis] = size[axis] - side
        elif cut_low and not cut_high:
            corner[axis] = 0
    return CropBox(int(corner[0]), int(corner[1]), side, out)


def crop(img: np.ndarray, box: CropBox, interp: int, mask: bool = False) -> np.ndarray:
    """Crop and resize to ``box.out``; outside the image, frames repeat their border and masks are 0."""
    H, W = img.shape[:2]
    pad = max(0, -box.u0, -box.v0, box.u0 + box.size - W, box.v0 + box.size - H)
    if pad:
        border = cv2.BORDER_CONSTANT if mask else cv2.BORDER_REPLICATE
        img = cv2.copyMakeBorder(img, pad, pad, pad, pad, border, value=0)
    patch = img[box.v0 + pad : box.v0 + pad + box.size, box.u0 + pad : box.u0 + pad + box.size]
    return cv2.resize(patch, (box.out, box.out), interpolation=interp)


#: the long side of a capture's whole frames when scored, unless the dataset's protocol says otherwise
MAX_SCORE_SIZE = 1080


def scoring_size(kind: str, width: int, height: int, score_size: int = 0) -> tuple[int, int]:
    """(W, H) of the whole frames that evaluation scores and exports render: ``score_size`` on the long
    side, else the protocol's (People Snapshot: half its frame, 540 of 1080; otherwise the capture's
    own, at most :data:`MAX_SCORE_SIZE`). Never larger than the capture."""
    long = max(width, height)
    if score_size:
        target = min(score_size, long)
    elif kind == "peoplesnapshot":
        target = (long + 1) // 2
    else:
        target = min(long, MAX_SCORE_SIZE)
    return max(1, round(width * target / long)), max(1, round(height * target / long))


def prepare(source: Source, out_path: str | Path, size: int, margin: float = 0.08,
            full_size: tuple[int, int] | None = None) -> dict:  # fmt: skip
    """Write the frame record of ``source`` (see :mod:`delta.data.record`); returns a summary.

    ``full_size`` (W, H): the size of the whole frames kept for scoring (default: the capture's own,
    see :func:`scoring_size`). Frames whose provided person mask is empty are skipped and listed in
    the record.
    """
    full_size = full_size or scoring_size("", source.camera.width, source.camera.height)
    try:
        return _prepare(source, out_path, size, margin, full_size)
    finally:
        source.close()


#: what a source says of itself, whatever it provides
NOTED = ("camera", "smpl", "rotation", "thinned")


def noted(source: Source) -> dict[str, str]:
    """Where the record's arrays come from, and what was done to the video (rotation, thinning)."""
    return {k: v for k, v in source.origin.items() if k in source.provided or k in NOTED}


def whole(img: np.ndarray, full_size: tuple[int, int], interp: int) -> np.ndarray:
    """A whole (undistorted) frame or mask resized to the scoring size (W, H)."""
    return img if img.shape[1::-1] == tuple(full_size) else cv2.resize(img, full_size, interpolation=interp)


class OnePerson:
    """The source's person masks with everybody but the tracked person removed
    (:func:`~delta.data.person.one_person`); ``removed``: frame -> how many others went."""

    def __init__(self, person, keypoints):
        self.person, self.keypoints, self.removed = person, keypoints, {}

    def __call__(self, i: int) -> np.ndarray:
        mask, others = one_person(self.person(i), self.keypoints(i) if self.keypoints is not None else None)
        if others:
            self.removed[i] = others
        return mask


def _prepare(source: Source, out_path, size: int, margin: float, full_size: tuple[int, int]) -> dict:
    last = max(i for i, _ in source.frames)
    if source.num_video_frames and last >= source.num_video_frames:
        raise DeltaError(f"{source.video}: asked for frame {last} but the dataset's annotations hold "
                         f"{source.num_video_frames} frames")  # fmt: skip
    if "person" not in source.provided:
        raise DeltaError(f"{source.video}: no person masks: the dataset ships none and no matting ran "
                         "(set preprocess.matting.model and preprocess.matting.path)")  # fmt: skip
    und = Undistorter(source.camera)
    keypoints = source.provided.get("keypoints")
    person = OnePerson(source.provided["person"], keypoints)
    # one streamed pass over the masks: which frames show nobody, which show a person, the box around everybody
    empty: list[int] = []
    plausible, confident = [], []
    edges: dict[int, tuple[str, ...]] = {}

    def shown():
        for i, _ in source.frames:
            m = und.image(person(i), mask=True)
            plausible.append(plausible_mask(m))
            if keypoints is not None:
                confident.append(int(confident_keypoints(keypoints(i))))
            if (m > 127).any():
                edges[i] = cut_edges(m)
                yield m
            else:
                empty.append(i)

    try:
        box = square_box(shown(), margin, size)
    except DeltaError as exc:
        raise DeltaError(f"{source.video}: no selected frame shows a person ({exc})") from exc
    ids = np.array([i for i, _ in source.frames])
    plausible = np.array(plausible, dtype=bool)
    counts = np.array(confident) if keypoints is not None else None
    enough = plausible & (counts >= MIN_KEYPOINTS) if counts is not None else plausible
    if not enough.any():
        raise DeltaError(no_person_message(source.video, len(ids), counts, plausible, "plausible", PLAUSIBLE))
    kept = ~np.isin(ids, empty)
    few = ids[kept & (counts < MIN_KEYPOINTS)].tolist() if counts is not None else []
    odd = ids[kept & ~plausible].tolist()
    if few or odd:
        log.warning("%s: kept, but showing no person: %d frames with < %d keypoints of confidence >= %g %s, "
                    "%d with an implausible person mask %s", source.video, len(few), MIN_KEYPOINTS, CONF_THRESHOLD,
                    few, len(odd), odd)  # fmt: skip
    skipped = set(empty)
    # blur is judged on frames that show the person, framed as most frames are (a person half out of the
    # image shows less of its texture: it would look blurred beside the whole)
    framing = Counter(edges.values()).most_common(1)[0][0] if edges else ()
    showing = {i for i in ids[enough].tolist() if edges.get(i) == framing} - skipped
    blur = blurred({i: sharpness(rgb, person(i)) for i, rgb in iter_video(source.video, showing)})
    dropped = sorted({i for i, s in source.frames if s == 0 and i in blur})
    if not any(s == 0 and i not in skipped and i not in dropped for i, s in source.frames):
        dropped = []  # every training frame blurred: a blurred avatar rather than none
    frames = [(i, s) for i, s in source.frames if i not in skipped and not (s == 0 and i in dropped)]
    if blur:
        log.warning("%s: %d motion-blurred frames (sharpness below %g of the median): %s; the training frames among "
                    "them are left out", source.video, len(blur), BLUR_RATIO, blur)  # fmt: skip
    if person.removed:
        log.warning("%s: somebody else in %d frames (%s): only the tracked person is kept (the mask region with "
                    "their keypoints)", source.video, len(person.removed), sorted(person.removed))  # fmt: skip
    cut = {e: sum(e in v for v in edges.values()) for e in EDGES if any(e in v for v in edges.values())}
    if cut:
        log.info("%s: the person runs off the image in %d frames (by edge: %s); the crop ends there", source.video,
                 sum(bool(v) for v in edges.values()), cut)  # fmt: skip
    camera = crop_camera(und.camera(source.camera), box)
    masks = tuple(m for m in MASKS if m in source.provided)
    with atomic_path(out_path) as tmp, h5py.File(tmp, "w") as h5:
        h5.create_dataset("frame_ids", data=np.array([i for i, _ in frames], dtype=np.int64), track_times=False)
        h5.create_dataset("split", data=np.array([s for _, s in frames], dtype=np.uint8), track_times=False)
        writer = RecordWriter(h5, len(frames), size, masks, face="face_landmarks" in source.provided,
                              face_points=source.face_points if "face_points" in source.provided else None,
                              depth="keypoint_depth" in source.provided)  # fmt: skip
        full = FullFrameWriter(h5, len(frames), *full_size, masks)
        rows: dict[int, list[int]] = {}  # a frame in two splits (a one-frame capture) fills both rows
        for r, (i, _) in enumerate(frames):
            rows.setdefault(i, []).append(r)
        for i, rgb in iter_video(source.video, set(rows)):
            if rgb.shape[:2] != (source.camera.height, source.camera.width):
                raise DeltaError(f"{source.video}: frame {i} is {rgb.shape[1]}x{rgb.shape[0]} but the camera is for "
                                 f"{source.camera.width}x{source.camera.height} images")  # fmt: skip
            mask = person(i)
            if rgb.shape[:2] != mask.shape[:2]:
                raise DeltaError(f"{source.video}: frame {i} is {rgb.shape[1]}x{rgb.shape[0]} but its mask is "
                                 f"{mask.shape[1]}x{mask.shape[0]}")  # fmt: skip
            person_u = und.image(mask, mask=True)
            out_masks = {"person": crop(person_u, box, cv2.INTER_AREA, mask=True)}
            full_masks = {"person": whole(person_u, full_size, cv2.INTER_AREA)}
            for m in masks[1:]:  # parts lie inside the person, whichever step made each
                part = und.image(source.provided[m](i), mask=True, nearest=True)
                out_masks[m] = crop(part, box, cv2.INTER_NEAREST, mask=True) * (out_masks["person"] > 127)
                full_masks[m] = whole(part, full_size, cv2.INTER_NEAREST) * (full_masks["person"] > 127)
            points = {}
            for name in ("keypoints", "face_landmarks", "face_points"):  # undistorted, then moved with the crop
                if name in source.provided:
                    p = np.asarray(source.provided[name](i), dtype=np.float64).copy()
                    p[:, :2] = box.apply_to_points(torch.from_numpy(und.points(p[:, :2]))).numpy()
                    points[name] = p
            rgb_u = und.image(rgb)
            cropped, whole_frame = crop(rgb_u, box, cv2.INTER_AREA), whole(rgb_u, full_size, cv2.INTER_AREA)
            depth = source.provided["keypoint_depth"](i) if "keypoint_depth" in source.provided else None
            for r in rows[i]:
                writer.write(r, cropped, out_masks, points.get("keypoints"), points.get("face_landmarks"),
                             points.get("face_points"), depth)  # fmt: skip
                full.write(r, whole_frame, full_masks)
        write_camera_attrs(h5, camera)
        ids = np.array([i for i, _ in frames])
        for name, values in source.body_params.items():  # per-frame rows for the kept frames; per-subject as is
            per_frame = values.ndim >= 2 and len(values) == source.num_video_frames
            h5.create_dataset(name, data=values[ids] if per_frame else values, track_times=False)
        origin = noted(source)
        h5.attrs["sources"] = json.dumps({**origin, "images": f"video:{source.video.name}"}, sort_keys=True)
        h5.attrs["crop"] = np.array([box.u0, box.v0, box.size, box.out])
        h5.attrs["source_size"] = np.array([source.camera.width, source.camera.height])
        h5.attrs["skipped_empty"] = np.array(empty, dtype=np.int64)
    summary = {"frames": len(frames), "skipped_empty": empty, "few_keypoints": few, "implausible_mask": odd,
               "blurred": blur, "skipped_blurred": dropped, "other_people": sorted(person.removed),
               "cut_by_edge": {"frames": sorted(i for i, v in edges.items() if v), "edges": cut},
               "crop": [box.u0, box.v0, box.size, box.out], "full_size": list(full_size),
               "sources": noted(source)}  # fmt: skip
    log.info("prepared %s", summary)
    return summary
