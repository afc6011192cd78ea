"""Staged, batched fitting of shared shape, per-frame pose and camera to 2D keypoints and person masks.

Stage 1 fits the global orientation and translation (pinhole) or the per-frame
scaled-orthographic camera to the torso keypoints; stage 2 adds the body pose
with its priors (per-joint pose prior, knee bend prior, joint-angle limits);
stage 3 adds the shared shape, temporal smoothness and, when masks are given,
the silhouette of a coarse body mesh. Frames with too few confident keypoints
or an empty mask are flagged and take their neighbours' parameters. All frames
are optimised together (no per-frame Python loop). With a ``FitStart`` (body
parameters a dataset provides for the same model) only stage 3 runs, from them.
"""

from __future__ import annotations

import dataclasses

import torch

from delta.body.keypoints import KeypointMap
from delta.body.lbs import batch_rodrigues, rigid_transforms, skin
from delta.body.model import BodyModel
from delta.cameras.models import OrthographicCamera, PinholeCamera
from delta.fitting import silhouette as sil
from delta.fitting import terms
from delta.fitting.limits import joint_limits
from delta.fitting.start import TORSO, facing_orientation, init_ortho_scale, init_translation, interpolate


@dataclasses.dataclass
class FitConfig:
    iterations: tuple[int, int, int] = (150, 200, 150)
    lr: float = 0.03
    sigma_px: float = 30.0
    """Robust-penalty scale of the keypoint residuals (pixels)."""
    pose_weight: float = 2e-3
    shape_weight: float = 1e-3
    bend_weight: float = 1.0
    limit_weight: float = 100.0
    """Joint-angle limits (limits.py), per squared radian beyond the range."""
    smooth_weight: float = 0.05
    min_keypoints: int = 4
    conf_threshold: float = 0.3
    sil_weight: float = 300.0
    """Silhouette term (mean squared coverage error a frame); 0 turns it off."""
    sil_size: int = 64
    """Resolution (pixels a side) the masks and the mesh are compared at."""
    sil_sigma: float = 0.3
    """Softness of the rasterised silhouette (grid pixels²)."""
    sil_fill: float = 1.0
    """Weight of mask pixels the body leaves uncovered (below 1: loose clothing and hair)."""
    sil_cell: float = 0.03
    """Vertex-clustering cell (metres) of the coarse silhouette mesh."""


@dataclasses.dataclass
class FitStart:
    """Body parameters to start from (a dataset's, for the same body model)."""

    betas: torch.Tensor
    """(S,) shape."""
    pose: torch.Tensor
    """(F, J, 3) axis-angle pose."""
    transl: torch.Tensor
    """(F, 3) translation (ignored with an orthographic camera, whose template then carries the cameras)."""


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
    """(F,) bool: too few keypoints or an empty mask; parameters interpolated from neighbours."""
    few_keypoints: torch.Tensor
    """(F,) bool: fewer than ``min_keypoints`` confident keypoints."""
    empty_mask: torch.Tensor
    """(F,) bool: the person mask is empty (all False without masks)."""
    residual_px: torch.Tensor
    """(F,) mean reprojection error over confident keypoints (nan when flagged)."""


