"""What dressing and reshaping share: the avatar's first training frame rendered as trained and edited, both
scored against the generated truth where there is one, a lineup image and a turntable of the edited avatar."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import torch

from delta.applications.settings import ShowSettings
from delta.applications.truth import mean_scores, score_rows, truth_scorer, write_scores
from delta.data.frames import load_full_frames
from delta.export.video import to_bgr, turntable, write_video
from delta.io import atomic_path
from delta.models.image import full_view, render_image
from delta.progress import Progress
from delta.training.run import Trained


def show_edit(tr: Trained, record: str | Path, out: Path, name: str, edit: Callable[[], None], settings: ShowSettings,
              tags: dict, truth: str | Path | None = None, perceptual_dir: str | None = None,
              clothing: tuple[str | Path | None, str | Path | None] = (None, None)) -> dict:  # fmt: skip
    """Render ``tr``'s first training frame at the capture's size, call ``edit`` (it changes ``tr.model`` in
    place), render it again; write ``{name}.png`` ([frame | as trained | edited]), ``turntable.mp4`` of the
    edited avatar and ``scores.csv`` (rows tagged with ``tags``; ``clothing``: the clothing surfaces as
    trained and edited, for the garment distances). Returns what the summary reports of it."""
    model = tr.model
    frame = int(tr.data.train[0])
    full = load_full_frames(record, [frame], tr.settings.background)
    view = full_view(full, model.resolution)
    out.mkdir(parents=True, exist_ok=True)
    scorer = None
    if truth is not None and settings.score_frames:
        scorer = truth_scorer(tr, record, truth, settings.score_frames, perceptual_dir, settings.supersample)
    progress = Progress(f"{name} ({view.width}x{view.height})", 2 + settings.turntable_frames)
    with torch.no_grad():
        before = render_image(model, frame, view=view, soft_silhouette=False)["rgb"]
        rows = score_rows(scorer, "as_trained", tags, clothing[0])
        progress.tick("as trained")
        edit()
        after = render_image(model, frame, view=view, soft_silhouette=False)["rgb"]
        rows += score_rows(scorer, "edited", tags, clothing[1])
        progress.tick("edited")
    write_scores(out / "scores.csv", rows)
    with atomic_path(out / f"{name}.png") as tmp:
        cv2.imwrite(str(tmp), np.concatenate([to_bgr(full.images[0]), to_bgr(before), to_bgr(after)], axis=1))
    turn = turntable(model, frame, settings.turntable_frames, view)
    count = write_video(out / "turntable.mp4", progress.counted(turn, "turntable"), settings.fps)
    changed = float(((before - after).abs().amax(-1) > 0.05).float().mean())
    return {"frame": frame, "frame_id": int(tr.data.frame_ids[frame]), "turntable_frames": count,
            "resolution": "{}x{}".format(*full.size), "changed_pixels": round(changed, 4),
            "settings": vars(settings).copy(), "scores": mean_scores(rows)}  # fmt: skip
