"""Where the fit starts when nothing is known: facing the camera, placed and sized from the torso keypoints.

Shapes: F frames, K = 18 OpenPose keypoints.
"""

from __future__ import annotations

import numpy as np
import torch

from delta.body.keypoints import OPENPOSE18
from delta.body.rotations import matrix_to_axis_angle
from delta.cameras.models import PinholeCamera

TORSO = tuple(OPENPOSE18.index(n) for n in ("neck", "right_shoulder", "left_shoulder", "right_hip", "left_hip"))
FACE = tuple(OPENPOSE18.index(n) for n in ("nose", "right_eye", "left_eye", "right_ear", "left_ear"))


def facing_orientation(camera) -> torch.Tensor:
    """Axis-angle of a body standing upright and facing the camera."""
    if isinstance(camera, PinholeCamera):
        flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
        return matrix_to_axis_angle((camera.R.T.to(torch.float64) @ flip)[None])[0]
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
    """Model size (F,), detected size in pixels (F,), detected centre (F, 2), the model point at that centre
    (F, 3) and usable (F,).

    With both hips detected: the torso's height and centre. Without them (a head-and-shoulders capture, whose
    torso runs off the image) the sizes are the box diagonals of the torso and face keypoints detected, the
    model's taken over the same keypoints, and the centres theirs: the torso's model height against the few
    pixels from neck to shoulders would put the body several times too far away."""
    torso, upper = list(TORSO), list(TORSO) + list(FACE)
    hips = list(TORSO[-2:])
    full = (detected[:, hips, 2] > 0).all(1)
    is_torso = torch.arange(len(upper)) < len(torso)
    conf = (detected[:, upper, 2] > 0) & (is_torso[None] | ~full[:, None])  # the face counts without the hips
    height = (kp[:, torso, 1].amax(1) - kp[:, torso, 1].amin(1)).clamp_min(1e-3)
    v = detected[:, torso, 1]
    c = conf[:, : len(torso)]
    pix_height = torch.where(c, v, -1e9).amax(1) - torch.where(c, v, 1e9).amin(1)

    def diagonal(points, mask):
        lo = torch.where(mask[..., None], points, torch.full_like(points, 1e9)).amin(1)
        hi = torch.where(mask[..., None], points, torch.full_like(points, -1e9)).amax(1)
        return (hi - lo).norm(dim=-1)

    model_size = torch.where(full, height, diagonal(kp[:, upper, :2], conf).clamp_min(1e-3))
    pix_size = torch.where(full, pix_height, diagonal(detected[:, upper, :2], conf))
    usable = conf.sum(1) >= 2
    pix_size = torch.where(usable, pix_size, 1.0).clamp_min(1.0)
    n = conf.sum(1, keepdim=True).clamp_min(1)
    centre = (detected[:, upper, :2] * conf[..., None]).sum(1) / n
    model_centre = torch.where(full[:, None], kp[:, torso].mean(1), (kp[:, upper] * conf[..., None]).sum(1) / n)
    return model_size, pix_size, centre, model_centre, usable


def init_translation(kp: torch.Tensor, detected: torch.Tensor, camera: PinholeCamera) -> torch.Tensor:
    """(F, 3) translation putting the (F, K, 3) untranslated keypoints' torso on the camera ray through the
    detected torso centre, at the depth where it has the detected size; frames without two torso
    detections take their neighbours' values (or, with none anywhere, 3 m ahead of the camera)."""
    model_size, pix_size, centre_px, model_centre, usable = _torso_extent(kp, detected)
    K = camera.K.to(torch.float64)
    depth = K[1, 1] * model_size / pix_size
    centre_px = torch.where(usable[:, None], centre_px, K[:2, 2])
    depth = torch.where(usable, depth, torch.full_like(depth, 3.0))
    ray = torch.cat([(centre_px - K[:2, 2]) / torch.diag(K)[:2], torch.ones_like(depth[:, None])], 1)
    target = (ray * depth[:, None] - camera.t.to(torch.float64)) @ camera.R.to(torch.float64)  # R^T (x - t)
    return interpolate(target - model_centre, ~usable)


def init_ortho_scale(kp: torch.Tensor, detected: torch.Tensor, height: int) -> torch.Tensor:
    """(F,) scaled-orthographic scale giving the torso its detected height (neighbours' value where unusable)."""
    model_size, pix_size, _, _, usable = _torso_extent(kp, detected)
    scale = 2 * pix_size / height / model_size
    return interpolate(torch.where(usable, scale, torch.ones_like(scale)), ~usable)


#: a frame's face needs this many confident points for its own head pose (fewer: its neighbours')
MIN_FACE_POINTS = 6


def face_start(model, points, detected: torch.Tensor, camera: PinholeCamera, conf: float = 0.5):
    """Where a close-up's fit starts: the mean-shaped body at rest, turned and placed per frame so that its
    face points (a :class:`delta.body.face_points.FacePoints`) reproject onto the (F, K, 3) detections —
    the perspective-n-point solution (EPnP, then refined by Levenberg-Marquardt). The head's turn is
    given to the whole body, which the fit then undoes where the shoulders say otherwise. Frames with
    fewer than ``MIN_FACE_POINTS`` points take their neighbours' values; None when no frame has them.
    Returns a :class:`delta.fitting.fit.FitStart`."""
    import cv2

    from delta.body.lbs import lbs
    from delta.fitting.fit import FitStart

    dtype = torch.float64
    betas = torch.zeros(model.num_shape, dtype=dtype)
    with torch.no_grad():
        rest = lbs(model, betas[None], torch.zeros(1, model.num_joints, 3, dtype=dtype))
    X = points(rest.vertices)[0].numpy()
    j0 = rest.joints[0, 0].numpy()
    K = camera.K.to(dtype).numpy()
    Rc, tc = camera.R.to(dtype).numpy(), camera.t.to(dtype).numpy()
    F = detected.shape[0]
    root, transl = np.zeros((F, 3)), np.zeros((F, 3))
    missing = torch.ones(F, dtype=torch.bool)
    for f in range(F):
        seen = detected[f, :, 2].numpy() >= conf
        if seen.sum() < MIN_FACE_POINTS:
            continue
        obj, img = X[seen].astype(np.float64), detected[f, seen, :2].numpy().astype(np.float64)
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_EPNP)
        if not ok:
            continue
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, rvec, tvec, useExtrinsicGuess=True,
                                      flags=cv2.SOLVEPNP_ITERATIVE)  # fmt: skip
        if not ok or tvec[2, 0] <= 0:
            continue
        Rp = cv2.Rodrigues(rvec)[0]
        # camera(R_root (X - j0) + j0 + transl) = Rp X + tp
        R_root = Rc.T @ Rp
        root[f] = cv2.Rodrigues(R_root)[0][:, 0]
        transl[f] = Rc.T @ (tvec[:, 0] - tc + Rp @ j0) - j0
        missing[f] = False
    if missing.all():
        return None
    pose = torch.zeros(F, model.num_joints, 3, dtype=dtype)
    pose[:, 0] = interpolate(torch.from_numpy(root), missing)
    return FitStart(betas, pose, interpolate(torch.from_numpy(transl), missing))
