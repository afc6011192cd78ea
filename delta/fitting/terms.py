"""Pure loss terms of the body-model initialisation (SMPLify-style), batched over frames.

Shapes: F frames, K keypoints, J joints, S shape coefficients.
"""

from __future__ import annotations

import torch

from delta.body.lbs import batch_rodrigues


def gmof(residual: torch.Tensor, sigma: float) -> torch.Tensor:
    """Geman-McClure robust penalty of (..., D) residuals: ρ(r) = σ² |r|² / (σ² + |r|²), per point.

    Quadratic near 0 (ρ ≈ |r|²), bounded by σ² far away, so outlier detections cost little.
    """
    sq = residual.square().sum(-1)
    return sigma**2 * sq / (sigma**2 + sq)


def keypoint_term(projected: torch.Tensor, detected: torch.Tensor, sigma: float = 20.0) -> torch.Tensor:
    """Confidence-weighted robust reprojection error.

    Args:
        projected: (F, K, 2) model keypoints in pixels.
        detected: (F, K, 3) detections (u, v, confidence).
    Returns:
        (F,) per-frame cost, normalised by the frame's total confidence (0 for frames without any).
    """
    conf = detected[..., 2]
    cost = (conf * gmof(projected - detected[..., :2], sigma)).sum(-1)
    return cost / conf.sum(-1).clamp_min(1e-6)


def depth_term(depth: torch.Tensor, detected: torch.Tensor, weight: torch.Tensor, bones: torch.Tensor,
               sigma: float = 0.1, margin: float = 0.1) -> torch.Tensor:  # fmt: skip
    """Robust cost of bones that run the other way along the viewing axis than a detector says.

    A limb swung toward the camera and one swung away project alike; a detector's relative depths tell
    the two apart, while the keypoints and the bone's length already fix how far it runs in depth. So
    the term takes from the detector only the side: per bone (a, b) whose detected depth difference
    d̂_b - d̂_a exceeds ``margin`` in size, the model's d_b - d_a on the other side of zero costs its
    Geman-McClure penalty; on the detector's side, any extent is free. The detector's depth origin
    and scale drop out.

    Args:
        depth: (F, K) model keypoints' camera depths.
        detected: (F, K) detected relative depths (non-finite: none).
        weight: (F, K) the keypoints' confidences.
        bones: (B, 2) keypoint index pairs.
    Returns:
        (F,) per-frame cost in [0, 1): the penalties over ``sigma``², weighted by the lesser confidence of
        each bone's ends, over the weights of the bones the detector gives a depth (0 for frames without).
    """
    a, b = bones[:, 0], bones[:, 1]
    seen = torch.isfinite(detected)
    w = torch.minimum(weight[:, a], weight[:, b]) * (seen[:, a] & seen[:, b])
    wanted = torch.where(seen, detected, 0.0)
    side = wanted[:, b] - wanted[:, a]
    sure = side.abs() > margin
    wrong = torch.relu(-torch.sign(side) * (depth[:, b] - depth[:, a])) * sure
    cost = (w * gmof(wrong[..., None], sigma)).sum(-1) / sigma**2
    return cost / w.sum(-1).clamp_min(1e-6)


def shape_prior(betas: torch.Tensor) -> torch.Tensor:
    """|β|² (the shape spaces here are scaled so that β ~ N(0, I))."""
    return betas.square().sum(-1)


