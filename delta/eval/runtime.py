"""How long a job that renders whole frames (evaluation, the export's videos) asks a cluster for.

A whole-frame render costs in proportion to its rays' samples: the capture's scoring size times the
samples a ray. Measured on 2 CPU cores (`benchmarks/render_speed.csv`): the long-haired talker's 512²
frame, 64 samples a ray through two NeRF layers, 35 s, ~2.1 µs a sample; tight's export, 16 samples,
~1.3 µs. A test-time refinement step renders ``refine_rays`` rays with gradients (the talker: ~2.5 s
for 4096 × 64 samples). The workflow reads what a job will render (the record's frames and the
evaluated stage's ``settings.json``) when its inputs exist — Snakemake evaluates a resource function
again just before the job runs — and asks for ``MARGIN`` times the estimate, for slower nodes.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import h5py
import numpy as np

from delta.eval.settings import SPLITS, EvalSettings, pick_frames
from delta.export.settings import ExportSettings

SECONDS_PER_SAMPLE = 2.5e-6
"""A ray sample's share of a whole-frame render without gradients (2 CPU cores)."""
SECONDS_PER_GRADIENT_SAMPLE = 1e-5
"""A ray sample's share of a refinement step (with gradients)."""
BUSY_FRACTION = 0.3
"""The share of a frame's pixels supersampled (``delta.models.image.busy_pixels``; the talker: ~0.3)."""
MARGIN = 3
"""The estimate times this much, for slower nodes."""


@dataclasses.dataclass(frozen=True)
class RenderJob:
    """What a job renders with: the scoring frame's pixels, a ray's samples, the record's split (N,)."""

    pixels: int
    samples: int
    split: np.ndarray


def read_job(record: str | Path, stage_settings: str | Path) -> RenderJob | None:
    """The record's whole-frame size and splits and the evaluated stage's samples a ray; None while
    either file is missing (a dry run, a job not yet ready) or does not hold them."""
    try:
        with h5py.File(record, "r") as f:
            height, width = f["full/images"].shape[1:3]
            split = np.asarray(f["split"][:])
        samples = json.loads(Path(stage_settings).read_text())["settings"]["render"]["samples"]
    except (OSError, KeyError, ValueError, TypeError):
        return None
    return RenderJob(int(height) * int(width), int(samples), split)


def render_seconds(job: RenderJob, supersample: int = 1) -> float:
    """One whole-frame render; supersampled only where the image is busy."""
    extra = BUSY_FRACTION * supersample**2 if supersample > 1 else 0.0
    return SECONDS_PER_SAMPLE * job.pixels * job.samples * (1.0 + extra)


def _minutes(seconds: float, attempt: int) -> int:
    return int(math.ceil(5 + attempt * MARGIN * seconds / 60))


def renders_minutes(job: RenderJob | None, renders: int, attempt: int, supersampled: int = 0, supersample: int = 1,
                    fallback: int = 20) -> int:  # fmt: skip
    """A job of ``renders`` whole frames at one ray a pixel and ``supersampled`` more at ``supersample``
    (an application's turntable and scored frames); ``fallback`` × attempt without a job."""
    if job is None:
        return fallback * attempt
    return _minutes(renders * render_seconds(job) + supersampled * render_seconds(job, supersample), attempt)


def videos_minutes(job: RenderJob | None, settings: ExportSettings, attempt: int, fallback: int = 20) -> int:
    """The export's videos part: the side-by-sides (a crop and a whole frame each, one line-up frame at
    least), the turntable and the novel-pose frames (at most ``novel_frames``)."""
    if job is None:
        return fallback * attempt
    novel = int(np.count_nonzero(job.split == SPLITS["test_pose"])) or len(job.split)
    renders = 2 * max(settings.sidebyside, 1) + settings.turntable_frames + min(novel, settings.novel_frames)
    return renders_minutes(job, renders, attempt)


def evaluation_minutes(job: RenderJob | None, settings: EvalSettings, attempt: int, fallback: int = 30) -> int:
    """The evaluation: per scored frame its refinement steps and its renders (refined, and unrefined
    where reported), supersampled as configured."""
    if job is None:
        return fallback * attempt
    frames = len(pick_frames(job.split, settings.splits, settings.max_frames))
    steps = settings.refine_steps
    renders = 2 if steps > 0 and settings.report_unrefined else 1
    refine = steps * settings.refine_rays * job.samples * SECONDS_PER_GRADIENT_SAMPLE
    per_frame = renders * render_seconds(job, settings.supersample) + refine
    return _minutes(frames * per_frame, attempt)
