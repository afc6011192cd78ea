"""The common per-frame record that training reads, whatever the source.

One HDF5 file per subject (``results/{dataset}/{subject}/frames.h5``):

- ``images`` (N, S, S, 3) uint8 RGB, cropped and resized to the training size S;
- ``person`` (N, S, S) uint8 alpha (0-255); ``clothing``, ``skin``, ``hair`` (N, S, S) uint8 0/1 when known;
- ``keypoints`` (N, 18, 3) float32 OpenPose-18 (u, v, confidence) in the cropped image;
  ``face_landmarks`` (N, 468, 3) MediaPipe face-mesh points, same format, when asked for;
  ``face_points`` (N, K, 3) face points on the body mesh, same format, with their embedding
  ``face_point_vertices`` (K, 3) int and ``face_point_bary`` (K, 3), when the dataset provides them;
- ``frame_ids`` (N,) int64 indices into the source video; ``split`` (N,) uint8 (0 train, 1 test view, 2 test pose);
- camera: attrs ``camera_model``; pinhole ``K`` (3, 3), ``R``, ``t`` (undistorted: no distortion left);
  orthographic ``ortho_scale`` (N,), ``ortho_trans`` (N, 2);
- attrs ``sources`` (JSON: which step or dataset file produced each array), ``crop`` (u0, v0, size, out),
  ``source_size`` (W, H);
- group ``full``: every frame whole (not cropped), undistorted and area-resized to the capture's scoring
  size (attr ``size`` (W, H): People Snapshot 540×540, a synthetic capture its own): ``images``,
  ``person`` and the part masks as above. Evaluation scores and exports render these frames.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import h5py
import numpy as np
import torch

from delta import DeltaError
from delta.data import SPLITS
from delta.body.face_points import FacePoints
from delta.cameras.models import OrthographicCamera, PinholeCamera

MASKS = ("person", "clothing", "skin", "hair")


class RecordWriter:
    """Append frames one at a time (streamed: a whole video never sits in memory)."""

    def __init__(self, h5: h5py.File, n: int, size: int, masks: tuple[str, ...], face: bool = False,
                 face_points=None, depth: bool = False):  # fmt: skip
        kw = dict(compression="gzip", compression_opts=3, track_times=False)
        self.images = h5.create_dataset("images", (n, size, size, 3), np.uint8, chunks=(1, size, size, 3), **kw)
        self.masks = {m: h5.create_dataset(m, (n, size, size), np.uint8, chunks=(1, size, size), **kw) for m in masks}
        self.keypoints = h5.create_dataset("keypoints", (n, 18, 3), np.float32, track_times=False)
        self.face = h5.create_dataset("face_landmarks", (n, 468, 3), np.float32, track_times=False) if face else None
        # the keypoints' relative depths (metres): a crop moves and scales the image, not them
        self.depth = h5.create_dataset("keypoint_depth", (n, 18), np.float32, fillvalue=np.nan,
                                       track_times=False) if depth else None  # fmt: skip
        self.face_points = None
        if face_points is not None:  # a FacePoints embedding
            self.face_points = h5.create_dataset("face_points", (n, face_points.num_points, 3), np.float32,
                                                 track_times=False)  # fmt: skip
            h5.create_dataset("face_point_vertices", data=face_points.vertex_ids.numpy().astype(np.int64),
                              track_times=False)  # fmt: skip
            h5.create_dataset("face_point_bary", data=face_points.bary.numpy().astype(np.float32), track_times=False)

    def write(self, i: int, image: np.ndarray, masks: dict[str, np.ndarray], keypoints: np.ndarray | None,
              face: np.ndarray | None = None, face_points: np.ndarray | None = None,
              depth: np.ndarray | None = None) -> None:  # fmt: skip
        self.images[i] = image
        for name, dset in self.masks.items():
            dset[i] = masks[name]
        if keypoints is not None:
            self.keypoints[i] = keypoints
        if face is not None and self.face is not None:
            self.face[i] = face
        if face_points is not None and self.face_points is not None:
            self.face_points[i] = face_points
        if depth is not None and self.depth is not None:
            self.depth[i] = depth


class FullFrameWriter:
    """The ``full`` group: frames whole at the scoring size (see the module's docstring)."""

    def __init__(self, h5: h5py.File, n: int, width: int, height: int, masks: tuple[str, ...]):
        g = h5.create_group("full")
        g.attrs["size"] = np.array([width, height])
        kw = dict(compression="gzip", compression_opts=3, track_times=False)
        self.images = g.create_dataset("images", (n, height, width, 3), np.uint8, chunks=(1, height, width, 3), **kw)
        self.masks = {m: g.create_dataset(m, (n, height, width), np.uint8, chunks=(1, height, width), **kw)
                      for m in masks}  # fmt: skip

    def write(self, i: int, image: np.ndarray, masks: dict[str, np.ndarray]) -> None:
        self.images[i] = image
        for name, dset in self.masks.items():
            dset[i] = masks[name]


def write_camera_attrs(h5: h5py.File, camera) -> None:
    if isinstance(camera, PinholeCamera):
        h5.attrs["camera_model"] = "pinhole"
        for k in ("K", "R", "t"):
            h5.create_dataset(k, data=getattr(camera, k).numpy(), track_times=False)
    else:
        h5.attrs["camera_model"] = "orthographic"
        n = h5["frame_ids"].shape[0]
        scale = np.broadcast_to(np.asarray(camera.scale, dtype=np.float64), (n,))
        trans = np.broadcast_to(np.asarray(camera.trans, dtype=np.float64), (n, 2))
        h5.create_dataset("ortho_scale", data=scale, track_times=False)
        h5.create_dataset("ortho_trans", data=trans, track_times=False)


class FrameRecord:
    """Read access to a frame record; arrays are read per frame unless asked for whole."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        if not self.path.is_file():
            raise DeltaError(f"frame record not found: {self.path}")
        self.h5 = h5py.File(self.path, "r")
        for key in ("images", "person", "keypoints", "frame_ids", "split"):
            if key not in self.h5:
                raise DeltaError(f"{self.path}: missing '{key}'; rerun the prepare_frames rule")

    def __len__(self) -> int:
        return int(self.h5["images"].shape[0])

    @property
    def size(self) -> int:
        return int(self.h5["images"].shape[1])

    @property
    def sources(self) -> dict:
        return json.loads(self.h5.attrs["sources"])

    def face_embedding(self) -> FacePoints | None:
        """Where the record's face points lie on the body mesh (None: the record has none)."""
        if "face_points" not in self.h5:
            return None
        return FacePoints(torch.from_numpy(self.h5["face_point_vertices"][:]).long(),
                          torch.from_numpy(self.h5["face_point_bary"][:]).double())  # fmt: skip

    def indices(self, split: str) -> np.ndarray:
        return np.flatnonzero(self.h5["split"][:] == SPLITS.index(split))

    def camera(self, i: int | None = None):
        if self.h5.attrs["camera_model"] == "pinhole":
            t = lambda k: torch.from_numpy(self.h5[k][:])  # noqa: E731
            return PinholeCamera(t("K"), t("R"), t("t"), torch.zeros(5, dtype=torch.float64), self.size, self.size)
        sel = slice(None) if i is None else i
        return OrthographicCamera(torch.from_numpy(np.asarray(self.h5["ortho_scale"][sel])),
                                  torch.from_numpy(np.asarray(self.h5["ortho_trans"][sel])), self.size, self.size)  # fmt: skip

    def close(self) -> None:
        self.h5.close()

    def __enter__(self) -> "FrameRecord":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
