"""Model only what a scene requires: which joints are optimised, which body parts are modelled.

- Frozen joints: named groups (``fingers``, ``toes``, ``eyes``, ``jaw``), joint names, and (``freeze_rest``
  ≥ 0) every joint the init leaves at rest: |pose| ≤ that (rad) in every training frame. The init fit
  of a People Snapshot A-pose never moves the fingers, wrists and feet from rest. A joint that is merely
  constant is not frozen: a wrong but shared init pose must stay correctable. Their pose gradient is
  zeroed, so Adam leaves them exactly at the init.
- Capture extent: ``full`` or ``upper`` (head and shoulders; the lower body is left out of
  backward skinning, the distance field and the NeRF's box); ``auto`` picks ``upper`` when the
  init body's lower-body vertices project outside the image in every sampled training frame.
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from delta import DeltaError
from delta.body.lbs import lbs
from delta.body.model import BodyModel
from delta.body.parts import lower_body_vertices
from delta.cameras.models import OrthographicCamera, PinholeCamera

log = logging.getLogger(__name__)

#: Joint groups by name fragments (Anny and SMPL-X spellings).
JOINT_GROUPS: dict[str, tuple[str, ...]] = {
    "fingers": ("finger", "metacarpal", "thumb", "index", "middle", "ring", "pinky"),
    "toes": ("toe",),
    "eyes": ("eye",),
    "jaw": ("jaw",),
}
#: An ``auto`` capture is ``upper`` when at most this share of lower-body vertices is ever in view.
#: A full-body capture shows nearly all of them (they are counted inside the image, seen or not);
#: a head-and-shoulders one the top of the pelvis at its bottom edge: 1.0–1.1% on the synthetic
#: ``upper`` subject from its init fit, which 1% called ``full``.
MAX_LOWER_IN_VIEW = 0.25


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


def _camera(camera, frame: int, n: int):
    if isinstance(camera, PinholeCamera):
        return camera
    return OrthographicCamera(camera.scale[frame], camera.trans[frame], n, n)


@torch.no_grad()
def detect_capture(body: BodyModel, betas, poses, transl, camera, frames, n: int, max_frames: int = 8) -> str:
    """``upper`` when the lower body stays out of the n×n image in (up to ``max_frames`` of) ``frames``."""
    lower = lower_body_vertices(body)
    if not lower.any():
        return "full"
    frames = np.asarray(frames)[:: max(1, len(frames) // max_frames)]
    seen, total = 0, 0
    for k in frames:
        k = int(k)
        out = lbs(body, betas[None].float(), poses[k : k + 1].float(), transl=transl[k : k + 1].float())
        uv, depth = _camera(camera, k, n).project(out.vertices[0, lower])
        inside = ((uv >= 0) & (uv < n)).all(-1)
        if isinstance(camera, PinholeCamera):
            inside &= depth > 0
        seen, total = seen + int(inside.sum()), total + len(uv)
    share = seen / max(total, 1)
    capture = "upper" if share <= MAX_LOWER_IN_VIEW else "full"
    log.info("lower body in view: %.1f%% of its vertices -> capture '%s'", 100 * share, capture)
    return capture
