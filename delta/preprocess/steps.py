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
from delta.data.video import FRAMINGS, iter_video, probe_video, select_frames

log = logging.getLogger(__name__)


#: the converted models a head framing runs, next to the pose model
HEAD_MODELS = ("face_detection_short_range.onnx", "face_landmark.onnx")


def head_model_paths(path) -> tuple[Path, ...]:
    """The face detector and face mesh beside the pose model ``path`` (the converted models' folder)."""
    return tuple(Path(path).parent / name for name in HEAD_MODELS)


def landmarker(path, threads=1, config_key=None, framing="full"):
    """MediaPipe's pose landmarker (``full``) or the face-tracking head landmarker (``head``, with the
    converted face models found beside ``path``): frame -> PoseResult."""
    from delta.preprocess.face_tracking import HeadLandmarker
    from delta.preprocess.pose_landmarks import PoseLandmarker

    if framing not in FRAMINGS:
        raise DeltaError(f"framing '{framing}': expected one of {list(FRAMINGS)}")
    if framing == "full":
        return PoseLandmarker(path, threads=threads, config_key=config_key)
    return HeadLandmarker(*head_model_paths(path), threads=threads)


def _mediapipe(path, threads=1, config_key=None, framing="full"):
    model = landmarker(path, threads, config_key, framing)
    return lambda frame: model(frame).mask


MATTING = {"rvm": om.RobustVideoMatting, "modnet": om.MODNet, "mediapipe": _mediapipe}


def _default_parser(path, threads=1, config_key=None, framing="full", person=None):
    """MediaPipe pose (or tracked face) landmarks + the skin-colour parser (:mod:`delta.preprocess.parsing_default`),
    within the landmarker's own person mask or, given ``person`` (:class:`PersonMasks`), the matting step's."""
    from delta.preprocess.parsing_default import VideoParser

    model, parser = landmarker(path, threads, config_key, framing), VideoParser()

    def parse(i, frame):
        # a given mask is the landmarker's result's: a tracked head's GrabCut is not cut twice
        pose = model(frame, mask=None if person is None else person(i, frame.shape[:2]))
        return parser(frame, pose.mask, pose)

    return parse


class PersonMasks:
    """The person alpha of a matting step's file (``delta matte``), frame by frame, as 0..1 floats: the
    parser's person where the matting step ran, so that the parts lie inside the record's person mask and
    a tracked head's mask is cut once."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_file():
            raise DeltaError(f"{self.path}: no such matting file (--person)")
        self.file = h5py.File(self.path, "r")
        if "person" not in self.file:
            self.file.close()
            raise DeltaError(f"{self.path}: not a matting step's file: it holds no 'person' masks")
        self.masks = self.file["person"]

    def __call__(self, i: int, shape: tuple[int, int]) -> np.ndarray:
        if i >= len(self.masks):
            raise DeltaError(f"{self.path}: no person mask for video frame {i} (the file holds {len(self.masks)} rows)")
        if tuple(self.masks.shape[1:]) != tuple(shape):
            raise DeltaError(f"{self.path}: person masks are {self.masks.shape[2]}x{self.masks.shape[1]}, "
                             f"the video's frames {shape[1]}x{shape[0]}")  # fmt: skip
        return self.masks[i].astype(np.float32) / 255.0

    def close(self) -> None:
        self.file.close()


PARSING = {"default": _default_parser, "u2net_cloth": om.ClothSegmentation, "bisenet_face": om.FaceParsing}
PARSED = {"default": ("clothing", "skin", "hair"), "u2net_cloth": ("clothing",), "bisenet_face": ("hair", "skin")}


#: the models that see the frame through the landmarker, and so follow the framing
LANDMARKED = ("mediapipe", "default")


def _model(kind: str, table: dict, path: str, threads: int, key: str, framing: str = "full", **extra):
    if kind not in table:
        raise DeltaError(f"{key}: unknown model '{kind}'; known: {sorted(table)}")
    if kind in LANDMARKED:
        extra["framing"] = framing
    return table[kind](path, threads=threads, config_key=f"{key.rsplit('.', 1)[0]}.path", **extra)


def model_name(kind: str, path: str, framing: str = "full") -> str:
    """What a step's file records as its model: ``kind:file``, for a tracked head ``kind:head:`` and the face models."""
    if framing == "head" and kind in LANDMARKED:
        return f"{kind}:head:{'+'.join(HEAD_MODELS)}"
    return f"{kind}:{Path(path).name}"


def _masks_file(out: Path, n: int, shape: tuple[int, int], names: tuple[str, ...]):
    f = h5py.File(out, "w")
    kw = dict(chunks=(1, *shape), compression="gzip", compression_opts=3, track_times=False)
    return f, {k: f.create_dataset(k, (n, *shape), np.uint8, maxshape=(None, *shape), **kw) for k in names}


