"""The minutes a rendering job asks a cluster for: read from what it will render, counted by hand."""

import csv
import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest

from delta.eval import runtime
from delta.eval.runtime import (
    RenderJob,
    evaluation_minutes,
    read_job,
    render_seconds,
    renders_minutes,
    videos_minutes,
)
from delta.eval.settings import EvalSettings
from delta.export.settings import ExportSettings

REPO = Path(__file__).resolve().parents[2]


def _record(path: Path, size=(48, 64), split=(0, 0, 1, 2)) -> Path:
    with h5py.File(path, "w") as f:
        f.create_dataset("full/images", data=np.zeros((len(split), *size, 3), np.uint8))
        f.create_dataset("split", data=np.asarray(split, np.int8))
    return path


def test_a_job_is_read_from_the_record_and_the_stage_settings(tmp_path):
    record = _record(tmp_path / "frames.h5")
    settings = tmp_path / "settings.json"
    settings.write_text(json.dumps({"preset": "fast", "settings": {"render": {"samples": 46}}}))
    job = read_job(record, settings)
    assert job.pixels == 48 * 64 and job.samples == 46 and job.split.tolist() == [0, 0, 1, 2]
    # a dry run (files not there yet) or files without what is needed: no estimate, the fallback applies
    assert read_job(tmp_path / "none.h5", settings) is None and read_job(record, tmp_path / "none.json") is None
    settings.write_text(json.dumps({"settings": {}}))
    assert read_job(record, settings) is None
    assert videos_minutes(None, ExportSettings(), 2) == 40 and evaluation_minutes(None, EvalSettings(), 3) == 90


def test_the_videos_count_their_renders():
    split = np.array([0] * 5 + [2] * 10)
    job = RenderJob(512 * 512, 64, split)
    st = ExportSettings(sidebyside=4, turntable_frames=36, novel_frames=48)
    one = 2.5e-6 * 512 * 512 * 64  # a render, by hand
    renders = 2 * 4 + 36 + 10  # a crop and a whole frame per side-by-side, the turn, the 10 test-pose frames
    assert videos_minutes(job, st, 1) == math.ceil(5 + 3 * renders * one / 60)
    assert videos_minutes(job, st, 2) == math.ceil(5 + 6 * renders * one / 60)
    # no test-pose frames: the capture's frames, at most novel_frames of them; no side-by-side still renders one
    job = RenderJob(512 * 512, 64, np.zeros(100, int))
    st = ExportSettings(sidebyside=0, turntable_frames=2, novel_frames=48)
    assert videos_minutes(job, st, 1) == math.ceil(5 + 3 * (2 + 2 + 48) * one / 60)


def test_the_evaluation_counts_its_frames_renders_and_steps():
    split = np.array([0] * 4 + [1] * 7 + [2] * 3)
    job = RenderJob(540 * 540, 32, split)
    st = EvalSettings(max_frames=5, refine_steps=30, supersample=2)
    frame = 2 * 2.5e-6 * 540 * 540 * 32 * (1 + 0.3 * 4) + 30 * 4096 * 32 * 1e-5  # two renders, 30 steps
    assert evaluation_minutes(job, st, 1) == math.ceil(5 + 3 * (5 + 3) * frame / 60)
    st = EvalSettings(max_frames=0, refine_steps=0, supersample=1, splits=("train",))
    assert evaluation_minutes(job, st, 1) == math.ceil(5 + 3 * 4 * 2.5e-6 * 540 * 540 * 32 / 60)


def test_a_render_estimate_is_near_the_measured_renders():
    """The committed whole-frame render times (benchmarks/render_speed.csv, the current code's rows) are
    within 1.5x of the estimate the cluster's runtime is derived from."""
    rows = list(csv.DictReader((REPO / "benchmarks/render_speed.csv").open()))
    newest = rows[0]["code"]
    checked = 0
    for row in rows:
        if row["code"] != newest or row["mode"] == "every_pixel" and row["supersample"] != "1":
            continue
        size, ss = int(row["size"]), int(row["supersample"])
        estimate = render_seconds(RenderJob(size * size, 64, np.zeros(1)), ss)  # the talker: 64 samples
        assert estimate / 1.5 < float(row["seconds"]) < estimate * 1.5, row
        checked += 1
    assert checked == 2 and runtime.MARGIN >= 2


def test_an_application_counts_its_renders_and_its_scored_frames():
    job = RenderJob(512 * 512, 32, np.zeros(3))
    one, ss2 = render_seconds(job), render_seconds(job, 2)
    assert ss2 == pytest.approx(one * (1 + 0.3 * 4))
    assert renders_minutes(job, 14, 1, supersampled=10, supersample=2) == math.ceil(5 + 3 * (14 * one + 10 * ss2) / 60)
    assert renders_minutes(None, 14, 2, fallback=15) == 30