class PosedPoints:
    """3D keypoints (and optionally a vertex subset) of a body model, skinning only the vertices needed."""

    def __init__(self, model: BodyModel, kp_map: KeypointMap, extra_vids: torch.Tensor | None = None):
        self.model = model
        kp_vids = torch.nonzero(kp_map.vertex_weights.abs().sum(0) > 0).squeeze(1)
        self.n_extra = 0 if extra_vids is None else len(extra_vids)
        self.vids = kp_vids if extra_vids is None else torch.cat([extra_vids, kp_vids])
        self.vw = kp_map.vertex_weights[:, kp_vids].to(model.v_template.dtype)
        self.jw = kp_map.joint_weights.to(model.v_template.dtype)

    def __call__(self, betas, pose, transl) -> tuple[torch.Tensor, torch.Tensor]:
        """(S,), (F, J, 3), (F, 3) -> (F, K, 3) keypoints and (F, V_extra, 3) extra vertices."""
        m, F, S = self.model, pose.shape[0], betas.shape[0]
        joints = m.joints_template + torch.einsum("s,jcs->jc", betas, m.joints_shapedirs[..., :S])
        verts = m.v_template[self.vids] + torch.einsum("s,vcs->vc", betas, m.shapedirs[self.vids][..., :S])
        posed_joints, A = rigid_transforms(batch_rodrigues(pose), joints.expand(F, -1, -1), m.parents)
        posed, _ = skin(verts.expand(F, -1, -1), m.weights[self.vids], A)
        posed = posed + transl[:, None]
        kp = torch.einsum("kj,fjc->fkc", self.jw, posed_joints + transl[:, None])
        kp = kp + torch.einsum("kv,fvc->fkc", self.vw, posed[:, self.n_extra :])
        return kp, posed[:, : self.n_extra]


class KeypointModel(PosedPoints):
    """3D keypoints only: (S,), (F, J, 3), (F, 3) -> (F, K, 3)."""

    def __call__(self, betas, pose, transl) -> torch.Tensor:
        return super().__call__(betas, pose, transl)[0]


def _project(camera, pinhole: bool, cam_params: list[torch.Tensor], points: torch.Tensor) -> torch.Tensor:
    if pinhole:
        return camera.project(points)[0]
    return OrthographicCamera(cam_params[0].exp(), cam_params[1], camera.width, camera.height).project(points)[0]


