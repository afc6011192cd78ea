"""Load the user's official SMPL-X model file (licensed; never shipped) into a BodyModel.

Reads ``SMPLX_NEUTRAL.npz`` (or ``.pkl`` through the restricted unpickler),
with the official key names: ``v_template``, ``f``, ``shapedirs``,
``posedirs``, ``J_regressor``, ``kintree_table``, ``weights``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from delta import DeltaError
from delta.body.model import REGION, BodyModel
from delta.safe_pickle import load_pickle

SMPLX_JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck",
    "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "jaw",
    "left_eye_smplhf", "right_eye_smplhf",
    *[f"left_{f}{i}" for f in ("index", "middle", "pinky", "ring", "thumb") for i in (1, 2, 3)],
    *[f"right_{f}{i}" for f in ("index", "middle", "pinky", "ring", "thumb") for i in (1, 2, 3)],
)  # fmt: skip

#: SMPL-X's official shape space has 300 components; later ones are expressions.
SHAPE_SPACE_DIM = 300
_REQUIRED = ("v_template", "f", "shapedirs", "J_regressor", "kintree_table", "weights")
_FACE_JOINTS = ("head", "jaw", "left_eye_smplhf", "right_eye_smplhf")

MISSING_HELP = (
    "SMPL-X is licensed and not shipped. Register at the SMPL-X website, download the model files "
    "and put SMPLX_NEUTRAL.npz at the path set in config/config.yaml under body_model.smplx_path "
    "(default resources/body/smplx/SMPLX_NEUTRAL.npz). The shipped Anny model works without it: "
    "set body_model.name: anny."
)


def _read_arrays(path: Path) -> dict:
    if path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                return {k: data[k] for k in data.files}
        except Exception as exc:
            raise DeltaError(f"{path}: not a readable SMPL-X npz ({exc.__class__.__name__}: {exc})") from exc
    if path.suffix == ".pkl":
        data = load_pickle(path)
        if not isinstance(data, dict):
            raise DeltaError(f"{path}: expected a dict of arrays, found {type(data).__name__}")
        return data
    raise DeltaError(f"{path}: SMPL-X model files end in .npz or .pkl")


def _dense(value) -> np.ndarray:
    return np.asarray(value.todense() if hasattr(value, "todense") else value)


def smplx_regions(weights: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """Region per vertex from its dominant joint: head/jaw/eyes -> face, wrists/fingers -> hands."""
    dominant = weights.argmax(1)
    region = np.full(weights.shape[0], REGION["body"])
    for j, name in enumerate(names):
        if name in _FACE_JOINTS:
            region[dominant == j] = REGION["face"]
        elif name.endswith("wrist") or any(f in name for f in ("index", "middle", "pinky", "ring", "thumb")):
            region[dominant == j] = REGION["hands"]
        elif name.endswith("foot") or name.endswith("ankle"):
            region[dominant == j] = REGION["feet"]
    return region


def smplx_canonical_pose(names: tuple[str, ...]) -> np.ndarray:
    """SCARF's canonical "da-pose": legs spread by π/6 about z, everything else at rest."""
    pose = np.zeros((len(names), 3))
    if "left_hip" in names:
        pose[names.index("left_hip"), 2] = np.pi / 6
        pose[names.index("right_hip"), 2] = -np.pi / 6
    return pose


def load_smplx(path: str | os.PathLike, num_shape: int = 10, num_expression: int = 10) -> BodyModel:
    """Load an official SMPL-X model file; errors say what is missing and where to put it."""
    path = Path(path)
    if not path.is_file():
        raise DeltaError(f"SMPL-X model file not found: {path}. {MISSING_HELP}")
    data = _read_arrays(path)
    missing = [k for k in _REQUIRED if k not in data]
    if missing:
        raise DeltaError(f"{path}: missing SMPL-X keys {missing}; is this the official SMPLX_NEUTRAL file?")
    v_template = _dense(data["v_template"]).astype(np.float64)
    V = v_template.shape[0]
    dirs = _dense(data["shapedirs"]).astype(np.float64)
    if dirs.ndim != 3 or dirs.shape[:2] != (V, 3):
        raise DeltaError(f"{path}: 'shapedirs' has shape {dirs.shape}, expected ({V}, 3, S)")
    split = SHAPE_SPACE_DIM if dirs.shape[-1] > SHAPE_SPACE_DIM else dirs.shape[-1] // 2
    if num_shape > split or num_expression > dirs.shape[-1] - split:
        raise DeltaError(
            f"{path}: holds {split} shape and {dirs.shape[-1] - split} expression components; "
            f"asked for {num_shape} and {num_expression}"
        )
    shapedirs, exprdirs = dirs[..., :num_shape], dirs[..., split : split + num_expression]
    J_reg = _dense(data["J_regressor"]).astype(np.float64)
    parents = _dense(data["kintree_table"])[0].astype(np.int64)
    parents[0] = -1
    J = parents.shape[0]
    names = SMPLX_JOINT_NAMES if J == len(SMPLX_JOINT_NAMES) else tuple(f"joint{j}" for j in range(J))
    weights = _dense(data["weights"]).astype(np.float64)
    posedirs = None
    if "posedirs" in data:
        posedirs = _dense(data["posedirs"]).astype(np.float64)
        if posedirs.ndim == 2:  # some exports store (P, V * 3)
            posedirs = posedirs.reshape(-1, V, 3).transpose(1, 2, 0)
    t = torch.from_numpy
    return BodyModel(
        name="smplx",
        v_template=t(v_template),
        faces=t(_dense(data["f"]).astype(np.int64)),
        shapedirs=t(np.ascontiguousarray(shapedirs)),
        joints_template=t(J_reg @ v_template),
        joints_shapedirs=t(np.einsum("jv,vks->jks", J_reg, shapedirs)),
        parents=t(parents),
        joint_names=list(names),
        weights=t(weights),
        regions=t(smplx_regions(weights, names)),
        canonical_pose=t(smplx_canonical_pose(names)),
        posedirs=None if posedirs is None else t(np.ascontiguousarray(posedirs)),
        exprdirs=t(np.ascontiguousarray(exprdirs)) if num_expression else None,
        joints_exprdirs=t(np.einsum("jv,vks->jks", J_reg, exprdirs)) if num_expression else None,
    ).validate(str(path))
