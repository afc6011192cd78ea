"""A smooth-in-time correction of every frame's heading and placement, shared between neighbouring frames.

Training refines each frame's pose from the pixels of that frame alone, and a frame is drawn a few
times a stage (one frame a step): its pose barely moves, and a held-out frame between training
frames keeps its init fit. Under an orthographic camera the init fit's heading is least certain
where the subject faces the camera (a width changes with cos θ): the loose synthetic subject's
fit is 8-10° off there, the same way in every such frame. This correction is piecewise linear in
the frame's time τ (``frame_times``) between K knots: each knot learns from every training frame
around it, and held-out frames between training frames get the correction of their time.
Frames outside the training sequence (τ NaN, a novel-pose sequence) get none.

Shapes: F frames, K knots.
"""

from __future__ import annotations

import torch
from torch import nn


def hat_weights(tau: torch.Tensor, knots: int) -> torch.Tensor:
    """(F,) times in [0, 1] -> (F, K) weights of linear interpolation between K evenly spaced knots.

    Each row sums to 1 (two neighbouring knots share a frame between them); rows of NaN times are 0.
    """
    if knots < 2:
        raise ValueError(f"knots: {knots} (at least 2, at both ends of the sequence)")
    grid = torch.arange(knots, dtype=tau.dtype, device=tau.device)
    pos = tau.clamp(0, 1)[:, None] * (knots - 1)
    w = (1 - (pos - grid).abs()).clamp_min(0)
    return torch.where(torch.isnan(tau)[:, None], torch.zeros_like(w), w)


class Trajectory(nn.Module):
    """Per-knot corrections: a rotation of the root (axis-angle, applied before the frame's own) and a
    3-vector shift of the placement (body translation (m) for a pinhole camera; log-scale and image
    translation for an orthographic one). All zero at the start."""

    def __init__(self, frame_time: torch.Tensor, knots: int):
        super().__init__()
        self.rotation = nn.Parameter(torch.zeros(knots, 3, device=frame_time.device))
        self.shift = nn.Parameter(torch.zeros(knots, 3, device=frame_time.device))
        # derived from the record's frame times, not saved (as the avatar's own frame_time)
        self.register_buffer("weights", hat_weights(frame_time.float(), knots), persistent=False)

    def forward(self, frame: int | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The frame's (3,) root rotation and (3,) placement shift ((B, 3) each for (B,) frame indices)."""
        w = self.weights[frame]
        return w @ self.rotation, w @ self.shift
