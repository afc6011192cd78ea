"""Scoring an edited avatar against what the synthetic generator renders for the same edit.

For a synthetic subject B, the generator can render the true result of an application: B's body
(shape, skin, motion, camera: B's seed) wearing avatar A's garments and hair, or B's garments on B's
body with its phenotype edited (``delta.synthetic.spec.dressed_raw`` / ``reshaped_raw``). Its frames go
through the frame record's own steps (undistortion, resizing to the scoring size, the person alpha
composited on the background) so that they line up pixel for pixel with B's record's whole frames.

Each scored frame is rendered twice, with B's fitted pose and camera (no test-time refinement): B's
avatar as trained (the baseline: what one gets without the application) and B's avatar edited; both
are scored against the truth (PSNR, SSIM, L1, ST-LPIPS, the IoU of the rendered exterior with the
true clothing-and-hair mask, the body vertex error against the true body and, given the clothing surface
the avatar exports, its distance to the true garments and hair).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import torch

from delta import DeltaError
from delta import metrics as M
from delta.data.sources import synthetic_source
from delta.eval.evaluate import Perceptual, body_errors, clothing_distance, gt_body_vertices, score_image
from delta.eval.settings import EvalSettings
from delta.models.image import View, render_image
from delta.data.video import iter_video
from delta.preprocess.frames import Undistorter, whole


@dataclasses.dataclass
class Truth:
    """Frames of a generated capture at a record's scoring size."""

    images: torch.Tensor
    """(F, H, W, 3) in [0, 1], composited on the background."""
    exterior: torch.Tensor
    """(F, H, W) bool: clothing or hair, inside the person."""
    head: torch.Tensor
    """(F, H, W) bool: the person less its clothing (a head-and-shoulders capture's face, hair and neck)."""


def truth_frames(capture: str | Path, frame_ids: list[int], size: tuple[int, int], background) -> Truth:
    """The generated capture's frames ``frame_ids`` at ``size`` (W, H), as a record's whole frames are made."""
    capture = Path(capture)
    if not (capture / "gt" / "params.npz").is_file():
        raise DeltaError(f"{capture}: no generated capture (gt/params.npz) to score against")
    source = synthetic_source(capture, capture.name)
    und = Undistorter(source.camera)
    bg = np.asarray(background, dtype=np.float32)
    images, exterior, head = {}, {}, {}
    try:
        for i, rgb in iter_video(source.video, set(frame_ids)):
            alpha = whole(und.image(source.provided["person"](i), mask=True), size, cv2.INTER_AREA)
            a = alpha.astype(np.float32)[..., None] / 255.0
            img = whole(und.image(rgb), size, cv2.INTER_AREA).astype(np.float32) / 255.0
            images[i] = img * a + bg * (1 - a)
            clothing, hair = (_part_mask(source, und, name, i, size) for name in ("clothing", "hair"))
            exterior[i] = (clothing | hair) & (alpha > 127)
            head[i] = (alpha > 127) & ~clothing
    finally:
        source.close()
    stack = lambda d: torch.from_numpy(np.stack([d[i] for i in frame_ids]))  # noqa: E731
    return Truth(stack(images), stack(exterior), stack(head))


