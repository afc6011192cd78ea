"""Face tracking: per-frame expression and head rotation from 2D face points, the body held as fitted.

Given the body's fit (shape, per-frame pose, translation, camera) and per-frame detections of face
points (u, v, confidence) whose embedding on the mesh is known (:mod:`delta.body.face_points`), the
fit finds per frame the expression activations (in [0, 1], Anny's facial actions) and a correction
of the head joints' rotations that reproject the points onto their detections. Priors: a small L2
and L1 pull of the activations towards a neutral face (most actions rest at 0), a pull of the head
correction towards the body fit, and first-order temporal smoothness of both. Every frame is fitted
at once; only the K face-point vertices are posed.

A frame is not fitted to garbage: where fewer than ``min_seen`` of the points are detected inside the
image it is flagged (``out of frame`` when the detections lie outside it, ``face not seen`` when they
are missing), and where the fitted face turns more than ``max_turn_deg`` from the camera it is flagged
``turned away``; flagged frames take their neighbours' values. A capture with no usable frame is an
error.

A frame the joint fit leaves far from its points (median residual over ``outlier_factor`` times the
capture's and over ``outlier_px``: a local minimum, typically every activation at its bound) starts
again from its neighbours' values for ``restart_iterations`` more steps of all frames; one still that
far is flagged ``poor fit`` and takes its neighbours' values too. The restart takes the nearest good
frame's whole pose and place for the frame as well: a face left that far usually sits on a body fit
that is off.

Shapes: F frames, K face points, J joints, E expression coefficients.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import torch

from delta import DeltaError
from delta.body.face_points import FacePoints, restrict
from delta.body.lbs import lbs
from delta.body.model import BodyModel
from delta.cameras.models import OrthographicCamera
from delta.fitting.start import interpolate
from delta.fitting.terms import gmof
from delta.optim import Adam

log = logging.getLogger(__name__)


@dataclasses.dataclass
class FaceFitConfig:
    iterations: int = 300
    lr: float = 0.02
    sigma_px: float = 6.0
    """Robust-penalty scale of the point residuals (pixels)."""
    expression_weight: float = 0.5
    """L2 pull of the activations to 0 (px² per unit activation²)."""
    sparsity_weight: float = 0.5
    """L1 pull of the activations to 0 (px² per unit activation)."""
    head_weight: float = 50.0
    """Pull of the head correction to the body fit (px² per rad²)."""
    shape_weight: float = 20.0
    """Pull of the shape correction to the body fit (px² per unit² of β, which is ~N(0, 1)): the face's
    points shape the face, which the body's few keypoints barely see."""
    place_weight: float = 1000.0
    """Pull of the per-frame translation correction across the image to the body fit (px² per m²)."""
    depth_weight: float = 1000.0
    """The same along the camera's axis, which a distant camera barely sees: a deeper, larger face
    projects like a nearer, smaller one, and the face is held at the body fit's depth."""
    one_place: bool = False
    """One translation correction for every frame (a still torso's, whose head turns on its neck), not one
    a frame."""
    smooth_weight: float = 2.0
    """First-difference smoothness of activations and head correction between consecutive frames (px² per unit²)."""
    conf_threshold: float = 0.5
    min_seen: float = 0.5
    """Share of the face points a frame must detect inside the image to be fitted."""
    max_turn_deg: float = 75.0
    """A fitted face turned further than this from the camera is flagged."""
    head_joints: tuple[str, ...] = ("neck02", "head", "neck")
    """The joints whose rotation the face corrects (those of them the body model has)."""
    outlier_factor: float = 4.0
    """A fitted frame whose median residual exceeds this many times the median over the fitted frames ..."""
    outlier_px: float = 2.0
    """... and this many pixels is fitted again from its neighbours (then flagged if it stays so)."""
    restart_iterations: int = 100
    """Steps of the fit again from the neighbours' values (0: no second try)."""


@dataclasses.dataclass
class FaceFit:
    expression: torch.Tensor
    """(F, E) activations in [0, 1]."""
    poses: torch.Tensor
    """(F, J, 3) the body poses with the head joints corrected."""
    betas: torch.Tensor
    """(S,) the body shape corrected by the face."""
    transl: torch.Tensor
    """(F, 3) the body translation corrected by the face."""
    flags: list[str]
    """(F,) '' for a fitted frame, else why it was not: 'face not seen', 'out of frame', 'turned away'."""
    residual_px: torch.Tensor
    """(F,) median reprojection error of the detected points (NaN where none)."""


def _inside(uv: torch.Tensor, camera) -> torch.Tensor:
    return (uv[..., 0] >= 0) & (uv[..., 0] < camera.width) & (uv[..., 1] >= 0) & (uv[..., 1] < camera.height)


