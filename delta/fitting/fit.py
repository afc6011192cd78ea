"""Staged, batched fitting of shared shape, per-frame pose and camera to 2D keypoints.

Stage 1 fits the global orientation and translation (pinhole) or the per-frame
scaled-orthographic camera to the torso keypoints; stage 2 adds the body pose
with its priors; stage 3 adds the shared shape and temporal smoothness. Frames
with too few confident keypoints are flagged and take their neighbours'
parameters. All frames are optimised together (no per-frame Python loop).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from delta.body.keypoints import OPENPOSE18, KeypointMap
from delta.body.lbs import batch_rodrigues, rigid_transforms, skin
from delta.body.model import BodyModel
from delta.cameras.models import OrthographicCamera, PinholeCamera
from delta.fitting import terms

TORSO = tuple(OPENPOSE18.index(n) for n in ("neck", "right_shoulder", "left_shoulder", "right_hip", "left_hip"))


@dataclasses.dataclass
class FitConfig:
    iterations: tuple[int, int, int] = (150, 200, 150)
    lr: float = 0.03
    sigma_px: float = 30.0
    """Robust-penalty scale of the keypoint residuals (pixels)."""
    pose_weight: float = 2e-3
    shape_weight: float = 1e-3
    bend_weight: float = 1.0
    smooth_weight: float = 0.05
    min_keypoints: int = 4
    conf_threshold: float = 0.3


@dataclasses.dataclass
class FitResult:
    betas: torch.Tensor
    """(S,) shared shape."""
    pose: torch.Tensor
    """(F, J, 3) axis-angle pose (joint 0 is the global orientation)."""
    transl: torch.Tensor
    """(F, 3) body translation (zero for orthographic cameras)."""
    camera: object
    """The fitted camera: the given pinhole, or an OrthographicCamera with (F,) scale and (F, 2) translation."""
    flagged: torch.Tensor
    """(F,) bool: too few confident keypoints; parameters interpolated from neighbours."""
    residual_px: torch.Tensor
    """(F,) mean reprojection error over confident keypoints (nan when flagged)."""


class KeypointModel:
    """3D keypoints of a body model, skinning only the few vertices the keypoint map reads."""

    def __init__(self, model: BodyModel, kp_map: KeypointMap):
        self.model = model
        self.vids = torch.nonzero(kp_map.vertex_weights.abs().sum(0) > 0).squeeze(1)
        self.vw = kp_map.vertex_weights[:, self.vids].to(model.v_template.dtype)
        self.jw = kp_map.joint_weights.to(model.v_template.dtype)

    def __call__(self, betas: torch.Tensor, pose: torch.Tensor, transl: torch.Tensor) -> torch.Tensor:
        """(S,), (F, J, 3), (F, 3) -> (F, K, 3) keypoints."""
        m, F, S = self.model, pose.shape[0], betas.shape[0]
        joints = m.joints_template + torch.einsum("s,jcs->jc", betas, m.joints_shapedirs[..., :S])
        verts = m.v_template[self.vids] + torch.einsum("s,vcs->vc", betas, m.shapedirs[self.vids][..., :S])
        posed_joints, A = rigid_transforms(batch_rodrigues(pose), joints.expand(F, -1, -1), m.parents)
        posed_verts, _ = skin(verts.expand(F, -1, -1), m.weights[self.vids], A)
        kp = torch.einsum("kj,fjc->fkc", self.jw, posed_joints) + torch.einsum("kv,fvc->fkc", self.vw, posed_verts)
        return kp + transl[:, None]


def facing_orientation(camera) -> torch.Tensor:
    """Axis-angle of a body standing upright and facing the camera."""
    if isinstance(camera, PinholeCamera):
        flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
        R = camera.R.T @ flip
        from kornia.geometry.conversions import rotation_matrix_to_axis_angle

        return rotation_matrix_to_axis_angle(R[None])[0]
    return torch.zeros(3, dtype=torch.float64)


def _interpolate(values: torch.Tensor, flagged: torch.Tensor) -> torch.Tensor:
    """Replace flagged frames of (F, ...) values by linear interpolation between good frames."""
    good = torch.nonzero(~flagged).squeeze(1).numpy()
    if len(good) == 0 or not flagged.any():
        return values
    flat = values.reshape(values.shape[0], -1).detach().numpy().copy()
    frames = np.arange(len(flat))
    for c in range(flat.shape[1]):
        flat[:, c] = np.interp(frames, good, flat[good, c])
    return torch.from_numpy(flat).reshape(values.shape).to(values.dtype)


def _init_translation(kpm, betas, pose, detected, camera) -> torch.Tensor:
    """Place the body on the camera axis at the depth where its torso has the detected size."""
    kp = kpm(betas, pose, torch.zeros(pose.shape[0], 3, dtype=pose.dtype)).detach()
    torso = list(TORSO)
    model_size = (kp[:, torso].amax(1) - kp[:, torso].amin(1))[:, 1].clamp_min(1e-3)
    conf = detected[:, torso, 2] > 0
    pix = detected[:, torso, :2]
    big, small = torch.where(conf[..., None], pix, -1e9).amax(1), torch.where(conf[..., None], pix, 1e9).amin(1)
    pix_size = (big - small)[:, 1].clamp_min(1.0)
    depth = camera.K[1, 1] * model_size / pix_size
    centre_px = torch.where(conf[..., None], pix, 0).sum(1) / conf.sum(1, keepdim=True).clamp_min(1)
    ray = torch.cat([(centre_px - camera.K[:2, 2]) / torch.diag(camera.K)[:2], torch.ones_like(depth[:, None])], 1)
    target_cam = ray * depth[:, None]
    target = (target_cam - camera.t) @ camera.R  # R^T (x - t) for row vectors
    return target - kp[:, torso].mean(1)


def fit(model: BodyModel, kp_map: KeypointMap, detected: torch.Tensor, camera, cfg: FitConfig = FitConfig(),
        pose_weights: torch.Tensor | None = None, knees: list[int] = ()) -> FitResult:  # fmt: skip
    """Fit β, θ_f and the camera to (F, 18, 3) keypoint detections (see the module docstring).

    ``camera`` is a PinholeCamera (static; the body moves) or an OrthographicCamera template
    whose per-frame scale and translation are fitted.
    """
    model = model.to(dtype=torch.float64)
    detected = detected.to(torch.float64).clone()
    detected[..., 2] = torch.where(detected[..., 2] >= cfg.conf_threshold, detected[..., 2], 0.0)
    F, J = detected.shape[0], model.num_joints
    flagged = (detected[..., 2] > 0).sum(-1) < cfg.min_keypoints
    detected[flagged, :, 2] = 0.0
    kpm = KeypointModel(model, kp_map)
    pose_weights = torch.ones(J, dtype=torch.float64) if pose_weights is None else pose_weights
    betas = torch.zeros(model.num_shape, dtype=torch.float64, requires_grad=True)
    pose = torch.zeros(F, J, 3, dtype=torch.float64)
    pose[:, 0] = facing_orientation(camera)
    pinhole = isinstance(camera, PinholeCamera)
    if pinhole:
        transl = _init_translation(kpm, betas.detach(), pose, detected, camera).requires_grad_()
        cam_params: list[torch.Tensor] = []
    else:
        transl = torch.zeros(F, 3, dtype=torch.float64)
        kp0 = kpm(betas.detach(), pose, transl).detach()
        extent = (kp0[:, list(TORSO), 1].amax(1) - kp0[:, list(TORSO), 1].amin(1)).clamp_min(1e-3)
        conf = detected[:, list(TORSO), 2] > 0
        v = detected[:, list(TORSO), 1]
        pix = (torch.where(conf, v, -1e9).amax(1) - torch.where(conf, v, 1e9).amin(1)).clamp_min(1.0)
        log_scale = torch.log(2 * pix / camera.height / extent).requires_grad_()
        trans = torch.zeros(F, 2, dtype=torch.float64, requires_grad=True)
        cam_params = [log_scale, trans]
    pose.requires_grad_()

    def project(kp3d):
        if pinhole:
            return camera.project(kp3d)[0]
        cam = OrthographicCamera(cam_params[0].exp(), cam_params[1], camera.width, camera.height)
        return cam.project(kp3d)[0]

    def loss(stage: int) -> torch.Tensor:
        kp2d = project(kpm(betas, pose, transl))
        det = detected if stage > 0 else detected * _torso_mask(detected)
        total = terms.keypoint_term(kp2d, det, cfg.sigma_px).sum()
        if stage > 0:
            total = total + cfg.pose_weight * terms.pose_prior(pose[:, 1:], pose_weights[1:]).sum() * cfg.sigma_px
            total = total + cfg.bend_weight * terms.bend_prior(pose, list(knees), 0, 1.0).sum()
        if stage > 1:
            total = total + cfg.shape_weight * terms.shape_prior(betas) * F * cfg.sigma_px
            total = total + cfg.smooth_weight * cfg.sigma_px * (terms.smoothness(pose) + terms.smoothness(transl))
        return total

    for stage, steps in enumerate(cfg.iterations):
        params = [transl] * pinhole + cam_params + [pose] + [betas] * (stage > 1)
        opt = torch.optim.Adam(params, lr=cfg.lr)
        for _ in range(steps):
            opt.zero_grad()
            value = loss(stage)
            value.backward()
            if stage == 0:  # only the global orientation moves in the first stage
                pose.grad[:, 1:] = 0
            opt.step()
    with torch.no_grad():
        pose_f = _interpolate(pose.detach(), flagged)
        transl_f = _interpolate(transl.detach(), flagged) if pinhole else transl
        if pinhole:
            cam_f = camera
        else:
            cam_f = OrthographicCamera(_interpolate(cam_params[0].detach(), flagged).exp(),
                                       _interpolate(cam_params[1].detach(), flagged), camera.width, camera.height)  # fmt: skip
        kp2d = (cam_f.project(kpm(betas.detach(), pose_f, transl_f))[0])
        conf = detected[..., 2] > 0
        err = (kp2d - detected[..., :2]).norm(dim=-1)
        residual = torch.where(flagged, torch.nan, (err * conf).sum(-1) / conf.sum(-1).clamp_min(1))
    return FitResult(betas.detach(), pose_f, transl_f, cam_f, flagged, residual)


def _torso_mask(detected: torch.Tensor) -> torch.Tensor:
    mask = torch.zeros_like(detected)
    mask[:, list(TORSO)] = 1.0
    return mask
