"""Dataset adapters: where a subject's video, camera, splits and provided annotations are.

Each adapter returns a ``Source``; preprocessing reads it frame by frame. What a
dataset provides (People Snapshot's masks and keypoints, the synthetic ground
truth) is used as is; the steps that would compute it are not run.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Callable

import h5py
import numpy as np
import torch

from delta import DeltaError
from delta.data import STANDARD_SPLITS
from delta.body.face_points import FacePoints
from delta.cameras.models import OrthographicCamera, PinholeCamera, check_camera
from delta.data.video import frame_range, probe_video, select_frames
from delta.data import peoplesnapshot as ps

log = logging.getLogger(__name__)
FrameArray = Callable[[int], np.ndarray]


@dataclasses.dataclass
class Source:
    """One subject's capture and what its dataset provides."""

    video: Path
    camera: object
    """PinholeCamera (possibly with distortion) or OrthographicCamera of the source frames."""
    frames: list[tuple[int, int]]
    """(frame index in the video, split id) of every frame to prepare."""
    num_video_frames: int
    provided: dict[str, FrameArray]
    """Per-frame arrays the dataset ships: 'person' (H, W) uint8 0-255, 'clothing'/'skin'/'hair' 0/1,
    'keypoints' (18, 3), 'face_points' (K, 3) (u, v, confidence)."""
    origin: dict[str, str]
    """Where each provided array comes from (recorded in the frame record)."""
    close: Callable[[], None] = lambda: None
    body_params: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    """Per-video-frame body parameters the dataset ships (People Snapshot's SMPL 'pose', 'trans'),
    and per-subject ones ('betas'); copied into the record for the selected frames."""
    face_points: FacePoints | None = None
    """Where the provided 'face_points' (K, 3) a frame sit on the body mesh."""


def frame_array(path, name: str, dset, per_frame: tuple[int, ...], what: str, needed: int = 0,
                scale: float = 1.0) -> FrameArray:  # fmt: skip
    """``i -> dset[i]`` once ``dset``'s shape is checked: (N, *per_frame) with N >= ``needed``.

    Masks (``per_frame`` (H, W)) stored with a trailing channel axis of 1, (N, H, W, 1), are read
    without it (logged); any other shape raises a DeltaError naming the file, the shape found and the
    one expected (``what`` says what a frame's entry is). ``scale`` multiplies and casts to uint8.
    """
    shape = tuple(int(n) for n in dset.shape)
    squeeze = len(per_frame) == 2 and len(shape) == 4 and shape[3] == 1
    fits = len(shape) == 1 + len(per_frame) + squeeze and shape[1 : 1 + len(per_frame)] == tuple(per_frame)
    if not fits or shape[0] < needed:
        count = f"N >= {needed}" if needed else "N"
        raise DeltaError(f"{path}: '{name}' has shape {shape}, expected ({count}, {', '.join(map(str, per_frame))}): "
                         f"{what}")  # fmt: skip
    if squeeze:
        log.info("%s: '%s' has shape %s: read without its trailing channel axis of 1", path, name, shape)

    def get(i: int) -> np.ndarray:
        a = np.asarray(dset[i])
        a = a[..., 0] if squeeze else a
        return (a * scale).astype(np.uint8) if scale != 1.0 else a

    return get


def mask_what(width: int, height: int, video) -> str:
    """What a mask file holds for each frame (for messages)."""
    return f"one {width}x{height} mask a frame of {Path(video).name}"


def _h5_frames(path: Path, key: str, width: int, height: int, video,
               scale: float = 1.0) -> tuple[FrameArray, Callable[[], None], int]:  # fmt: skip
    f = h5py.File(path, "r")
    if key not in f:
        f.close()
        raise DeltaError(f"{path}: no dataset '{key}' (found {sorted(f)})")
    dset = f[key]
    try:
        get = frame_array(path, key, dset, (height, width), mask_what(width, height, video), scale=scale)
    except DeltaError:
        f.close()
        raise
    return get, f.close, int(dset.shape[0])


