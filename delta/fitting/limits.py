"""Joint-angle limits the project defines for its body models (no learned pose prior ships).

Poses are axis-angle in world-aligned joint axes (y up, the body faces +z at zero
rotation, left = +x). Near the rest pose each component is close to a rotation about
that world axis, so a box [lo, hi] per component is a serviceable limit: knees bend
about +x only, elbows about ∓y (left/right) only, the spine and neck move a little,
twist and helper bones hardly at all. Joints without a rule are unlimited (±π); the root
(the global orientation) is not limited at all: a subject turning round has headings
beyond π, and an axis-angle written past π is the same rotation.
Ranges are in radians; the penalty is quadratic beyond them (terms.joint_limit_prior).
"""

from __future__ import annotations

import math
import re

import torch

from delta.body.model import BodyModel

_FREE = (-math.pi, math.pi)

#: (name pattern, (lo_x, hi_x), (lo_y, hi_y), (lo_z, hi_z)); the first pattern a joint matches applies.
_RULES = {
    "anny": [
        (r"lowerleg01\.[LR]$", (-0.05, 2.6), (-0.35, 0.35), (-0.35, 0.35)),  # knees (some tibial twist)
        # elbows (rest: forearm forward-down-out): -x lifts the forearm, +y (left) / -y (right) hyperextends it
        (r"lowerarm01\.L$", (-2.0, 0.6), (-2.6, 0.05), (-0.3, 0.3)),
        (r"lowerarm01\.R$", (-2.0, 0.6), (-0.05, 2.6), (-0.3, 0.3)),
        (r"spine0[1-5]$", (-0.4, 0.6), (-0.4, 0.4), (-0.3, 0.3)),
        (r"neck0[1-3]$|head$", (-0.5, 0.6), (-0.7, 0.7), (-0.4, 0.4)),
        (r"(upper|lower)(leg|arm)02\.|foot\.", (-0.3, 0.3), (-0.3, 0.3), (-0.3, 0.3)),  # helper bones, ankles
        (r"pelvis\.|clavicle\.|shoulder01\.|eye\.", (-0.2, 0.2), (-0.2, 0.2), (-0.2, 0.2)),
        (r"finger|metacarpal|toe", (-0.5, 0.5), (-0.5, 0.5), (-0.5, 0.5)),
    ],
    "smplx": [
        (r"(left|right)_knee$", (-0.05, 2.6), (-0.35, 0.35), (-0.35, 0.35)),
        (r"left_elbow$", (-0.6, 0.6), (-2.6, 0.05), (-0.3, 0.3)),  # T-pose arm along +x: flexion about -y
        (r"right_elbow$", (-0.6, 0.6), (-0.05, 2.6), (-0.3, 0.3)),
        (r"spine[1-3]$", (-0.4, 0.6), (-0.4, 0.4), (-0.3, 0.3)),
        (r"neck$|head$", (-0.5, 0.6), (-0.7, 0.7), (-0.4, 0.4)),
        (r"(left|right)_(ankle|foot|wrist)$", (-0.6, 0.6), (-0.6, 0.6), (-0.6, 0.6)),
        (r"(left|right)_collar$|jaw$|eye_smplhf$", (-0.2, 0.2), (-0.2, 0.2), (-0.2, 0.2)),
        (r"index|middle|pinky|ring|thumb", (-0.5, 0.5), (-0.5, 0.5), (-0.5, 0.5)),
    ],
}


#: (group, name pattern, axis-angle direction) of the joints that swing a limb forward of the body.
_FORWARD = {
    "anny": [
        ("arms", r"upperarm01\.[LR]$", (-1.0, 0.0, 0.0)),  # -x swings a hanging limb forward (+z)
        ("legs", r"upperleg01\.[LR]$", (-1.0, 0.0, 0.0)),
    ],  # fmt: skip
    "smplx": [
        ("arms", r"left_shoulder$", (0.0, -1.0, 0.0)),
        ("arms", r"right_shoulder$", (0.0, 1.0, 0.0)),
        ("legs", r"(left|right)_hip$", (-1.0, 0.0, 0.0)),
    ],  # fmt: skip
}


def forward_directions(model: BodyModel) -> dict[str, torch.Tensor]:
    """Per limb group ("arms", "legs"), (J, 3) unit axis-angle directions that swing its shoulders or hips
    forward (zero for the other joints); empty for a body model without rules. The SMPL-X rules assume its
    T-pose (arms along ±x)."""
    out: dict[str, torch.Tensor] = {}
    for group, pattern, direction in _FORWARD.get(model.name.split("_sub")[0], []):
        d = out.setdefault(group, torch.zeros(model.num_joints, 3, dtype=torch.float64))
        for j, name in enumerate(model.joint_names):
            if j > 0 and re.search(pattern, name):
                d[j] = torch.tensor(direction, dtype=torch.float64)
    return out


def joint_limits(model: BodyModel) -> tuple[torch.Tensor, torch.Tensor]:
    """(J, 3) lower and upper axis-angle limits of ``model``'s joints (the root is free)."""
    rules = _RULES.get(model.name.split("_sub")[0], [])
    lo = torch.full((model.num_joints, 3), _FREE[0], dtype=torch.float64)
    hi = torch.full((model.num_joints, 3), _FREE[1], dtype=torch.float64)
    lo[0], hi[0] = -math.inf, math.inf
    for j, name in enumerate(model.joint_names):
        if j == 0:
            continue
        for pattern, *ranges in rules:
            if re.search(pattern, name):
                lo[j] = torch.tensor([r[0] for r in ranges], dtype=torch.float64)
                hi[j] = torch.tensor([r[1] for r in ranges], dtype=torch.float64)
                break
    return lo, hi
