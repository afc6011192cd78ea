"""Retargeting SMPL-family poses (AMASS archives) onto the body model's skeleton.

Both skeletons pose joints in world-aligned axes (y up, the subject facing +z, its left on +x) about
their rest positions, so a joint both have means the same rotation in both — except where their rest
poses differ. SMPL's rest is a T-pose (arms along ±x, legs and spine vertical); Anny's is an A-pose
(arms ~45° down, forearms forward). The retargeting therefore matches *posed bone directions*, not
local rotations:

* each mapped joint j of the body model takes the source joint s's global rotation G_s, corrected by
  the rest difference: G_j = G_s C_j, where C_j is the smallest rotation taking the body model's rest
  bone direction (j towards the joint ``JOINT_MAP`` names as the bone's end) onto the source's T-pose
  direction. The posed bone then points where the source's does: G_j d_j = G_s d_T;
* joints the map does not name (Anny's extra spine and twist joints, the fingers) keep their rest
  orientation relative to their parent (G_j = G_parent); the source's fingers and toes are not used;
* local rotations follow from the globals: R_j = G_parent(j)ᵀ G_j.

The twist about a bone is the source's (C_j is the smallest rotation, with no twist of its own).
A body model with SMPL-X's joint names (the user's SMPL-X) takes the shared joints' rotations as they
are: both rests are the same T-pose.

Shape vocabulary: F frames, J the body model's joints, S the source's joints.
"""

from __future__ import annotations

import numpy as np
import torch

from delta import DeltaError
from delta.body.lbs import batch_rodrigues
from delta.body.rotations import matrix_to_axis_angle

#: SMPL's 22 body joints, shared by SMPL, SMPL+H and SMPL-X, and their parents.
SMPL_BODY = ("pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
             "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
             "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist")  # fmt: skip
SMPL_BODY_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)
_HANDS = tuple(f"{side}_{f}{i}" for side in ("left", "right") for f in ("index", "middle", "pinky", "ring", "thumb")
               for i in (1, 2, 3))  # fmt: skip

#: Joint order of each family's ``poses`` rows (AMASS).
FAMILY_JOINTS: dict[str, tuple[str, ...]] = {
    "smpl": SMPL_BODY + ("left_hand", "right_hand"),
    "smplh": SMPL_BODY + _HANDS,
    "smplx": SMPL_BODY + ("jaw", "left_eye_smplhf", "right_eye_smplhf") + _HANDS,
}

_X, _Y = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)
_NX, _NY = (-1.0, 0.0, 0.0), (0.0, -1.0, 0.0)

#: Anny joint -> (SMPL joint, the Anny joint that ends the bone, the bone's direction in SMPL's T-pose).
#: No end: the rest orientations agree (root, spine, neck, head, feet, eyes). SMPL's three spine joints sit
#: at ~0.12, 0.25 and 0.30 m above the pelvis; Anny's spine03, spine02 and spine01 at ~0.13, 0.20 and 0.32 m.
JOINT_MAP: dict[str, tuple[str, str | None, tuple[float, float, float] | None]] = {
    "root": ("pelvis", None, None),
    "upperleg01.L": ("left_hip", "lowerleg01.L", _NY),
    "upperleg01.R": ("right_hip", "lowerleg01.R", _NY),
    "lowerleg01.L": ("left_knee", "foot.L", _NY),
    "lowerleg01.R": ("right_knee", "foot.R", _NY),
    "foot.L": ("left_ankle", None, None),
    "foot.R": ("right_ankle", None, None),
    "spine03": ("spine1", None, None),
    "spine02": ("spine2", None, None),
    "spine01": ("spine3", None, None),
    "neck01": ("neck", None, None),
    "head": ("head", None, None),
    "clavicle.L": ("left_collar", "upperarm01.L", _X),
    "clavicle.R": ("right_collar", "upperarm01.R", _NX),
    "upperarm01.L": ("left_shoulder", "lowerarm01.L", _X),
    "upperarm01.R": ("right_shoulder", "lowerarm01.R", _NX),
    "lowerarm01.L": ("left_elbow", "wrist.L", _X),
    "lowerarm01.R": ("right_elbow", "wrist.R", _NX),
    "wrist.L": ("left_wrist", "finger3-1.L", _X),
    "wrist.R": ("right_wrist", "finger3-1.R", _NX),
    "eye.L": ("left_eye_smplhf", None, None),
    "eye.R": ("right_eye_smplhf", None, None),
}