def screen_frames(detected: torch.Tensor, camera, cfg: FaceFitConfig) -> tuple[torch.Tensor, list[str]]:
    """(F, K) usable detections and each frame's flag before fitting ('' when it can be fitted)."""
    confident = detected[..., 2] >= cfg.conf_threshold
    inside = _inside(detected[..., :2], camera)
    usable = confident & inside
    seen, found = usable.float().mean(1) >= cfg.min_seen, confident.float().mean(1) >= cfg.min_seen
    flags = ["" if s else "out of frame" if c else "face not seen" for s, c in zip(seen.tolist(), found.tolist())]
    return usable, flags


def face_turn_deg(out_transforms: torch.Tensor, head: int, camera, head_pos: torch.Tensor):
    """(F,) angle (deg) between the head's forward axis (+z at rest) and the direction to the camera."""
    forward = out_transforms[:, head, :3, 2]
    if isinstance(camera, OrthographicCamera):
        to_camera = torch.tensor([0.0, 0.0, 1.0], dtype=forward.dtype).expand_as(forward)
    else:
        centre = -(camera.R.T.to(forward.dtype) @ camera.t.to(forward.dtype))
        to_camera = centre[None] - head_pos
    cos = torch.nn.functional.cosine_similarity(forward, to_camera, dim=-1)
    return torch.rad2deg(torch.acos(cos.clamp(-1, 1)))


def nearest_good(bad: torch.Tensor) -> torch.Tensor:
    """(F,) for each frame the nearest frame not ``bad`` (itself when it is good; the earlier one on a tie)."""
    good = torch.nonzero(~bad).squeeze(1)
    frames = torch.arange(len(bad))
    return good[(frames[:, None] - good[None]).abs().argmin(1)]


