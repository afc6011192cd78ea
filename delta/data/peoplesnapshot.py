"""People Snapshot's file layout: read (never unpickling code) and write.

Per subject: ``{subject}.mp4``, ``masks.hdf5`` (``masks``: N x H x W),
``camera.pkl`` (``camera_f``, ``camera_c``, ``camera_k``, ``camera_rt``,
``camera_t``, ``width``, ``height``) and ``keypoints.hdf5`` (``keypoints``:
N x 54 = 18 OpenPose points x (x, y, confidence)).
"""

from __future__ import annotations

import dataclasses
import math
import os
import pickle
from pathlib import Path

import cv2
import h5py
import numpy as np
import torch

from delta import DeltaError
from delta.cameras.models import PinholeCamera
from delta.io import atomic_path
from delta.safe_pickle import load_pickle

CAMERA_KEYS = ("camera_f", "camera_c", "camera_k", "camera_rt", "camera_t", "width", "height")
#: how many values each array of camera.pkl may hold
CAMERA_SIZES = {"camera_f": (2,), "camera_c": (2,), "camera_k": (0, 1, 2, 3, 4, 5), "camera_rt": (3,), "camera_t": (3,)}


@dataclasses.dataclass
class SnapshotCamera:
    f: np.ndarray
    c: np.ndarray
    k: np.ndarray
    rt: np.ndarray
    t: np.ndarray
    width: int
    height: int

    def to_pinhole(self) -> PinholeCamera:
        K = torch.tensor([[self.f[0], 0, self.c[0]], [0, self.f[1], self.c[1]], [0, 0, 1]], dtype=torch.float64)
        R = torch.from_numpy(cv2.Rodrigues(np.asarray(self.rt, dtype=np.float64).reshape(3, 1))[0])
        dist = torch.zeros(5, dtype=torch.float64)
        dist[: len(self.k)] = torch.as_tensor(np.asarray(self.k, dtype=np.float64))
        return PinholeCamera(K, R, torch.as_tensor(self.t, dtype=torch.float64), dist, self.width, self.height)


def read_camera(path: str | os.PathLike) -> SnapshotCamera:
    """camera.pkl through the restricted unpickler; errors name the file and key."""
    data = load_pickle(path)
    if not isinstance(data, dict):
        raise DeltaError(f"{path}: expected a dict, found {type(data).__name__}")
    missing = [k for k in CAMERA_KEYS if k not in data]
    if missing:
        raise DeltaError(f"{path}: missing camera keys {missing}")
    arr = {}
    for key, sizes in CAMERA_SIZES.items():
        try:
            arr[key] = np.asarray(data[key], dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise DeltaError(f"{path}: camera key '{key}' must hold numbers, found {data[key]!r:.80}") from None
        if arr[key].size not in sizes:
            expected = sizes[0] if len(sizes) == 1 else f"at most {max(sizes)}"
            raise DeltaError(f"{path}: camera key '{key}' holds {arr[key].size} values, expected {expected}")
        if not np.isfinite(arr[key]).all():
            raise DeltaError(f"{path}: camera key '{key}' is not finite: {arr[key].tolist()}")
    pixels = {}
    for key in ("width", "height"):
        try:
            value = float(np.asarray(data[key], dtype=np.float64).reshape(()))
        except (TypeError, ValueError):
            value = math.nan
        if not (math.isfinite(value) and value == round(value) and value > 0):
            raise DeltaError(f"{path}: camera key '{key}' must be a whole number of pixels > 0, "
                             f"found {data[key]!r:.80}")  # fmt: skip
        pixels[key] = int(value)
    return SnapshotCamera(arr["camera_f"], arr["camera_c"], arr["camera_k"], arr["camera_rt"], arr["camera_t"],
                          pixels["width"], pixels["height"])  # fmt: skip


def write_camera(path: str | os.PathLike, camera: PinholeCamera) -> None:
    K = camera.K.numpy()
    data = {
        "camera_f": np.array([K[0, 0], K[1, 1]]),
        "camera_c": np.array([K[0, 2], K[1, 2]]),
        "camera_k": camera.dist.numpy().copy(),
        "camera_rt": cv2.Rodrigues(camera.R.numpy())[0].reshape(3),
        "camera_t": camera.t.numpy().copy(),
        "width": int(camera.width),
        "height": int(camera.height),
    }
    with atomic_path(path) as tmp:
        tmp.write_bytes(pickle.dumps(data, protocol=2))


def iter_masks(path: str | os.PathLike):
    """Yield (H, W) uint8 masks one frame at a time (never the whole array)."""
    with h5py.File(path, "r") as f:
        if "masks" not in f:
            raise DeltaError(f"{path}: no dataset 'masks' (found {list(f)})")
        for i in range(f["masks"].shape[0]):
            yield np.asarray(f["masks"][i])


def read_keypoints(path: str | os.PathLike) -> np.ndarray:
    """(N, 18, 3) keypoints (x, y, confidence)."""
    with h5py.File(path, "r") as f:
        if "keypoints" not in f:
            raise DeltaError(f"{path}: no dataset 'keypoints' (found {list(f)})")
        kp = np.asarray(f["keypoints"])
    if kp.ndim != 2 or kp.shape[1] != 54:
        raise DeltaError(f"{path}: 'keypoints' has shape {kp.shape}, expected (N, 54)")
    return kp.reshape(len(kp), 18, 3)


def write_layout(out_dir: str | os.PathLike, subject: str, video: str | os.PathLike, camera: PinholeCamera,
                 masks, keypoints: np.ndarray) -> None:  # fmt: skip
    """Write a subject in People Snapshot's layout; ``masks`` is an iterable of (H, W) arrays."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / f"{subject}.mp4") as tmp:
        tmp.write_bytes(Path(video).read_bytes())
    write_camera(out / "camera.pkl", camera)
    n = len(keypoints)
    with atomic_path(out / "masks.hdf5") as tmp:
        with h5py.File(tmp, "w") as f:
            d = f.create_dataset("masks", (n, camera.height, camera.width), dtype=np.uint8,
                                 chunks=(1, camera.height, camera.width), compression="gzip", track_times=False)  # fmt: skip
            for i, m in enumerate(masks):
                d[i] = m
    with atomic_path(out / "keypoints.hdf5") as tmp:
        with h5py.File(tmp, "w") as f:
            f.create_dataset("keypoints", data=keypoints.reshape(n, 54).astype(np.float64), track_times=False)
