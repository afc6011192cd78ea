"""Forward skinning of canonical points (clothing vertices) to a frame, the inverse of backward kNN skinning.

Backward skinning (``delta.deformers.knn``) maps a posed point x with the per-vertex maps
M^c_i M_i^{-1}, blended over the k nearest *posed* vertices. The forward direction blends
the inverse maps M_i (M^c_i)^{-1} = G_i ∘ translate(d_i) ∘ (G^c_i)^{-1} over the k nearest
*canonical* vertices with the same weights α ∝ exp(-‖x_c - c_i‖ ‖w_nn - w_i‖ / (2σ²)):

    x = Σ_i α_i G_i ((G^c_i)^{-1} x_c + d_i)

That is exactly backward skinning with the roles of the two spaces swapped (the canonical
vertices are searched, the displacement enters with the opposite sign), so it reuses
``knn.prepare`` and ``knn.deform``; where the blend is locally constant, backward(forward(x)) = x.
"""

from __future__ import annotations

import math

import torch

from delta.deformers import knn as deformer


def prepare_forward(canonical: torch.Tensor, canonical_T: torch.Tensor, posed_T: torch.Tensor,
                    displacement: torch.Tensor, weights: torch.Tensor) -> deformer.SkinningFrame:  # fmt: skip
    """Per-vertex maps canonical -> posed.

    Args:
        canonical: (V, 3) canonical vertices c_i = G^c_i template_i; canonical_T: (V, 3, 4) G^c_i;
        posed_T: (V, 3, 4) the frame's blended transforms G_i; displacement: (V, 3) d_i = rest_i - template_i;
        weights: (V, J) skinning weights.
    """
    return deformer.prepare(canonical, canonical_T, -displacement, posed_T, weights)


def forward_skin(frame: deformer.SkinningFrame, points: torch.Tensor, k: int = 6, sigma: float = 0.1) -> torch.Tensor:
    """Canonical points (N, 3) -> posed points (N, 3); every point is mapped (no distance cut-off)."""
    return deformer.deform(frame, points, k, sigma, max_dist=math.inf).canonical