_EYE_PARENT = {"left_eye_smplhf": "head", "right_eye_smplhf": "head", "jaw": "head"}


def _parents(names: tuple[str, ...]) -> list[int]:
    """Parents of the source joints that retargeting uses (-2: not used)."""
    out = []
    for j, n in enumerate(names):
        if j < len(SMPL_BODY):
            out.append(SMPL_BODY_PARENTS[j])
        else:
            out.append(names.index(_EYE_PARENT[n]) if n in _EYE_PARENT else -2)
    return out


def global_rotations(local: torch.Tensor, parents: list[int]) -> torch.Tensor:
    """(F, S, 3, 3) world rotations from local ones (parents[j] < j; -2: left as the local rotation)."""
    glob = [None] * local.shape[1]
    for j, p in enumerate(parents):
        glob[j] = local[:, j] if p < 0 else glob[p] @ local[:, j]
    return torch.stack(glob, 1)


def smallest_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest rotation taking unit direction ``a`` onto unit direction ``b``."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis, c = np.cross(a, b), float(np.clip(a @ b, -1.0, 1.0))
    s = np.linalg.norm(axis)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        raise DeltaError("retargeting: a rest bone points opposite the source's (no smallest rotation)")
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * K @ K


def retarget_smpl_family(poses: np.ndarray, family: str, joint_names: list[str], parents: np.ndarray,
                         joints_template: np.ndarray) -> np.ndarray:  # fmt: skip
    """(F, J, 3) axis-angle poses of the body model from (F, S, 3) poses of an SMPL-family ``family``."""
    src_names = FAMILY_JOINTS[family]
    if poses.shape[1] != len(src_names):
        raise DeltaError(f"{family} poses have {poses.shape[1]} joints; expected {len(src_names)}")
    F, J = len(poses), len(joint_names)
    out = np.zeros((F, J, 3))
    if "pelvis" in joint_names:  # SMPL-X's joint names: the same T-pose rest, the rotations carry over
        for s, name in enumerate(src_names):
            if name in joint_names:
                out[:, joint_names.index(name)] = poses[:, s]
        return out
    missing = [n for n in JOINT_MAP if n not in joint_names and n not in ("eye.L", "eye.R")]
    if missing:
        raise DeltaError(f"retargeting {family} poses: the body model has no joint(s) {missing}; "
                         "retargeting knows SMPL-X's and Anny's skeletons")  # fmt: skip
    local_src = batch_rodrigues(torch.from_numpy(poses).reshape(-1, 3)).reshape(F, -1, 3, 3)
    G_src = global_rotations(local_src, _parents(src_names))
    rest = np.asarray(joints_template, dtype=np.float64)
    G: list[torch.Tensor] = []
    eye = torch.eye(3, dtype=torch.float64).expand(F, 3, 3)
    for j, name in enumerate(joint_names):
        p = int(parents[j])
        entry = JOINT_MAP.get(name)
        if entry is None or entry[0] not in src_names:
            G.append(G[p] if p >= 0 else eye)
            continue
        src, end, t_dir = entry
        C = np.eye(3)
        if end is not None and end in joint_names:
            C = smallest_rotation(rest[joint_names.index(end)] - rest[j], np.asarray(t_dir))
        G.append(G_src[:, src_names.index(src)] @ torch.from_numpy(C))
    Gt = torch.stack(G, 1)
    par = torch.as_tensor(np.asarray(parents), dtype=torch.long)
    local = Gt.clone()
    nonroot = par >= 0
    local[:, nonroot] = Gt[:, par[nonroot]].transpose(-1, -2) @ Gt[:, nonroot]
    return matrix_to_axis_angle(local.reshape(-1, 3, 3)).reshape(F, J, 3).numpy()