def pose_prior(pose: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Per-joint weighted |θ_j|² around the rest pose: (F, J, 3), (J,) -> (F,)."""
    return (pose.square().sum(-1) * weights).sum(-1)


def subspace_prior(pose: torch.Tensor, projectors: torch.Tensor) -> torch.Tensor:
    """Σ_j |P_j θ_j|²: the part of each joint's rotation in the subspace its (J, 3, 3) projector keeps.

    With the projectors onto the rotations that move no keypoint (``unobserved_projectors``) it holds
    what the keypoints cannot see (a wrist's or foot's turn, a straight limb's twist) at rest; (F, J, 3) -> (F,).
    """
    return torch.einsum("jab,fjb->fja", projectors, pose).square().flatten(1).sum(-1)


def bend_prior(pose: torch.Tensor, joints: list[int], axis: int, sign: float) -> torch.Tensor:
    """Hinge joints bend one way only: penalise exp of the wrong-way angle (SMPLify's angle prior).

    ``sign`` is the direction of a natural bend of the ``axis`` component; (F, J, 3) -> (F,).
    """
    if not joints:
        return pose.new_zeros(pose.shape[0])
    wrong = -sign * pose[:, joints, axis]
    return torch.exp(wrong).sub(1).clamp_min(0).square().sum(-1)


def _linked(links: torch.Tensor | None, n: int, like: torch.Tensor) -> torch.Tensor:
    """(n,) 1 where consecutive frames belong to one sequence (``links`` None: all do)."""
    return like.new_ones(n) if links is None else links.to(like.dtype)


def smoothness(x: torch.Tensor, links: torch.Tensor | None = None) -> torch.Tensor:
    """Σ |x_{f+1} - x_f|² over consecutive frames of (F, ...) parameters (0 for one frame).

    ``links`` (F-1,) bool: whether frames f and f+1 are of one sequence (a novel-pose sequence
    after the training one is not tied to it); None: all are.
    """
    if x.shape[0] < 2:
        return x.new_zeros(())
    d = (x[1:] - x[:-1]).square().reshape(x.shape[0] - 1, -1).sum(-1)
    return (d * _linked(links, len(d), d)).sum()


def rotation_smoothness(axis_angle: torch.Tensor, links: torch.Tensor | None = None) -> torch.Tensor:
    """Σ ½ |R_{f+1} - R_f|²_F over consecutive frames of (F, 3) rotations (≈ Σ Δθ² for small steps).

    On rotation matrices, not axis-angle vectors: a subject turning through 180 degrees has
    neighbouring headings written (0, 3.1, 0) and (0, -3.1, 0), close as rotations and 6.2 apart
    as vectors, which the vector difference would tear apart. ``links`` as in ``smoothness``.
    """
    if axis_angle.shape[0] < 2:
        return axis_angle.new_zeros(())
    R = batch_rodrigues(axis_angle)
    d = 0.5 * (R[1:] - R[:-1]).square().sum((-1, -2))
    return (d * _linked(links, len(d), d)).sum()


def acceleration(x: torch.Tensor, links: torch.Tensor | None = None) -> torch.Tensor:
    """Σ |x_{f+1} - 2 x_f + x_{f-1}|² over frame triples of (F, ...) parameters (0 for fewer than 3).

    Unlike ``smoothness`` it costs nothing for a constant rate: a subject turning at a steady speed is
    not pulled towards standing still. ``links`` as in ``smoothness`` (a triple counts when both its
    links do).
    """
    if x.shape[0] < 3:
        return x.new_zeros(())
    d = (x[2:] - 2 * x[1:-1] + x[:-2]).square().reshape(x.shape[0] - 2, -1).sum(-1)
    link = _linked(links, x.shape[0] - 1, d)
    return (d * link[1:] * link[:-1]).sum()


def rotation_acceleration(axis_angle: torch.Tensor, links: torch.Tensor | None = None) -> torch.Tensor:
    """Σ ½ |R_f⁻¹ R_{f+1} - R_{f-1}⁻¹ R_f|²_F over frame triples of (F, 3) rotations.

    The change of the relative rotation between consecutive steps: zero for a steady turn about any
    axis, ≈ Σ |Δ²θ|² for small steps, and, like ``rotation_smoothness``, blind to the 2π jumps of
    axis-angle vectors. ``links`` as in ``acceleration``.
    """
    if axis_angle.shape[0] < 3:
        return axis_angle.new_zeros(())
    R = batch_rodrigues(axis_angle)
    step = R[:-1].transpose(1, 2) @ R[1:]  # (F-1, 3, 3) relative rotations
    d = 0.5 * (step[1:] - step[:-1]).square().sum((-1, -2))
    link = _linked(links, axis_angle.shape[0] - 1, d)
    return (d * link[1:] * link[:-1]).sum()


def static_pose(x: torch.Tensor, held: torch.Tensor | None = None) -> torch.Tensor:
    """Σ over the held frames of |x_f - x̄|², x̄ their mean: (F, ...) parameters, (F,) bool -> ().

    For a capture whose subject holds one pose while turning in place (People Snapshot's protocol,
    the synthetic turn): per-frame fits of the limbs wander with the heading (at an orthographic
    camera a frontal elbow's depth is unseen), and the wander is slow, so smoothness cannot remove
    it. Zero for fewer than two held frames.
    """
    held = torch.ones(x.shape[0], dtype=torch.bool, device=x.device) if held is None else held.to(x.device)
    if int(held.sum()) < 2:
        return x.new_zeros(())
    h = x[held]
    return (h - h.mean(0, keepdim=True)).square().sum()


def joint_limit_prior(pose: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Σ over joints and axes of the squared excess beyond [lo, hi]: (F, J, 3), (J, 3), (J, 3) -> (F,).

    Zero inside the range, so limits never pull a plausible pose towards the rest pose.
    """
    excess = (lo - pose).clamp_min(0) + (pose - hi).clamp_min(0)
    return excess.square().flatten(1).sum(-1)