def _part_mask(source, und: Undistorter, name: str, frame: int, size: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: a part's mask (it holds 0/1; the person's alpha 0..255) of ``frame`` at ``size``."""
    return whole(und.image(source.provided[name](frame), mask=True, nearest=True), size, cv2.INTER_NEAREST) > 0


class Scorer:
    """Scores renders and meshes of a trained avatar's frames against a generated truth: the images (ST-LPIPS
    when its weights folder is given), the exterior mask, the body vertex error (mm) against the truth's
    body and, given the avatar's clothing surface, its distance to the truth's garments and hair (mm)."""

    def __init__(self, tr, truth: Truth, meshes: Path, frames: list[int], view: View, perceptual_dir: str | None,
                 supersample: int):  # fmt: skip
        self.tr, self.truth, self.meshes, self.frames, self.view = tr, truth, meshes, frames, view
        self.supersample = supersample
        self.perceptual = Perceptual(EvalSettings(perceptual_dir=perceptual_dir), tr.model.background.device)
        self.body = gt_body_vertices(meshes, tr.data.frame_ids[frames])

    @torch.no_grad()
    def score(self, clothing: str | Path | None = None) -> list[dict]:
        """One row per frame of the avatar as it is now (``clothing``: its clothing surface in the NeRF's space,
        clothing_nerf_space.ply, for the garment distances)."""
        model, rows = self.tr.model, []
        keep = model.modelled.cpu().numpy()
        for k, f in enumerate(self.frames):
            img = render_image(model, f, supersample=self.supersample, view=self.view, soft_silhouette=False)
            row = {"frame": f, **score_image(img, self.truth.images[k], {}, self.perceptual)}
            mask = img["nerf_mask"] > 0.5 if model.nerf is not None else torch.zeros_like(self.truth.exterior[k])
            row["exterior_iou"] = M.iou(mask, self.truth.exterior[k])
            mesh = model.posed_mesh(f)[0]
            row |= body_errors(mesh, self.body[int(self.tr.data.frame_ids[f])], keep, model.camera(f))
            if clothing is not None and Path(clothing).is_file() and model.nerf is not None:
                found = clothing_distance(self.tr, clothing, self.meshes, [f], samples=10000)
                row |= {k: v for k, v in found.items() if k in ("clothing_chamfer_mm", "clothing_p2s_mm")}
            rows.append(row)
        return rows


def truth_scorer(tr, record: str | Path, truth_dir: str | Path, count: int, perceptual_dir: str | None,
                 supersample: int) -> Scorer:  # fmt: skip
    """A scorer of ``count`` of the trained avatar's test frames (evenly spaced) against a generated capture."""
    from delta.data.frames import load_full_frames
    from delta.export.run import report_frames
    from delta.models.image import full_view

    frames = report_frames(tr.data.split, count)
    full = load_full_frames(record, frames, tr.settings.background)
    ids = [int(tr.data.frame_ids[f]) for f in frames]
    truth = truth_frames(truth_dir, ids, full.size, tr.settings.background)
    return Scorer(tr, truth, Path(truth_dir) / "gt" / "meshes.h5", frames, full_view(full, tr.model.resolution),
                  perceptual_dir, supersample)  # fmt: skip


def score_rows(scorer: Scorer | None, variant: str, about: dict, clothing: str | Path | None = None) -> list[dict]:
    """Rows of ``scores.csv`` for one variant ("as_trained", "edited"); none without a truth."""
    if scorer is None:
        return []
    return [{**about, "variant": variant, **row} for row in scorer.score(clothing)]


def write_scores(path: str | Path, rows: list[dict]) -> None:
    """``scores.csv``: one row per (variant, frame); a header alone where there is no truth."""
    from delta.io import atomic_path

    table = pd.DataFrame(rows) if rows else pd.DataFrame(columns=["application", "variant", "frame", "psnr"])
    with atomic_path(path) as tmp:
        table.to_csv(tmp, index=False, float_format="%.5g")


#: the columns of ``scores.csv`` that say what a row is, not how it scores
NOT_SCORES = ("application", "variant", "frame", "frame_id", "split", "model", "wearer", "edit")


def summarize_scores(paths: list[str | Path]) -> pd.DataFrame:
    """``results/{dataset}/applications.csv``: per job (``.../{subject}/{application}/{name}/scores.csv``) and
    variant, the mean of each score over the frames, the number of frames, and what the edit gained over the
    avatar as trained (the ``gain`` row: edited − as trained; lower is better for L1 and ST-LPIPS)."""
    rows = []
    for path in paths:
        p = Path(path)
        table = pd.read_csv(p)
        if table.empty:
            continue
        subject, application, name = p.parts[-4], p.parts[-3], p.parts[-2]
        scores = [c for c in table.columns if c not in NOT_SCORES and pd.api.types.is_numeric_dtype(table[c])]
        means = table.groupby("variant", sort=False)[scores].mean()
        for variant, values in means.iterrows():
            rows.append({"application": application, "subject": subject, "name": name, "variant": variant,
                         "frames": int((table["variant"] == variant).sum()), **values.round(4).to_dict()})  # fmt: skip
        if {"as_trained", "edited"} <= set(means.index):
            gain = (means.loc["edited"] - means.loc["as_trained"]).round(4)
            rows.append({"application": application, "subject": subject, "name": name, "variant": "gain",
                         "frames": int((table["variant"] == "edited").sum()), **gain.to_dict()})  # fmt: skip
    return pd.DataFrame(rows)


def mean_scores(rows: list[dict]) -> dict:
    """{variant: {score: mean over the frames}} of ``scores.csv``'s rows (empty without a truth)."""
    out: dict = {}
    for variant in dict.fromkeys(r["variant"] for r in rows):
        sel = [r for r in rows if r["variant"] == variant]
        keys = [k for k, v in sel[0].items() if isinstance(v, float)]
        out[variant] = {k: round(float(np.mean([r[k] for r in sel])), 4) for k in keys}
    return out
