"""Backward skinning over the k nearest posed body vertices (DELTA §3.2).

A posed body vertex i carries the per-vertex map M_i = G_i ∘ translate(d_i), with G_i the
blended skinning transform and d_i = rest_i - template_i (shape, pose-corrective and offset
displacement), so that M_i(template_i) = posed_i. The canonical space is the template in
the canonical pose: M^c_i = G^c_i. A posed point x maps back to

    x_c = Σ_i α_i M^c_i M_i^{-1} x = Σ_i α_i G^c_i (G_i^{-1} x - d_i),
    α_i ∝ exp(-‖x - v_i‖ ‖w_nn - w_i‖ / (2σ²))        (normalised in log space)

over its k nearest posed vertices v_i; w are skinning weights and nn the nearest vertex.
Points farther than ``max_dist`` from every vertex are invalid (the renderer gives them
no density and does not evaluate the NeRF there).

Contract (InstantAvatar-style, with no hidden state): ``prepare(...) -> SkinningFrame``
once per frame, then ``deform(frame, points)``.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import torch

from delta.geometry import distance_grid
from delta.geometry.nearest import PointIndex


@dataclasses.dataclass
class SkinningFrame:
    """Everything backward skinning needs for one frame (V vertices, J joints)."""

    posed: torch.Tensor
    """(V, 3) posed body vertices."""
    to_canonical: torch.Tensor
    """(V, 3, 4) affine maps posed space -> canonical space, one per vertex."""
    weights: torch.Tensor
    """(V, J) skinning weights."""
    index: PointIndex
    """kNN structure over the detached posed vertices, on their device (non-differentiable selection)."""
    near: Optional[distance_grid.DistanceGrid] = None
    """Coarse distance field to the posed vertices, with each voxel's nearest vertex (culling), when asked for."""


@dataclasses.dataclass
class Deformed:
    canonical: torch.Tensor
    """(N, 3) canonical points (garbage where not valid)."""
    valid: torch.Tensor
    """(N,) bool: within ``max_dist`` of the body."""
    posed_ref: torch.Tensor
    """(N, 3) kNN-weighted posed body point (the pose cue of the deformation network F_e)."""
    distance: torch.Tensor
    """(N,) distance to the nearest posed vertex."""


def affine_inverse(T: torch.Tensor) -> torch.Tensor:
    """(..., 3, 4) affine [A | a] -> its inverse [A^-1 | -A^-1 a]."""
    A_inv = torch.linalg.inv(T[..., :3])
    return torch.cat([A_inv, -(A_inv @ T[..., 3:])], dim=-1)


def compose(P: torch.Tensor, Q: torch.Tensor) -> torch.Tensor:
    """(..., 3, 4) affines: P ∘ Q."""
    return torch.cat([P[..., :3] @ Q[..., :3], P[..., :3] @ Q[..., 3:] + P[..., 3:]], dim=-1)


def prepare(posed: torch.Tensor, posed_T: torch.Tensor, displacement: torch.Tensor, canonical_T: torch.Tensor,
            weights: torch.Tensor, near_cell: float = 0.0, near_pad: float = 0.0) -> SkinningFrame:  # fmt: skip
    """Per-vertex maps posed -> canonical.

    Args:
        posed: (V, 3) posed vertices; posed_T: (V, 3, 4) their blended transforms G_i;
        displacement: (V, 3) d_i = rest_i - template_i; canonical_T: (V, 3, 4) G^c_i;
        weights: (V, J) skinning weights.
        near_cell, near_pad: also build a distance grid of this cell size with this room (0: none).
    """
    inv = affine_inverse(posed_T)
    eye = torch.eye(3, dtype=inv.dtype, device=inv.device).expand_as(inv[..., :3])
    untranslate = torch.cat([eye, -displacement[..., None]], dim=-1)
    to_canonical = compose(canonical_T, compose(untranslate, inv))
    pts = posed.detach()
    near = distance_grid.build(pts, near_cell, near_pad, nearest=True) if near_cell > 0 else None
    return SkinningFrame(posed=posed, to_canonical=to_canonical, weights=weights, index=PointIndex(pts), near=near)


def knn(frame: SkinningFrame, points: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices (N, k) of the k nearest posed vertices, nearest first, and differentiable distances (N, k)."""
    idx = frame.index.query(points, k)[1]
    diff = points[:, None] - frame.posed[idx]
    # sqrt with a floor: finite gradient for a point exactly on a vertex
    return idx, torch.sqrt((diff * diff).sum(-1) + 1e-12)


def blend_weights(frame: SkinningFrame, idx: torch.Tensor, dist: torch.Tensor, sigma: float) -> torch.Tensor:
    """α (N, k): softmax of -‖x - v_i‖ ‖w_nn - w_i‖ / (2σ²) (log-space normalisation never underflows)."""
    return torch.softmax(-dist * weight_distance(frame.weights, idx) / (2 * sigma * sigma), dim=-1)


@torch.no_grad()
def weight_distance(weights: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """‖w_nn - w_i‖ (N, k) for neighbour lists idx (N, k), nearest first (constant: no gradient).

    Computed once per distinct (nearest, neighbour) vertex pair: the N·k pairs of a batch of samples
    repeat a few thousand vertex pairs, so this gathers far fewer (J,) weight rows than N·k of them.
    """
    n, k = idx.shape
    pairs = idx[:, :1] * weights.shape[0] + idx
    uniq, inverse = torch.unique(pairs.reshape(-1), return_inverse=True)
    a, b = uniq // weights.shape[0], uniq % weights.shape[0]
    return (weights[a] - weights[b]).norm(dim=-1)[inverse].view(n, k)


def deform(frame: SkinningFrame, points: torch.Tensor, k: int = 6, sigma: float = 0.1,
           max_dist: float = 0.2) -> Deformed:  # fmt: skip
    """Map posed points (N, 3) to the canonical space."""
    if len(points) == 0:
        empty = points.new_zeros((0,))
        return Deformed(points, empty.bool(), points, empty)
    idx, dist = knn(frame, points, k)
    alpha = blend_weights(frame, idx, dist, sigma)
    M = (alpha[..., None, None] * frame.to_canonical[idx]).sum(1)  # (N, 3, 4)
    canonical = (M[..., :3] @ points[..., None]).squeeze(-1) + M[..., 3]
    posed_ref = (alpha[..., None] * frame.posed[idx]).sum(1)
    return Deformed(canonical, dist[:, 0] < max_dist, posed_ref, dist[:, 0])


@torch.no_grad()
def rough_canonical(frame: SkinningFrame, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A cheap guess of ``deform``, for culling before the kNN query (no gradient, needs ``frame.near``).

    Each point goes back by the map of the vertex its distance-grid voxel is nearest to, instead
    of the blend over its k nearest vertices. Returns canonical points (N, 3) and the voxel
    distance to the body (N,) (+inf outside the grid; within √3 cells of the true distance).
    On a trained loose-clothing avatar the guess lies within 3 cm of ``deform``'s point
    (99th percentile 0.9 cm): less than one occupancy cell.
    """
    if frame.near is None:
        raise ValueError("rough_canonical needs a SkinningFrame prepared with a distance grid (near_cell > 0)")
    dist, who = distance_grid.lookup_nearest(frame.near, points)
    M = frame.to_canonical.detach()[who.to(points.device).clamp_min(0)]
    canonical = (M[..., :3] @ points.detach()[..., None]).squeeze(-1) + M[..., 3]
    return canonical, dist.to(points.device)
