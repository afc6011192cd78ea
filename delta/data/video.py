"""Reading a user's video: what it holds, which of its frames a subject uses, and the frames themselves.

Phone videos are the common case, and they are not what a video header says they are:

- **rotation metadata**: a portrait phone clip is stored landscape with a display rotation; OpenCV
  applies it when decoding, and every size here is the decoded (upright) one;
- **variable frame rate**: the header's frame count is the duration times an average rate, not a count;
  frames are numbered here in decoding order, and a step reads until the video ends rather than
  trusting the header (:func:`iter_video` with ``to_end``);
- **long videos**: a subject's ranges are thinned evenly to at most ``max_frames`` frames each
  (:func:`select_frames`), and only the selected frames are decoded and analysed.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Iterator

import numpy as np

from delta import DeltaError

log = logging.getLogger(__name__)

#: the splits a video subject's ranges fill, in order
RANGE_SPLITS = {"train": 0, "test": 1}
FRAMINGS = ("full", "head")
"""What a video's frames show: a person's body (``full``, also half bodies), or a head-and-shoulders close-up
(``head``), whose face the model steps track directly (:mod:`delta.preprocess.face_tracking`)."""


@dataclasses.dataclass(frozen=True)
class VideoInfo:
    """What the container says, with sizes as the frames decode (upright)."""

    path: Path
    frames: int
    """The header's frame count (an estimate for variable-frame-rate video)."""
    width: int
    height: int
    fps: float
    rotation: int
    """The display rotation (degrees) the container asks for, applied when decoding."""


def _open(path: Path):
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        cap.release()
        raise DeltaError(f"cannot open video {path} (missing, empty or not a video)")
    return cap


def probe_video(path: str | Path) -> VideoInfo:
    """The :class:`VideoInfo` of ``path``; errors name the file."""
    import cv2

    path = Path(path)
    cap = _open(path)
    try:
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        W, H = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        rotation = int(round(cap.get(cv2.CAP_PROP_ORIENTATION_META))) % 360
        ok, first = cap.read()
    finally:
        cap.release()
    if not ok or n <= 0:
        raise DeltaError(f"{path}: the video has no readable frame")
    if first.shape[:2] != (H, W):  # a backend that reports the stored size: the decoded one is what counts
        H, W = first.shape[:2]
    return VideoInfo(path, n, W, H, fps if np.isfinite(fps) and fps > 0 else 0.0, rotation)


def iter_video(
    path: str | Path, wanted: set[int] | None = None, to_end: bool = False
) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (index, RGB frame) for the wanted indices (all with None), decoding sequentially; errors name
    the file. A wanted frame beyond the video's end is an error, unless ``to_end``: then the frames
    there are simply not yielded (a step that reads what the video holds)."""
    import cv2

    path = Path(path)
    cap = _open(path)
    last = max(wanted) if wanted else -1
    i = 0
    try:
        while wanted is None or i <= last:
            ok, frame = cap.read()
            if not ok:
                if i == 0:
                    raise DeltaError(f"{path}: the video has no readable frame")
                if wanted is None or to_end:
                    return
                missing = sorted(f for f in wanted if f >= i)
                raise DeltaError(f"{path}: the video ends after {i} frames, but frame(s) {missing[:5]}"
                                 f"{' ...' if len(missing) > 5 else ''} were asked for")  # fmt: skip
            if wanted is None or i in wanted:
                yield i, cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
            i += 1
    finally:
        cap.release()


def frame_range(spec, split: int, key: str) -> list[tuple[int, int]]:
    """(frame, split) pairs of an inclusive ``[start, end, step]`` range; errors name ``key``."""
    if not (isinstance(spec, list) and len(spec) == 3 and all(isinstance(v, int) for v in spec)):
        raise DeltaError(f"{key}: expected [start, end, step] (inclusive end), got {spec!r}")
    start, end, step = spec
    if step < 1 or end < start or start < 0:
        raise DeltaError(f"{key}: [start, end, step] = {spec} is not a valid range")
    return [(i, split) for i in range(start, end + 1, step)]


def thin(frames: list[int], count: int) -> list[int]:
    """At most ``count`` of ``frames``, evenly spaced, the first and last kept (all with count 0)."""
    if count <= 0 or len(frames) <= count:
        return list(frames)
    if count == 1:
        return [frames[0]]
    picks = np.round(np.linspace(0, len(frames) - 1, count)).astype(int)
    return [frames[k] for k in picks]


def select_frames(
    ranges: dict, video_frames: int, key: str, max_frames: dict | None = None
) -> tuple[list[tuple[int, int]], dict]:
    """A video subject's (frame, split) pairs from its ``train`` (default: every frame) and ``test``
    ranges, each thinned to at most ``max_frames[split name]`` frames; and a note of what was thinned
    ({split: [asked, kept]})."""
    max_frames = max_frames or {}
    out, thinned = [], {}
    for name, split in RANGE_SPLITS.items():
        spec = ranges.get(name, [0, video_frames - 1, 1] if name == "train" else None)
        if spec is None:
            continue
        picked = [i for i, _ in frame_range(spec, split, f"{key}.{name}")]
        kept = thin(picked, int(max_frames.get(name, 0)))
        if len(kept) < len(picked):
            thinned[name] = [len(picked), len(kept)]
            log.info("%s.%s: %d frames asked for, %d kept, evenly spaced (preprocess.max_frames.%s)", key, name,
                     len(picked), len(kept), name)  # fmt: skip
        out += [(i, split) for i in kept]
    return out, thinned
