"""Motions that drive a trained avatar, read from the files users bring.

Two kinds of npz file are read (plain arrays only: a file holding pickled objects is refused, since
loading it could run code):

* **the body model's own motion** — ``poses`` (F, J, 3) or (F, J·3) axis-angle in the body model's
  joint order and conventions, ``transl`` (F, 3) optional, ``joint_names`` (J,) optional (checked
  against the body model's when present), ``fps`` optional, ``up`` (3,) optional (the world's up; estimated
  from the motion when absent). A subject's fit
  (``results/{dataset}/{subject}/init/params.npz``) is one: driving avatar A with B's fit is motion
  transfer between two captures.
* **AMASS-style SMPL-family archives** — ``poses`` (F, 72 | 156 | 165) in SMPL, SMPL+H or SMPL-X joint
  order, ``trans`` (F, 3), ``mocap_framerate`` (or ``mocap_frame_rate``). They are retargeted onto the
  body model's skeleton (:mod:`delta.applications.retarget`).

Shape vocabulary: F motion frames, J the body model's joints.
"""

from __future__ import annotations

import dataclasses
import os
import zipfile
from pathlib import Path

import numpy as np

from delta import DeltaError

#: Frame rate assumed for a motion file that names none.
DEFAULT_FPS = 30.0
#: Width of an AMASS ``poses`` row -> the SMPL family member whose joint order it follows.
SMPL_FAMILY = {72: "smpl", 156: "smplh", 165: "smplx"}
#: AMASS's world is z-up
AMASS_UP = np.array([0.0, 0.0, 1.0])


@dataclasses.dataclass
class Motion:
    """A motion in the body model's joint order."""

    poses: np.ndarray
    """(F, J, 3) axis-angle per joint, the root's first (float64)."""
    transl: np.ndarray
    """(F, 3) translation of the body (m)."""
    fps: float
    """Frames per second of the motion."""
    source: str
    """What it was read as: "body model" or the SMPL family member retargeted from."""
    up: np.ndarray | None = None
    """(3,) the motion world's up where the file or its convention says it (AMASS: z); None: estimated."""

    @property
    def num_frames(self) -> int:
        return int(self.poses.shape[0])


def load_plain_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The arrays of an npz file, refusing pickled objects; errors name the file."""
    p = Path(path)
    if not p.is_file():
        raise DeltaError(f"{p}: no such motion file")
    with open(p, "rb") as fh:
        head = fh.read(4)
    if head != b"PK\x03\x04":  # every npz is a zip archive
        what = "a pickle" if head[:1] == b"\x80" else "no zip archive"
        raise DeltaError(f"{p}: not a readable npz file ({what}); a motion file is an npz of plain arrays")
    try:
        with np.load(p, allow_pickle=False) as d:
            return {k: d[k] for k in d.files}
    except ValueError as e:
        if "pickle" in str(e).lower() or "object arrays" in str(e).lower():
            raise DeltaError(f"{p}: holds pickled objects; a motion file must hold plain arrays only "
                             "(loading pickles could run code)") from None  # fmt: skip
        raise DeltaError(f"{p}: not a readable npz file ({e})") from None
    except (zipfile.BadZipFile, OSError, EOFError) as e:
        raise DeltaError(f"{p}: not a readable npz file ({e})") from None


def _fps(d: dict[str, np.ndarray], path: Path) -> float:
    for key in ("fps", "mocap_framerate", "mocap_frame_rate"):
        if key in d:
            fps = float(np.asarray(d[key]).reshape(-1)[0])
            if not np.isfinite(fps) or fps <= 0:
                raise DeltaError(f"{path}: '{key}' is {fps}; expected a positive frame rate")
            return fps
    return DEFAULT_FPS


def _finite(name: str, a: np.ndarray, path: Path) -> None:
    bad = ~np.isfinite(a.reshape(len(a), -1)).all(1)
    if bad.any():
        frames = np.flatnonzero(bad)
        raise DeltaError(f"{path}: '{name}' is not finite in {len(frames)} frame(s), the first frame {int(frames[0])}")


def _up(d: dict[str, np.ndarray], path: Path) -> np.ndarray | None:
    """The file's ``up`` (3,) when it has one (a subject's fit writes its capture's), unit length."""
    if "up" not in d:
        return None
    up = np.asarray(d["up"])
    if up.shape != (3,) or not np.issubdtype(up.dtype, np.number) or not np.isfinite(up).all():
        raise DeltaError(f"{path}: 'up' is {up.shape} {up.dtype}; expected three finite numbers, the world's up")
    norm = float(np.linalg.norm(up))
    if norm < 1e-6:
        raise DeltaError(f"{path}: 'up' is the zero vector; expected the world's up direction")
    return up.astype(np.float64) / norm


