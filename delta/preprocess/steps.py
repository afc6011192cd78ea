"""Model-based preprocessing steps (matting, parsing), streamed over a subject's frames.

Each step writes one HDF5 file of per-frame masks at the source resolution,
indexed by video frame, which :mod:`delta.preprocess.frames` reads as if the
dataset had shipped them; ``attrs['model']`` records which model made them.
"""

from __future__ import annotations

import logging
from pathlib import Path

import h5py
import numpy as np

from delta import DeltaError
from delta.io import atomic_path
from delta.preprocess import onnx_models as om
from delta.preprocess.frames import iter_video

log = logging.getLogger(__name__)


def _mediapipe(path, threads=1, config_key=None):
    from delta.preprocess.pose_landmarks import PoseLandmarker

    landmarker = PoseLandmarker(path, threads=threads, config_key=config_key)
    return lambda frame: landmarker(frame).mask


MATTING = {"rvm": om.RobustVideoMatting, "modnet": om.MODNet, "mediapipe": _mediapipe}


def _default_parser(path, threads=1, config_key=None):
    """MediaPipe pose landmarks + the skin-colour parser (:mod:`delta.preprocess.parsing_default`)."""
    from delta.preprocess.parsing_default import VideoParser
    from delta.preprocess.pose_landmarks import PoseLandmarker

    landmarker, parser = PoseLandmarker(path, threads=threads, config_key=config_key), VideoParser()

    def parse(frame):
        pose = landmarker(frame)
        return parser(frame, pose.mask, pose)

    return parse


PARSING = {"default": _default_parser, "u2net_cloth": om.ClothSegmentation, "bisenet_face": om.FaceParsing}
PARSED = {"default": ("clothing", "skin", "hair"), "u2net_cloth": ("clothing",), "bisenet_face": ("hair", "skin")}


def _model(kind: str, table: dict, path: str, threads: int, key: str):
    if kind not in table:
        raise DeltaError(f"{key}: unknown model '{kind}'; known: {sorted(table)}")
    return table[kind](path, threads=threads, config_key=f"{key.rsplit('.', 1)[0]}.path")


def _masks_file(out: Path, n: int, shape: tuple[int, int], names: tuple[str, ...]):
    f = h5py.File(out, "w")
    kw = dict(chunks=(1, *shape), compression="gzip", compression_opts=3, track_times=False)
    return f, {k: f.create_dataset(k, (n, *shape), np.uint8, **kw) for k in names}


def video_length(video: str | Path) -> int:
    import cv2

    cap = cv2.VideoCapture(str(video))
    if not cap.isOpened():
        raise DeltaError(f"cannot open video {video} (missing, empty or not a video)")
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    cap.release()
    if n <= 0:
        raise DeltaError(f"{video}: the video has no frame")
    return n


def run_matting(video: Path, num_frames: int, kind: str, path: str, out: str | Path, threads: int = 1) -> None:
    """Person alpha (0-255) for every frame of the video, in order (RVM is recurrent)."""
    model = _model(kind, MATTING, path, threads, "preprocess.matting.model")
    with atomic_path(out) as tmp:
        f = None
        try:
            for i, rgb in iter_video(Path(video), set(range(num_frames))):
                if f is None:
                    f, d = _masks_file(tmp, num_frames, rgb.shape[:2], ("person",))
                d["person"][i] = np.round(np.clip(model(rgb), 0, 1) * 255).astype(np.uint8)
            f.attrs["model"] = f"{kind}:{Path(path).name}"
        finally:
            if f is not None:
                f.close()
    log.info("matting (%s) of %d frames -> %s", kind, num_frames, out)


def run_parsing(video: Path, num_frames: int, kind: str, path: str, out: str | Path, threads: int = 1) -> None:
    """Clothing, skin and hair (default), clothing (U²-Net cloth) or hair and face skin (BiSeNet face
    parsing) masks, 0/1, per frame."""
    model = _model(kind, PARSING, path, threads, "preprocess.parsing.model")
    names = PARSED[kind]
    with atomic_path(out) as tmp:
        f = None
        try:
            for i, rgb in iter_video(Path(video), set(range(num_frames))):
                if f is None:
                    f, d = _masks_file(tmp, num_frames, rgb.shape[:2], names)
                result = model(rgb)
                if kind == "default":
                    for name in names:
                        d[name][i] = result[name]
                elif kind == "u2net_cloth":
                    d["clothing"][i] = om.clothing_mask(result)
                else:
                    d["hair"][i] = om.hair_mask(result)
                    d["skin"][i] = om.face_skin_mask(result)
            f.attrs["model"] = f"{kind}:{Path(path).name}"
        finally:
            if f is not None:
                f.close()
    log.info("parsing (%s) of %d frames -> %s", kind, num_frames, out)


def run_keypoints(video: Path, num_frames: int, kind: str, path: str, out: str | Path, threads: int = 1,
                  face_path: str | None = None) -> None:  # fmt: skip
    """OpenPose-18 keypoints (N, 18, 3) and, with ``face_path``, face-mesh landmarks (N, 468, 3),
    as (u, v, confidence), per frame from MediaPipe's pose (and face) landmark models."""
    from delta.preprocess.pose_landmarks import FaceLandmarker, PoseLandmarker

    if kind != "mediapipe":
        raise DeltaError(f"preprocess.keypoints.model: unknown model '{kind}'; known: ['mediapipe']")
    model = PoseLandmarker(path, threads=threads, config_key="preprocess.keypoints.path")
    face = FaceLandmarker(face_path, threads=threads) if face_path else None
    keypoints = np.zeros((num_frames, 18, 3), np.float32)
    faces = np.zeros((num_frames, 468, 3), np.float32)
    for i, rgb in iter_video(Path(video), set(range(num_frames))):
        pose = model(rgb)
        keypoints[i] = pose.openpose18()
        if face is not None:
            faces[i] = face(rgb, pose)
    with atomic_path(out) as tmp, h5py.File(tmp, "w") as f:
        f.create_dataset("keypoints", data=keypoints, track_times=False)
        if face is not None:
            f.create_dataset("face_landmarks", data=faces, track_times=False)
        f.attrs["model"] = f"{kind}:{Path(path).name}"
    log.info("keypoints (%s) of %d frames -> %s", kind, num_frames, out)


def attach(source, path: str | Path) -> None:
    """Add the masks of a step's output file to a Source's provided arrays (not overriding the dataset's).

    Each array's shape is checked against the source: (N, H, W) masks of the video's size,
    (N, 18, 3) keypoints, (N, 468, 3) face landmarks, N covering every selected frame.
    """
    from delta.data.sources import frame_array, mask_what

    f = h5py.File(path, "r")
    model = str(f.attrs.get("model", "unknown"))
    W, H = source.camera.width, source.camera.height
    needed = max((i for i, _ in source.frames), default=-1) + 1
    points = {"keypoints": ((18, 3), "18 OpenPose keypoints (u, v, confidence) a frame"),
              "face_landmarks": ((468, 3), "468 face-mesh landmarks (u, v, confidence) a frame")}  # fmt: skip
    try:
        for name in f:
            if name in source.provided:
                continue
            shape, what = points.get(name, ((H, W), mask_what(W, H, source.video)))
            source.provided[name] = frame_array(path, name, f[name], shape, what, needed)
            source.origin[name] = f"model:{model}"
    except DeltaError:
        f.close()
        raise
    previous = source.close
    source.close = lambda: (previous(), f.close())
