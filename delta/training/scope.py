"""Model only what a scene requires: which joints are optimised, which body parts are modelled.

- Frozen joints: named groups (``fingers``, ``toes``, ``eyes``, ``jaw``), joint names, and (``freeze_rest``
  ≥ 0) every joint the init leaves at rest: |pose| ≤ that (rad) in every training frame. The init fit
  of a People Snapshot A-pose never moves the fingers, wrists and feet from rest. A joint that is merely
  constant is not frozen: a wrong but shared init pose must stay correctable. Their pose gradient is
  zeroed, so Adam leaves them exactly at the init.
- Capture extent: ``full`` or ``upper`` (head and shoulders; the lower body is left out of
  backward skinning, the distance field and the NeRF's box); ``auto`` follows the scene analysis
  (:func:`delta.scene.framing.detect_capture`).
"""

from __future__ import annotations

import logging

import torch

from delta import DeltaError
from delta.body.model import BodyModel

log = logging.getLogger(__name__)

#: Joint groups by name fragments (Anny and SMPL-X spellings).
JOINT_GROUPS: dict[str, tuple[str, ...]] = {
    "fingers": ("finger", "metacarpal", "thumb", "index", "middle", "ring", "pinky"),
    "toes": ("toe",),
    "eyes": ("eye",),
    "jaw": ("jaw",),
}


def frozen_joints(body: BodyModel, freeze: list, rest_eps: float, poses: torch.Tensor) -> list[int]:
    """Joint indices not optimised: named groups or joints in ``freeze``, plus (``rest_eps`` ≥ 0)
    joints with |pose| ≤ ``rest_eps`` on every axis of every frame of ``poses`` (N, J, 3). Never the root."""
    names = [n.lower() for n in body.joint_names]
    out = set()
    for item in freeze:
        key = str(item).lower()
        if key in JOINT_GROUPS:
            out |= {j for j, n in enumerate(names) if any(f in n for f in JOINT_GROUPS[key])}
        elif key in names:
            out.add(names.index(key))
        else:
            raise DeltaError(f"training.freeze: '{item}' is neither a group {sorted(JOINT_GROUPS)} nor a joint")
    if rest_eps >= 0 and len(poses):
        out |= set(torch.nonzero(poses.abs().amax(dim=(0, 2)) <= rest_eps).squeeze(1).tolist())
    out.discard(0)
    return sorted(out)