def step_frames(video: str | Path, frames: dict | None, max_frames: dict | None = None) -> set[int] | None:
    """The frames a step analyses: a video subject's selected frames (its ``frames`` ranges thinned to
    ``max_frames``, as the record selects them); None (every frame) without ranges."""
    if frames is None:
        return None
    info = probe_video(video)
    selected, _ = select_frames(frames, info.frames, f"datasets.*.subjects.{Path(video).stem}", max_frames)
    return {i for i, _ in selected}


def _rows(video: Path, wanted: set[int] | None) -> int:
    """Rows of a step's arrays: one per video frame up to the last one analysed (the header's count
    for every frame; grown if the video holds more)."""
    return max(wanted) + 1 if wanted else probe_video(video).frames


def _decoded(video: Path, wanted: set[int] | None, what: str):
    """(index, RGB) of the analysed frames, read until the video ends, with a warning for wanted frames
    it does not hold (a header that overstates the count): their rows stay empty."""
    last = -1
    for i, rgb in iter_video(video, wanted, to_end=True):
        last = i
        yield i, rgb
    missing = sorted(f for f in (wanted or ()) if f > last)
    if missing:
        log.warning("%s: %s: the video ends after frame %d; %d frame(s) asked for are not there, from %d on",
                    video, what, last, len(missing), missing[0])  # fmt: skip


def _mask_step(video: Path, wanted: set[int] | None, names: tuple[str, ...], compute, out: str | Path, model: str,
               what: str) -> int:  # fmt: skip
    """Write the masks ``names`` that ``compute(i, rgb) -> {name: (H, W) uint8}`` gives for the ``wanted``
    frames (None: all), one row per video frame, empty where no frame was analysed; returns how many
    frames were analysed."""
    rows = _rows(Path(video), wanted)
    count = 0
    with atomic_path(out) as tmp:
        f = None
        try:
            for i, rgb in _decoded(Path(video), wanted, what):
                if f is None:
                    f, d = _masks_file(tmp, rows, rgb.shape[:2], names)
                for name, mask in compute(i, rgb).items():
                    if i >= d[name].shape[0]:  # the video holds more frames than its header said
                        d[name].resize(i + 1, axis=0)
                    d[name][i] = mask
                count += 1
            f.attrs["model"] = model
        finally:
            if f is not None:
                f.close()
    return count


def run_matting(video: Path, wanted: set[int] | None, kind: str, path: str, out: str | Path, threads: int = 1,
                framing: str = "full") -> None:  # fmt: skip
    """Person alpha (0-255) for the ``wanted`` frames of the video (None: all), in order (RVM is
    recurrent); one row per video frame, empty where no frame was analysed."""
    model = _model(kind, MATTING, path, threads, "preprocess.matting.model", framing)

    def alpha(i, rgb):
        return {"person": np.round(np.clip(model(rgb), 0, 1) * 255).astype(np.uint8)}

    count = _mask_step(video, wanted, ("person",), alpha, out, model_name(kind, path, framing), "matting")
    log.info("matting (%s) of %d frames -> %s", kind, count, out)


def run_parsing(video: Path, wanted: set[int] | None, kind: str, path: str, out: str | Path, threads: int = 1,
                framing: str = "full", person: str | Path | None = None) -> None:  # fmt: skip
    """Clothing, skin and hair (default), clothing (U²-Net cloth) or hair and face skin (BiSeNet face
    parsing) masks, 0/1, for the ``wanted`` frames (None: all). ``person``: a matting step's file whose
    person masks the default parser partitions (the other parsers see the frame alone)."""
    if person is not None and kind != "default":
        raise DeltaError(f"--person: only the default parser partitions a matting step's person, not '{kind}'")
    masks = PersonMasks(person) if person is not None else None
    extra = {"person": masks} if masks is not None else {}
    model = _model(kind, PARSING, path, threads, "preprocess.parsing.model", framing, **extra)
    names = PARSED[kind]

    def parts(i, rgb):
        if kind == "default":
            result = model(i, rgb)
            return {name: result[name] for name in names}
        result = model(rgb)
        if kind == "u2net_cloth":
            return {"clothing": om.clothing_mask(result)}
        return {"hair": om.hair_mask(result), "skin": om.face_skin_mask(result)}

    try:
        count = _mask_step(video, wanted, names, parts, out, model_name(kind, path, framing), "parsing")
    finally:
        if masks is not None:
            masks.close()
    log.info("parsing (%s) of %d frames%s -> %s", kind, count, f" within {person}'s person" if masks else "", out)


