"""Rotations: axis-angle ↔ matrix ↔ quaternion, as pure batched functions.

The body model's poses are axis-angle vectors (SMPL-X's convention: the vector's direction is the axis,
its length the angle in radians, right-handed). Shapes: ``(..., 3)`` axis-angle, ``(..., 3, 3)``
matrices, ``(..., 4)`` quaternions ``(w, x, y, z)``. Device and dtype follow the inputs.

Every function is exact (to rounding) at the extremes a fit reaches, and differentiable there: a zero
angle (the rest pose: the closed forms divide by the angle, so small angles take their Taylor series)
and angles near π (a matrix's axis is read from its largest diagonal entry, not from the antisymmetric
part that vanishes at π).

They live here rather than being imported from kornia: ``import kornia`` loads its whole package (~0.5 s),
which every ``delta`` process, one per workflow job, would pay for three small functions.
"""

from __future__ import annotations

import torch

#: Below this angle (radians) the closed forms' ratios take their Taylor series (error < 1e-16 there).
SMALL_ANGLE = 1e-3


def _skew(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) the cross-product matrix: ``skew(v) @ u == v × u``."""
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    rows = (torch.stack([zero, -z, y], -1), torch.stack([z, zero, -x], -1), torch.stack([-y, x, zero], -1))
    return torch.stack(rows, -2)


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis-angle -> (..., 3, 3) rotation matrices (Rodrigues: R = I + a K + b K², K = skew(v),
    a = sin θ / θ, b = (1 - cos θ) / θ²)."""
    theta2 = (axis_angle * axis_angle).sum(-1, keepdim=True)[..., None]  # (..., 1, 1)
    small = theta2 < SMALL_ANGLE**2
    theta = torch.where(small, torch.ones_like(theta2), theta2).sqrt()  # the closed form's θ, 1 where unused
    a = torch.where(small, 1 - theta2 / 6 + theta2 * theta2 / 120, torch.sin(theta) / theta)
    half = torch.sin(theta / 2) / theta  # 1 - cos θ = 2 sin²(θ/2): no cancellation in single precision
    b = torch.where(small, 0.5 - theta2 / 24 + theta2 * theta2 / 720, 2 * half * half)
    K = _skew(axis_angle)
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device)
    return eye + a * K + b * (K @ K)


def matrix_to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions (w, x, y, z) with w ≥ 0.

    Each quaternion is read from whichever of its four components is largest (its square comes from the
    trace and the diagonal; the others from sums and differences of off-diagonal pairs divided by it),
    so no division is by a small number at any angle."""
    m = R.reshape(-1, 3, 3)
    m00, m01, m02 = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    m10, m11, m12 = m[:, 1, 0], m[:, 1, 1], m[:, 1, 2]
    m20, m21, m22 = m[:, 2, 0], m[:, 2, 1], m[:, 2, 2]
    # 4 q_i² (w, x, y, z)
    sq = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    # candidate k: (w, x, y, z) scaled by 4 q_k, from the off-diagonal sums and differences
    cand = torch.stack(
        [
            torch.stack([sq[:, 0], m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, sq[:, 1], m10 + m01, m02 + m20], -1),
            torch.stack([m02 - m20, m10 + m01, sq[:, 2], m21 + m12], -1),
            torch.stack([m10 - m01, m02 + m20, m21 + m12, sq[:, 3]], -1),
        ],
        -2,
    )  # (N, 4 candidates, 4 components)
    best = sq.argmax(-1)  # the four sum to 4: the largest is ≥ 1
    rows = torch.arange(len(m), device=m.device)
    q = cand[rows, best] / (2 * sq[rows, best].sqrt())[:, None]  # 4 |q_k| = 2 sqrt(4 q_k²)
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[:, :1] < 0, -q, q)
    return q.reshape(*R.shape[:-2], 4)


def quaternion_to_axis_angle(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) unit quaternions (w, x, y, z) -> (..., 3) axis-angle with angle in [0, π]."""
    q = torch.where(q[..., :1] < 0, -q, q)  # q and -q are one rotation: take the one with angle ≤ π
    w, v = q[..., :1], q[..., 1:]
    s2 = (v * v).sum(-1, keepdim=True)  # sin²(θ/2) for a unit quaternion
    small = s2 < SMALL_ANGLE**2
    s = torch.where(small, torch.ones_like(s2), s2).sqrt()  # the closed form's |v|, 1 where unused
    w_small = torch.where(small, w, torch.ones_like(w))
    # θ / |v| with θ = 2 atan(|v| / w); near 0 its Taylor series 2/w (1 - |v|²/(3 w²))
    ratio = torch.where(small, 2 / w_small * (1 - s2 / (3 * w_small * w_small)), 2 * torch.atan2(s, w) / s)
    return v * ratio


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 3) axis-angle with angle in [0, π]."""
    return quaternion_to_axis_angle(matrix_to_quaternion(R))


def mean_rotation(R: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) rotations -> (3, 3): their chordal mean, the rotation nearest (Frobenius) to their
    arithmetic mean, by its singular value decomposition with the determinant kept at +1."""
    U, _, Vt = torch.linalg.svd(R.mean(0))
    flip = torch.ones(3, dtype=R.dtype, device=R.device)
    flip[2] = torch.det(U @ Vt).sign()
    return U @ torch.diag(flip) @ Vt
