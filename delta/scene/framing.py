"""The framing of a capture: the full body, or head and shoulders (``upper``: the lower body is never in view)."""

from __future__ import annotations

import logging

import numpy as np
import torch

from delta.body.lbs import lbs
from delta.body.model import BodyModel
from delta.body.parts import head_vertices, lower_body_vertices
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


def _projected(body: BodyModel, betas, poses, transl, camera, frame: int, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(V, 2) pixel coordinates of one frame's posed vertices and (V,) bool: those inside the n×n image (in
    front of a pinhole camera), seen or hidden behind the body alike."""
    k = int(frame)
    out = lbs(body, betas[None].float(), poses[k : k + 1].float(), transl=transl[k : k + 1].float())
    uv, depth = frame_camera(camera, k, n).project(out.vertices[0])
    inside = ((uv >= 0) & (uv < n)).all(-1)
    if isinstance(camera, PinholeCamera):
        inside &= depth > 0
    return uv, inside


def _in_image(body: BodyModel, betas, poses, transl, camera, frame: int, n: int) -> torch.Tensor:
    """(V,) bool: the posed vertices of one frame that project inside the n×n image."""
    return _projected(body, betas, poses, transl, camera, frame, n)[1]


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


#: ``training.clothing_on_head: auto`` bars the clothing layer from the head where the capture's clothing
#: covers at most this share of the fitted head's projected vertices (the short-haired synthetic talker's
#: shirt: 0.0; a hat or a hood covers the crown).
MAX_CLOTHING_ON_HEAD = 0.1


@torch.no_grad()
def clothing_on_head(body: BodyModel, betas, poses, transl, camera, frames, n: int, clothing,
                     max_frames: int = 16) -> float | None:  # fmt: skip
    """Share of the head's vertices (:func:`delta.body.parts.head_vertices`), posed by the fit and projected
    into (up to ``max_frames`` of) ``frames``, that land on ``clothing(frame)`` (n, n) bool; None for a body
    model without a head or a head never in the image."""
    head = head_vertices(body)
    if not head.any():
        return None
    frames = np.asarray(frames)[:: max(1, -(-len(frames) // max_frames))]
    on, seen = 0, 0
    for k in frames:
        uv, inside = _projected(body, betas, poses, transl, camera, int(k), n)
        px = uv[head & inside].long()
        on += int(clothing(int(k))[px[:, 1], px[:, 0]].sum())
        seen += len(px)
    return on / seen if seen else None