def run_keypoints(video: Path, wanted: set[int] | None, kind: str, path: str, out: str | Path, threads: int = 1,
                  face_path: str | None = None, framing: str = "full") -> None:  # fmt: skip
    """OpenPose-18 keypoints (N, 18, 3) and, with ``face_path`` or a ``head`` framing, face-mesh landmarks
    (N, 468, 3), as (u, v, confidence), for the ``wanted`` frames (None: all) from MediaPipe's pose (and
    face) landmark models, or for a head from the tracked face alone; zero rows elsewhere. The body model
    also gives the keypoints' relative depths, ``keypoint_depth`` (N, 18) in metres (NaN elsewhere)."""
    from delta.preprocess.face_tracking import FaceTracker, blazepose_from_face
    from delta.preprocess.pose_landmarks import FaceLandmarker, openpose18

    if kind != "mediapipe":
        raise DeltaError(f"preprocess.keypoints.model: unknown model '{kind}'; known: ['mediapipe']")
    head = framing == "head"
    if head:  # the face alone: no mask wanted here, so none is cut
        tracker = FaceTracker(*head_model_paths(path), threads=threads)
    else:
        model = landmarker(path, threads, "preprocess.keypoints.path", framing)
    face = FaceLandmarker(face_path, threads=threads) if face_path and not head else None
    keypoints, faces, depths = [], [], []
    for i, rgb in _decoded(Path(video), wanted, "keypoints"):
        if head:
            seen = tracker(rgb)
            keypoints.append((i, openpose18(blazepose_from_face(seen), float(seen[0, 2]))))
            faces.append((i, seen))
            continue
        pose = model(rgb)
        keypoints.append((i, pose.openpose18()))
        depths.append((i, pose.depth18()))
        if face is not None:
            faces.append((i, face(rgb, pose)))
    if head and not any(a[0, 2] > 0 for _, a in faces):
        raise DeltaError(f"{video}: no face found in any of the {len(faces)} frames analysed; 'framing: head' tracks "
                         "a head-and-shoulders close-up by its face (a body seen whole wants framing: full)")  # fmt: skip
    rows = max(_rows(Path(video), wanted), max((i for i, _ in keypoints), default=-1) + 1)

    def table(items, shape, fill=0.0):
        out = np.full((rows, *shape), fill, np.float32)
        for i, a in items:
            out[i] = a
        return out

    with atomic_path(out) as tmp, h5py.File(tmp, "w") as f:
        f.create_dataset("keypoints", data=table(keypoints, (18, 3)), track_times=False)
        if depths:
            f.create_dataset("keypoint_depth", data=table(depths, (18,), np.nan), track_times=False)
        if head or face is not None:
            f.create_dataset("face_landmarks", data=table(faces, (468, 3)), track_times=False)
        f.attrs["model"] = model_name(kind, path, framing)
    log.info("keypoints (%s) of %d frames -> %s", kind, len(keypoints), out)


def attach(source, path: str | Path) -> None:
    """Add the masks of a step's output file to a Source's provided arrays (not overriding the dataset's).

    Each array's shape is checked against the source: (N, H, W) masks of the video's size,
    (N, 18, 3) keypoints, (N, 18) their depths, (N, 468, 3) face landmarks, N covering every selected frame.
    """
    from delta.data.sources import frame_array, mask_what

    f = h5py.File(path, "r")
    model = str(f.attrs.get("model", "unknown"))
    W, H = source.camera.width, source.camera.height
    needed = max((i for i, _ in source.frames), default=-1) + 1
    points = {"keypoints": ((18, 3), "18 OpenPose keypoints (u, v, confidence) a frame"),
              "keypoint_depth": ((18,), "the 18 OpenPose keypoints' relative depths (metres) a frame"),
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


def embed_landmarks(source, path: str | Path) -> None:
    """Give a Source's face-mesh landmarks a place on the body mesh: its ``face_points`` become the
    landmarks the embedding file (:class:`delta.body.face_points.LandmarkEmbedding`) keeps, so the init
    fit tracks the face. A source without landmarks, or with face points of its own, is left as it is."""
    from delta.body.face_points import LandmarkEmbedding

    if "face_landmarks" not in source.provided or "face_points" in source.provided:
        return
    embedding = LandmarkEmbedding.load(path)
    landmarks, kept = source.provided["face_landmarks"], embedding.landmarks
    source.provided["face_points"] = lambda i: np.asarray(landmarks(i))[kept]
    source.face_points = embedding.points
    source.origin["face_points"] = f"{source.origin.get('face_landmarks', 'face landmarks')} on {Path(path).name}"