def _transl(d: dict[str, np.ndarray], frames: int, path: Path) -> np.ndarray:
    key = "transl" if "transl" in d else "trans" if "trans" in d else None
    if key is None:
        return np.zeros((frames, 3))
    t = np.asarray(d[key], dtype=np.float64)
    if t.shape != (frames, 3):
        raise DeltaError(f"{path}: '{key}' has shape {t.shape}; expected ({frames}, 3), one row per pose")
    _finite(key, t, path)
    return t


def read_motion(path: str | os.PathLike, joint_names: list[str], parents: np.ndarray,
                joints_template: np.ndarray) -> Motion:  # fmt: skip
    """The motion in ``path`` in the body model's joint order (``joint_names``, ``parents`` (J,) and
    rest ``joints_template`` (J, 3) describe its skeleton; SMPL-family archives are retargeted onto it)."""
    p = Path(path)
    d = load_plain_npz(p)
    if "poses" not in d:
        raise DeltaError(f"{p}: no 'poses' array; a motion file holds 'poses' (frames × joints × 3 axis-angle, "
                         f"the body model's {len(joint_names)} joints, or AMASS's SMPL-family rows)")  # fmt: skip
    poses = np.asarray(d["poses"])
    if not np.issubdtype(poses.dtype, np.number):
        raise DeltaError(f"{p}: 'poses' holds {poses.dtype} values, not numbers")
    poses = poses.astype(np.float64)
    if poses.ndim == 0 or len(poses) == 0:
        raise DeltaError(f"{p}: 'poses' has no frames")
    J = len(joint_names)
    own = (poses.ndim == 3 and poses.shape[1:] == (J, 3)) or (poses.ndim == 2 and poses.shape[1] == 3 * J)
    if "joint_names" in d:
        names = [str(x) for x in d["joint_names"]]
        if names != list(joint_names):
            missing = sorted(set(joint_names) - set(names))[:5]
            raise DeltaError(f"{p}: its joint_names ({len(names)} joints) are not the body model's ({J}); "
                             f"e.g. missing {missing}: the motion was made for another body model")  # fmt: skip
    if own:
        poses = poses.reshape(len(poses), J, 3)
        _finite("poses", poses, p)
        return Motion(poses, _transl(d, len(poses), p), _fps(d, p), "body model", _up(d, p))
    family = SMPL_FAMILY.get(poses.shape[1]) if poses.ndim == 2 else None
    if family is None:
        raise DeltaError(f"{p}: 'poses' has shape {poses.shape}; expected (frames, {J}, 3) or (frames, {3 * J}) "
                         f"for the body model's joints, or (frames, 72 | 156 | 165) for SMPL, SMPL+H or "
                         f"SMPL-X (AMASS)")  # fmt: skip
    _finite("poses", poses, p)
    from delta.applications.retarget import retarget_smpl_family

    local = retarget_smpl_family(poses.reshape(len(poses), -1, 3), family, joint_names, parents, joints_template)
    return Motion(local, _transl(d, len(poses), p), _fps(d, p), family, AMASS_UP.copy())


def resample(motion: Motion, fps: float, max_frames: int) -> Motion:
    """The motion at ``fps`` (nearest source frame; never faster than the source), at most ``max_frames``
    frames (0: all)."""
    step = max(motion.fps / fps, 1.0) if fps > 0 else 1.0
    idx = np.unique(np.floor(np.arange(0, motion.num_frames, step)).astype(int))
    if max_frames > 0:
        idx = idx[:max_frames]
    return dataclasses.replace(motion, poses=motion.poses[idx], transl=motion.transl[idx], fps=motion.fps / step)