def peoplesnapshot_source(root: str | Path, subject: str, cfg: dict) -> Source:
    """People Snapshot: ``{root}/{subject}/{subject}.mp4``, masks.hdf5, camera.pkl, keypoints.hdf5."""
    d = Path(root) / subject
    need = [d / f"{subject}.mp4", d / "masks.hdf5", d / "camera.pkl", d / "keypoints.hdf5"]
    missing = [str(p) for p in need if not p.is_file()]
    if missing:
        raise DeltaError(f"People Snapshot subject '{subject}': missing {missing}. Download the dataset "
                         f"(licensed) and set datasets.peoplesnapshot.root to the folder holding '{subject}/'")  # fmt: skip
    camera = ps.read_camera(d / "camera.pkl").to_pinhole()
    check_camera(camera, str(d / "camera.pkl"))
    key = f"datasets.peoplesnapshot.subjects.{subject}"
    cfg = {**STANDARD_SPLITS.get(subject, {}), **cfg}
    if "train" not in cfg or "test" not in cfg:
        raise DeltaError(f"{key}: give 'train' and 'test' frame ranges [start, end, step] (standard ones are "
                         f"known for {sorted(STANDARD_SPLITS)})")  # fmt: skip
    frames = frame_range(cfg.get("train"), 0, f"{key}.train") + frame_range(cfg.get("test"), 1, f"{key}.test")
    kp_all = ps.read_keypoints(d / "keypoints.hdf5")
    masks, close_m, n_masks = _h5_frames(d / "masks.hdf5", "masks", camera.width, camera.height, need[0], 255.0)
    closers = [close_m]
    body, origin = {}, {"person": "dataset:masks.hdf5", "keypoints": "dataset:keypoints.hdf5"}
    if (d / "reconstructed_poses.hdf5").is_file():  # optional: SMPL poses of every frame
        with h5py.File(d / "reconstructed_poses.hdf5", "r") as f:
            body = {f"smpl_{k}": np.asarray(f[k]) for k in ("pose", "trans", "betas") if k in f}
        origin["smpl"] = "dataset:reconstructed_poses.hdf5"
    return Source(
        video=need[0],
        camera=camera,
        frames=frames,
        num_video_frames=min(n_masks, len(kp_all)),
        provided={"person": masks, "keypoints": lambda i: kp_all[i]},
        origin=origin,
        close=lambda: [c() for c in closers],
        body_params=body,
    )


def default_camera(width: int, height: int) -> PinholeCamera:
    """The camera assumed for a video without one: pinhole, focal 1.2 x the longer side
    (about a 45° field of view), principal point at the centre, no distortion, at the origin."""
    f = 1.2 * max(width, height)
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float64)
    return PinholeCamera(K, torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                         torch.zeros(5, dtype=torch.float64), width, height)  # fmt: skip


def read_camera_json(path: Path, width: int, height: int) -> PinholeCamera:
    """``{"K": 3x3 numbers, "dist": up to 5 numbers (k1, k2, p1, p2, k3)}``; errors name the file and key."""
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise DeltaError(f"{path}: not valid JSON ({err})") from None
    if not isinstance(data, dict):
        raise DeltaError(f"{path}: expected a JSON object with 'K' (3x3) and optionally 'dist', "
                         f"found {type(data).__name__}")  # fmt: skip
    unknown = sorted(set(data) - {"K", "dist"})
    if unknown:
        raise DeltaError(f"{path}: unknown key(s) {unknown} (known: 'K', 'dist')")
    if "K" not in data:
        raise DeltaError(f"{path}: expected a 'K' (3x3) entry")

    def numbers(key: str, shape: str, ok) -> np.ndarray:
        value = data[key]
        try:
            a = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            a = None
        if a is None or isinstance(value, (str, bool)) or np.asarray(value).dtype.kind not in "iuf" or not ok(a.shape):
            raise DeltaError(f"{path}: '{key}' must be {shape}, found {json.dumps(value)[:80]}")
        return a

    K = numbers("K", "a 3x3 array of numbers", lambda s: s == (3, 3))
    dist = np.zeros(5)
    if "dist" in data:
        d = numbers("dist", "a list of at most 5 numbers (k1, k2, p1, p2, k3)", lambda s: len(s) == 1 and s[0] <= 5)
        dist[: len(d)] = d
    return PinholeCamera(torch.from_numpy(K), torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                         torch.from_numpy(dist), width, height)  # fmt: skip


