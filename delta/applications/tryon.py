"""Entry point of ``delta try-on``: a person seen in one frame, dressed in a trained avatar's exterior.

The person needs no trained avatar of their own: the body model fitted to that frame (the init fit's
shape, pose and camera) makes a bare avatar (no offsets, the frame's average skin colour as albedo),
which takes the wearer's exterior as :mod:`delta.applications.dress` gives it. The exterior is rendered
from the frame's own camera and laid over the frame by its opacity: the person's face, hands and
background stay the photograph's, the garment and hair are the avatar's (``tryon.png``: the frame, the
try-on, the dressed bare body). A turntable shows the dressed body from all sides. What the new
exterior does not cover keeps the frame's pixels: a long dress in the frame shows below a short
garment put on over it (nothing is inpainted).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch

from delta import DeltaError
from delta.applications.dress import check_wearable, confine, put_on
from delta.applications.settings import ShowSettings
from delta.body.model import load_body_model
from delta.data.frames import load_frames, load_full_frames
from delta.export.video import to_bgr, turntable, write_video
from delta.io import atomic_path, require_files, save_json
from delta.models.image import full_view, render_image
from delta.models.init import load_init
from delta.progress import Progress
from delta.training.run import build_avatar, load_trained, pick_device

log = logging.getLogger(__name__)


def composite(photo: torch.Tensor, render: dict) -> torch.Tensor:
    """(H, W, 3) the photograph with the rendered exterior laid over it by the exterior's opacity."""
    alpha = render["nerf_mask"].clamp(0, 1)[..., None]
    return alpha * render["nerf"].clamp(0, 1) + (1 - alpha) * photo


def try_on(record: str | Path, init_params: str | Path, body_path: str | Path, wearer_model: str | Path,
           wearer_record: str | Path, out_dir: str | Path, anchor: int = -1, settings: ShowSettings | None = None,
           device: str = "cpu", wearer_body: str | Path | None = None, layers: Sequence[str] = ()) -> dict:  # fmt: skip
    """Write ``tryon.png``, ``turntable.mp4`` and ``tryon.json`` of the person of frame ``anchor`` of
    ``record`` (-1: the first training frame) wearing the exterior of ``wearer_model`` (trained on
    ``wearer_body``, when not ``body_path``; ``layers``: only these layers of it); returns the summary."""
    t_start = time.perf_counter()
    settings = settings or ShowSettings()
    require_files(record=record, init_fit=init_params, body_model=body_path, wearer_model=wearer_model,
                  wearer_record=wearer_record, wearer_body_model=wearer_body or body_path)  # fmt: skip
    wearer = load_trained(wearer_model, wearer_record, wearer_body or body_path, device)
    st = wearer.settings
    data = load_frames(record, st.resolution, st.background, st.box_margin)
    frame = int(data.train[0]) if anchor == -1 else anchor
    if not 0 <= frame < len(data.frame_ids):
        raise DeltaError(f"anchor: frame {anchor} is not a frame of {record} (0..{len(data.frame_ids) - 1})")
    body = load_body_model(body_path)
    # the person's own avatar is built bare (one NeRF at most): it wears the wearer's exterior
    model = build_avatar(body, dataclasses.replace(st, layers="one"), load_init(init_params, data), data, 1,
                         pick_device(device))  # fmt: skip
    model.eval()
    check_wearable(model, wearer.model, layers)
    confine(wearer, layers)
    put_on(model, wearer.model, layers)
    full = load_full_frames(record, [frame], st.background)
    view = full_view(full, model.resolution)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    progress = Progress(f"try-on ({view.width}x{view.height})", 1 + settings.turntable_frames)
    with torch.no_grad():
        render = render_image(model, frame, view=view, soft_silhouette=False)
    tried = composite(full.images[0], render)
    progress.tick("the frame")
    with atomic_path(out / "tryon.png") as tmp:
        cv2.imwrite(str(tmp), np.concatenate([to_bgr(full.images[0]), to_bgr(tried), to_bgr(render["rgb"])], axis=1))
    turn = turntable(model, frame, settings.turntable_frames, view)
    count = write_video(out / "turntable.mp4", progress.counted(turn, "turntable"), settings.fps)
    summary = {"record": str(record), "init": str(init_params), "wearer_model": str(wearer_model), "frame": frame,
               "frame_id": int(data.frame_ids[frame]), "capture": model.spec.capture,
               "wearer_capture": wearer.model.spec.capture, "covered": round(float((render["nerf_mask"] > 0.5).float().mean()), 4),
               "turntable_frames": count, "resolution": "{}x{}".format(*full.size),
               "seconds": round(time.perf_counter() - t_start, 2)}  # fmt: skip
    save_json(out / "tryon.json", summary)
    log.info("frame %d of %s wears %s's exterior: %s", frame, record, wearer_model, out)
    return summary
