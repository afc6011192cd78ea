"""Where the fit starts when nothing is known: facing the camera, placed and sized from the torso keypoints.

Shapes: F frames, K = 18 OpenPose keypoints.
"""

from __future__ import annotations

import numpy as np
import torch
from kornia.geometry.conversions import rotation_matrix_to_axis_angle

from delta.body.keypoints import OPENPOSE18
from delta.cameras.models import PinholeCamera

TORSO = tuple(OPENPOSE18.index(n) for n in ("neck", "right_shoulder", "left_shoulder", "right_hip", "left_hip"))
FACE = tuple(OPENPOSE18.index(n) for n in ("nose", "right_eye", "left_eye", "right_ear", "left_ear"))


def facing_orientation(camera) -> torch.Tensor:
    """Axis-angle of a body standing upright and facing the camera."""
    if isinstance(camera, PinholeCamera):
        flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
        return rotation_matrix_to_axis_angle((camera.R.T.to(torch.float64) @ flip)[None])[0]
    return torch.zeros(3, dtype=torch.float64)


def interpolate(values: torch.Tensor, flagged: torch.Tensor) -> torch.Tensor:
    """Replace flagged frames of (F, ...) values by linear interpolation between good frames (held at the ends)."""
    good = torch.nonzero(~flagged).squeeze(1).numpy()
    if len(good) == 0 or not flagged.any():
        return values
    flat = values.reshape(values.shape[0], -1).detach().numpy().copy()
    frames = np.arange(len(flat))
    for c in range(flat.shape[1]):
        flat[:, c] = np.interp(frames, good, flat[good, c])
    return torch.from_numpy(flat).reshape(values.shape).to(values.dtype)


def _torso_extent(kp: torch.Tensor, detected: torch.Tensor):
    """Model torso height (F,), detected torso height in pixels (F,), detected torso centre (F, 2), usable (F,)."""
    torso = list(TORSO)
    model_size = (kp[:, torso, 1].amax(1) - kp[:, torso, 1].amin(1)).clamp_min(1e-3)
    conf = detected[:, torso, 2] > 0
    v = detected[:, torso, 1]
    pix_size = torch.where(conf, v, -1e9).amax(1) - torch.where(conf, v, 1e9).amin(1)
    usable = conf.sum(1) >= 2
    pix_size = torch.where(usable, pix_size, 1.0).clamp_min(1.0)
    centre = (detected[:, torso, :2] * conf[..., None]).sum(1) / conf.sum(1, keepdim=True).clamp_min(1)
    return model_size, pix_size, centre, usable


def init_translation(kp: torch.Tensor, detected: torch.Tensor, camera: PinholeCamera) -> torch.Tensor:
    """(F, 3) translation putting the (F, K, 3) untranslated keypoints' torso on the camera ray through the
    detected torso centre, at the depth where it has the detected size; frames without two torso
    detections take their neighbours' values (or, with none anywhere, 3 m ahead of the camera)."""
    model_size, pix_size, centre_px, usable = _torso_extent(kp, detected)
    K = camera.K.to(torch.float64)
    depth = K[1, 1] * model_size / pix_size
    centre_px = torch.where(usable[:, None], centre_px, K[:2, 2])
    depth = torch.where(usable, depth, torch.full_like(depth, 3.0))
    ray = torch.cat([(centre_px - K[:2, 2]) / torch.diag(K)[:2], torch.ones_like(depth[:, None])], 1)
    target = (ray * depth[:, None] - camera.t.to(torch.float64)) @ camera.R.to(torch.float64)  # R^T (x - t)
    return interpolate(target - kp[:, list(TORSO)].mean(1), ~usable)


def init_ortho_scale(kp: torch.Tensor, detected: torch.Tensor, height: int) -> torch.Tensor:
    """(F,) scaled-orthographic scale giving the torso its detected height (neighbours' value where unusable)."""
    model_size, pix_size, _, usable = _torso_extent(kp, detected)
    scale = 2 * pix_size / height / model_size
    return interpolate(torch.where(usable, scale, torch.ones_like(scale)), ~usable)