def video_source(root: str | Path, subject: str, cfg: dict, max_frames: dict | None = None) -> Source:
    """Any video ``{root}/{subject}.mp4``, with an optional ``{root}/{subject}.camera.json``
    (``{"K": 3x3, "dist": [k1, k2, p1, p2, k3]}``); annotations come from the model steps. Its ranges are
    thinned to ``max_frames`` ({"train": n, "test": m}) each; a display rotation is applied."""
    video = Path(root) / f"{subject}.mp4"
    info = probe_video(video)
    W, H = info.width, info.height
    cam_file = Path(root) / f"{subject}.camera.json"
    camera = default_camera(W, H)
    if cam_file.is_file():
        camera = read_camera_json(cam_file, W, H)
    check_camera(camera, str(cam_file) if cam_file.is_file() else f"{video} (default camera)")
    frames, thinned = select_frames(cfg, info.frames, f"datasets.*.subjects.{subject}", max_frames)
    origin = {"camera": "file" if cam_file.is_file() else "default"}
    if info.rotation:
        origin["rotation"] = f"{info.rotation} degrees, applied"
        log.info("%s: stored with a %d degree display rotation: frames are read upright, %dx%d", video, info.rotation,
                 W, H)  # fmt: skip
    if thinned:
        origin["thinned"] = ", ".join(f"{k} {a} -> {b}" for k, (a, b) in thinned.items())
    return Source(video=video, camera=camera, frames=frames, num_video_frames=info.frames, provided={}, origin=origin)


def synthetic_source(capture: str | Path, subject: str) -> Source:
    """A generated capture: the video plus its ground truth used as the dataset's annotations."""
    capture = Path(capture)
    gt = capture / "gt"
    with np.load(gt / "params.npz", allow_pickle=False) as p:
        if str(p["camera_model"]) == "pinhole":
            t = lambda k: torch.from_numpy(p[k])  # noqa: E731
            camera: object = PinholeCamera(t("K"), t("R"), t("t"), t("dist"), int(p["width"]), int(p["height"]))
        else:
            camera = OrthographicCamera(torch.tensor(float(p["ortho_scale"][0])),
                                        torch.from_numpy(p["ortho_trans"][0]), int(p["width"]), int(p["height"]))  # fmt: skip
    check_camera(camera, str(gt / "params.npz"))
    splits = json.loads((gt / "splits.json").read_text())
    frames = sorted((i, s) for s, name in enumerate(("train", "test_view", "test_pose")) for i in splits[name])
    h5 = h5py.File(gt / "frames.h5", "r")
    video = capture / f"{subject}.mp4"
    what = mask_what(camera.width, camera.height, video)
    try:
        masks = {name: frame_array(gt / "frames.h5", key, h5[key], (camera.height, camera.width), what)
                 for name, key in (("person", "alpha"), ("clothing", "clothing"), ("skin", "skin"), ("hair", "hair"))}  # fmt: skip
        keypoints = np.asarray(h5["keypoints"])
    except DeltaError:
        h5.close()
        raise
    face = {}
    if "face_points" in h5:  # a talking face: its dense face points and their embedding on the body mesh
        points = np.asarray(h5["face_points"])
        face = {"face_points": lambda i: points[i]}
    source = Source(
        video=video,
        camera=camera,
        frames=frames,
        num_video_frames=int(h5["person"].shape[0]),
        provided={**masks, "keypoints": lambda i: keypoints[i], **face},
        origin={
            k: f"dataset:gt/frames.h5:{v}"
            for k, v in (
                ("person", "alpha"),
                ("clothing", "clothing"),
                ("skin", "skin"),
                ("hair", "hair"),
                ("keypoints", "keypoints"),
                ("face_points", "face_points"),
            )
        },  # fmt: skip
        close=h5.close,
    )
    if face:
        source.face_points = FacePoints(torch.from_numpy(np.asarray(h5["face_point_vertices"])).long(),
                                        torch.from_numpy(np.asarray(h5["face_point_bary"])).double())  # fmt: skip
    return source