def fit(model: BodyModel, kp_map: KeypointMap, detected: torch.Tensor, camera, cfg: FitConfig = FitConfig(),
        pose_weights: torch.Tensor | None = None, knees: list[int] = (), masks: torch.Tensor | None = None,
        start: FitStart | None = None) -> FitResult:  # fmt: skip
    """Fit β, θ_f and the camera to (F, 18, 3) keypoint detections and optional (F, H, W) person masks.

    ``camera`` is a PinholeCamera (static; the body moves) or an OrthographicCamera whose per-frame
    scale and translation are fitted (its own values are the start when ``start`` is given).
    """
    model = model.to(dtype=torch.float64)
    detected = torch.nan_to_num(detected.to(torch.float64), nan=0.0).clone()
    detected[..., 2] = torch.where(detected[..., 2] >= cfg.conf_threshold, detected[..., 2], 0.0)
    F, J = detected.shape[0], model.num_joints
    few = (detected[..., 2] > 0).sum(-1) < cfg.min_keypoints
    use_sil = masks is not None and cfg.sil_weight > 0
    small = sil.downsample_masks(masks, cfg.sil_size) if masks is not None else None
    empty = small.flatten(1).amax(-1) <= 0 if small is not None else torch.zeros(F, dtype=torch.bool)
    flagged = few | empty
    detected[flagged, :, 2] = 0.0
    coarse = sil.coarse_mesh(model, cfg.sil_cell) if use_sil else None
    points = PosedPoints(model, kp_map, coarse.vertex_ids if use_sil else None)
    pose_weights = torch.ones(J, dtype=torch.float64) if pose_weights is None else pose_weights
    lo, hi = joint_limits(model)
    pinhole = isinstance(camera, PinholeCamera)
    if start is not None:
        betas = start.betas.to(torch.float64).clone()
        pose = start.pose.to(torch.float64).clone()
        transl = start.transl.to(torch.float64).clone() if pinhole else torch.zeros(F, 3, dtype=torch.float64)
    else:
        betas = torch.zeros(model.num_shape, dtype=torch.float64)
        pose = torch.zeros(F, J, 3, dtype=torch.float64)
        pose[:, 0] = facing_orientation(camera)
        kp0 = points(betas, pose, torch.zeros(F, 3, dtype=torch.float64))[0].detach()
        transl = init_translation(kp0, detected, camera) if pinhole else torch.zeros(F, 3, dtype=torch.float64)
    cam_params: list[torch.Tensor] = []
    if not pinhole:
        if start is not None:
            log_scale = torch.as_tensor(camera.scale, dtype=torch.float64).expand(F).log().clone()
            trans = torch.as_tensor(camera.trans, dtype=torch.float64).expand(F, 2).clone()
        else:
            log_scale = init_ortho_scale(kp0, detected, camera.height).log()
            trans = torch.zeros(F, 2, dtype=torch.float64)
        cam_params = [log_scale.requires_grad_(), trans.requires_grad_()]
    for t in (betas, pose, transl):
        t.requires_grad_()
    image_size = (camera.width, camera.height)
    sil_w = (~empty).to(torch.float64)

    def loss(stage: int) -> torch.Tensor:
        kp3d, verts = points(betas, pose, transl)
        kp2d = _project(camera, pinhole, cam_params, kp3d)
        det = detected if stage > 0 else detected * _torso_mask(detected)
        total = terms.keypoint_term(kp2d, det, cfg.sigma_px).sum()
        if stage > 0:
            total = total + cfg.pose_weight * terms.pose_prior(pose[:, 1:], pose_weights[1:]).sum() * cfg.sigma_px
            total = total + cfg.bend_weight * terms.bend_prior(pose, list(knees), 0, 1.0).sum()
            total = total + cfg.limit_weight * terms.joint_limit_prior(pose, lo, hi).sum()
        if stage > 1:
            total = total + cfg.shape_weight * terms.shape_prior(betas) * F * cfg.sigma_px
            total = total + cfg.smooth_weight * cfg.sigma_px * (terms.smoothness(pose) + terms.smoothness(transl))
            if use_sil:
                uv = _project(camera, pinhole, cam_params, verts)
                rendered = sil.frames_silhouette(uv, coarse.faces, cfg.sil_size, image_size, cfg.sil_sigma, masks=small)
                total = total + cfg.sil_weight * (sil_w * sil.silhouette_term(rendered, small, cfg.sil_fill)).sum()
        return total

    stages = list(enumerate(cfg.iterations))
    for stage, steps in stages[2:] if start is not None else stages:
        params = [transl] * pinhole + cam_params + [pose] + [betas] * (stage > 1)
        opt = torch.optim.Adam(params, lr=cfg.lr)
        for _ in range(steps):
            opt.zero_grad()
            value = loss(stage)
            value.backward()
            for p in params:  # a non-finite gradient (degenerate geometry) must not poison the parameters
                torch.nan_to_num_(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
            if stage == 0:  # only the global orientation moves in the first stage
                pose.grad[:, 1:] = 0
            opt.step()
    return _result(points, betas, pose, transl, camera, cam_params, detected, few, empty)


def _result(points, betas, pose, transl, camera, cam_params, detected, few, empty) -> FitResult:
    """Interpolate flagged frames from their neighbours and measure the reprojection residuals."""
    flagged = few | empty
    with torch.no_grad():
        pose_f = interpolate(pose.detach(), flagged)
        if isinstance(camera, PinholeCamera):
            transl_f, cam_f = interpolate(transl.detach(), flagged), camera
        else:
            transl_f = transl.detach()
            cam_f = OrthographicCamera(interpolate(cam_params[0].detach(), flagged).exp(),
                                       interpolate(cam_params[1].detach(), flagged), camera.width, camera.height)  # fmt: skip
        kp2d = cam_f.project(points(betas.detach(), pose_f, transl_f)[0])[0]
        conf = detected[..., 2] > 0
        err = (kp2d - detected[..., :2]).norm(dim=-1)
        residual = torch.where(flagged, torch.nan, (err * conf).sum(-1) / conf.sum(-1).clamp_min(1))
    return FitResult(betas.detach(), pose_f, transl_f, cam_f, flagged, few, empty, residual)


def _torso_mask(detected: torch.Tensor) -> torch.Tensor:
    mask = torch.zeros_like(detected)
    mask[:, list(TORSO)] = 1.0
    return mask