def fit_face(
    model: BodyModel,
    points: FacePoints,
    detected: torch.Tensor,
    camera,
    betas: torch.Tensor,
    poses: torch.Tensor,
    transl: torch.Tensor,
    cfg: FaceFitConfig = FaceFitConfig(),
) -> FaceFit:
    """Fit (F, E) expressions and head corrections to (F, K, 3) detections; see the module docstring.

    ``betas`` (S,), ``poses`` (F, J, 3), ``transl`` (F, 3): the body fit; ``camera`` shared (pinhole) or
    per frame (orthographic with (F,) scale)."""
    if model.exprdirs is None:
        raise DeltaError(f"body model '{model.name}': face tracking needs an expression space")
    F, K = detected.shape[:2]
    if K != points.num_points:
        raise DeltaError(f"face points: {K} detections a frame for {points.num_points} embedded points")
    if not torch.isfinite(detected).all():
        bad = int(torch.nonzero(~torch.isfinite(detected).reshape(F, -1).all(1))[0])
        raise DeltaError(f"face points: frame {bad} holds NaN or infinite values")
    usable, flags = screen_frames(detected, camera, cfg)
    if all(flags):
        raise DeltaError(f"no face in any of the {F} frames: fewer than {cfg.min_seen:.0%} of the face points "
                         "detected inside the image in every frame")  # fmt: skip
    dtype = model.v_template.dtype
    used = points.used_vertices()
    small = restrict(model, used)
    local = FacePoints(torch.searchsorted(used, points.vertex_ids), points.bary)
    joints = [model.joint_names.index(n) for n in cfg.head_joints if n in model.joint_names]
    if not joints:
        raise DeltaError(f"body model '{model.name}': none of the head joints {list(cfg.head_joints)}")
    E = model.num_expression
    expression = torch.zeros(F, E, dtype=dtype, requires_grad=True)
    head = torch.zeros(F, len(joints), 3, dtype=dtype, requires_grad=True)
    shape = torch.zeros_like(betas, dtype=dtype, requires_grad=True)
    # in the camera's axes: across, up, depth
    place = torch.zeros(1 if cfg.one_place else F, 3, dtype=dtype, requires_grad=True)
    axes = torch.eye(3, dtype=dtype) if isinstance(camera, OrthographicCamera) else camera.R.to(dtype)
    place_w = torch.tensor([cfg.place_weight, cfg.place_weight, cfg.depth_weight], dtype=dtype)
    base = poses.to(dtype).detach().clone()  # (a restart replaces a frame's body fit: never the caller's)
    B0 = betas.to(dtype).detach()
    T0 = transl.to(dtype).detach().clone()
    target = detected[..., :2].to(dtype)
    fitted = torch.tensor([not f for f in flags])
    weight = usable.to(dtype) * fitted.to(dtype)[:, None]

    def pose_of(h):
        full = base.clone()
        full[:, joints] = full[:, joints] + h
        return full

    def fitted_points():
        out = lbs(small, (B0 + shape)[None].expand(F, -1), pose_of(head), expression, transl=T0 + place @ axes)
        return out, camera.project(local(out.vertices))[0]

    def optimise(iterations: int, rigid: int) -> None:
        # metres move pixels ~10x more than radians and activations: smaller steps for the translation
        opt = Adam([{"params": [expression, head, shape], "lr": cfg.lr},
                                {"params": [place], "lr": cfg.lr / 10}])  # fmt: skip
        for it in range(iterations):
            # first the face's placement, size and turn with a neutral face and a wide robust scale (a body
            # fit off by tens of pixels), then the expressions with it
            sigma = cfg.sigma_px * (5.0 if it < rigid else 1.0)
            expression.requires_grad_(it >= rigid)
            opt.zero_grad()
            uv = fitted_points()[1]
            data = (weight * gmof(uv - target, sigma)).sum(1)
            prior = cfg.expression_weight * expression.square().sum(1) + cfg.sparsity_weight * expression.abs().sum(1)
            prior = prior + cfg.head_weight * head.square().sum((1, 2)) + (place.square() * place_w).sum(1)
            smooth = cfg.smooth_weight * (
                (expression[1:] - expression[:-1]).square().sum(1) + (head[1:] - head[:-1]).square().sum((1, 2))
            )
            steady = ((place[1:] - place[:-1]).square() * place_w).sum()  # 0 for one place
            loss = (data + prior).sum() + smooth.sum() + steady + cfg.shape_weight * F * shape.square().sum()
            loss.backward()
            opt.step()
            with torch.no_grad():
                expression.clamp_(0.0, 1.0)
        expression.requires_grad_(True)

    def settled():
        """The fit as it stands: the posed points and each frame's median residual (F,)."""
        with torch.no_grad():
            out, uv = fitted_points()
            err = (uv - target).norm(dim=-1)
            return out, err.masked_fill(~usable, math.nan).nanmedian(1).values

    def far_off(residual: torch.Tensor) -> torch.Tensor:
        typical = float(residual[fitted].median())
        return fitted & (residual > max(cfg.outlier_factor * typical, cfg.outlier_px))

    optimise(cfg.iterations, cfg.iterations // 3)
    out, residual = settled()
    off = far_off(residual)
    if off.any() and cfg.restart_iterations > 0 and int(fitted.sum()) > int(off.sum()):
        log.info("face tracking: %d frame(s) far from their points (%s); fitted again from their neighbours",
                 int(off.sum()), torch.nonzero(off).squeeze(1).tolist()[:10])  # fmt: skip
        with torch.no_grad():  # from the frames fitted well (the unfitted ones take theirs at the end)
            bad = off | ~fitted
            expression.copy_(interpolate(expression.detach(), bad))
            # the body fit under such a frame is often off itself (a body turned or moved by decimetres
            # where the face moved a pixel): the frame takes its nearest good frame's whole pose and place
            # (not a blend: two fits may split one head turn differently between root, spine and neck)
            near = nearest_good(bad)[off]
            base[off] = pose_of(head.detach())[near]
            if cfg.one_place:  # the frames share their place's correction: it stays
                T0[off] = T0[near]
            else:
                T0[off] = (T0 + place.detach() @ axes)[near]
                place[off] = 0.0
            head[off] = 0.0
        optimise(cfg.restart_iterations, cfg.restart_iterations // 3)
        out, residual = settled()
        off = far_off(residual)
    flags = [f or ("poor fit" if off[i] else "") for i, f in enumerate(flags)]

    with torch.no_grad():
        head_j = model.joint_names.index("head") if "head" in model.joint_names else joints[-1]
        turn = face_turn_deg(out.joint_transforms, head_j, camera, out.joints[:, head_j])
        flags = [f or ("turned away" if turn[i] > cfg.max_turn_deg else "") for i, f in enumerate(flags)]
        bad = torch.tensor([bool(f) for f in flags])
        expr = interpolate(expression.detach(), bad)
        corrected = interpolate(head.detach(), bad)
        moved = interpolate((place.detach() @ axes).expand(F, -1), bad)
    if bad.any():
        counts = {k: flags.count(k) for k in set(flags) if k}
        log.warning("face tracking: %d of %d frames not fitted (%s); they take their neighbours' values",
                    int(bad.sum()), F, ", ".join(f"{v} {k}" for k, v in sorted(counts.items())))  # fmt: skip
    return FaceFit(expression=expr, poses=pose_of(corrected).detach(), betas=(B0 + shape).detach(), transl=T0 + moved,
                   flags=flags, residual_px=residual)  # fmt: skip
