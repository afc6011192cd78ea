"""The framing of a capture: the full body, or head and shoulders (``upper``: the lower body is never in view)."""

from __future__ import annotations

import logging

import numpy as np
import torch

from delta.body.lbs import lbs
from delta.body.model import BodyModel
from delta.body.parts import lower_body_vertices
from delta.cameras.models import OrthographicCamera, PinholeCamera

log = logging.getLogger(__name__)

#: An ``auto`` capture is ``upper`` when at most this share of lower-body vertices is ever in view.
#: A full-body capture shows nearly all of them (they are counted inside the image, seen or not);
#: a head-and-shoulders one the top of the pelvis at its bottom edge: 1.0–1.1% on the synthetic
#: ``upper`` subject from its init fit, which 1% called ``full``.
MAX_LOWER_IN_VIEW = 0.25


def frame_camera(camera, frame: int, n: int):
    """The camera of one frame: a pinhole camera is shared, an orthographic one is per frame."""
    if isinstance(camera, PinholeCamera):
        return camera
    return OrthographicCamera(camera.scale[frame], camera.trans[frame], n, n)


def _in_image(body: BodyModel, betas, poses, transl, camera, frame: int, n: int) -> torch.Tensor:
    """(V,) bool: the posed vertices of one frame that project inside the n×n image (in front of a
    pinhole camera), seen or hidden behind the body alike."""
    k = int(frame)
    out = lbs(body, betas[None].float(), poses[k : k + 1].float(), transl=transl[k : k + 1].float())
    uv, depth = frame_camera(camera, k, n).project(out.vertices[0])
    inside = ((uv >= 0) & (uv < n)).all(-1)
    if isinstance(camera, PinholeCamera):
        inside &= depth > 0
    return inside


@torch.no_grad()
def lower_body_in_view(
    body: BodyModel, betas, poses, transl, camera, frames, n: int, max_frames: int = 8
) -> float | None:
    """Share of the lower body's vertices inside the n×n image over (up to ``max_frames`` of) ``frames``
    (seen or hidden behind the body alike); None for a body model without a lower body."""
    lower = lower_body_vertices(body)
    if not lower.any():
        return None
    frames = np.asarray(frames)[:: max(1, len(frames) // max_frames)]
    seen = sum(int(_in_image(body, betas, poses, transl, camera, k, n)[lower].sum()) for k in frames)
    return seen / max(len(frames) * int(lower.sum()), 1)


@torch.no_grad()
def framed_vertices(
    body: BodyModel, betas, poses, transl, camera, frames, n: int, max_frames: int = 64
) -> torch.Tensor:
    """(V,) bool: the vertices inside the n×n image in at least one of (up to ``max_frames`` of) ``frames``:
    what the capture frames, seen or hidden behind the body (the back of a head that never turns is
    framed). A full-body capture frames every vertex; a head-and-shoulders one its upper chest up."""
    frames = np.asarray(frames)[:: max(1, -(-len(frames) // max_frames))]
    framed = torch.zeros(body.num_vertices, dtype=torch.bool)
    for k in frames:
        framed |= _in_image(body, betas, poses, transl, camera, k, n).cpu()
    return framed


def detect_capture(body: BodyModel, betas, poses, transl, camera, frames, n: int, max_frames: int = 8) -> str:
    """``upper`` when the lower body stays out of the n×n image in (up to ``max_frames`` of) ``frames``."""
    share = lower_body_in_view(body, betas, poses, transl, camera, frames, n, max_frames)
    if share is None:
        return "full"
    capture = "upper" if share <= MAX_LOWER_IN_VIEW else "full"
    log.info("lower body in view: %.1f%% of its vertices -> capture '%s'", 100 * share, capture)
    return capture
