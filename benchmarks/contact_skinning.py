"""What telling body surfaces in contact apart does to a trained avatar in new poses (``render.contact_cell``).

A trained avatar's frames are scored twice with the same model: once with the plain kNN blend, once with
the contact probe (``deformers/knn.py``), whole capture frames, no refinement, against the capture's own
images. Training frames whose pose has no two surfaces in contact deform the same either way, so an
avatar trained without the probe measures what it does at render time; the frames that differ are the
poses where a hand, an arm or a leg touches another part. Rows: one per (setting, frame) with PSNR,
SSIM, ST-LPIPS, NeRF-mask IoU, the share of NeRF samples that had a second candidate, and the render's
process seconds (CPU time, which holds when other work shares the cores); a ``mean`` row per setting.

    PYTHONPATH=$PWD python3 benchmarks/contact_skinning.py --model results/synthetic/tight/stage1/model.pt \\
        --record results/synthetic/tight/frames.h5 --body resources/body/anny_sub1.npz \\
        --subject tight --splits test_pose --csv benchmarks/contact_skinning.csv
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from delta.deformers import knn
from delta.eval.evaluate import evaluate
from delta.eval.settings import SPLITS
from delta.eval.settings import EvalSettings
from delta.render import hybrid
from delta.training.run import load_trained

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402


class CountingDeform:
    """``knn.deform`` that counts the samples it maps and those with a second candidate."""

    def __init__(self):
        self.samples = self.others = 0
        self.inner = knn.deform

    def __call__(self, *args, **kwargs):
        out = self.inner(*args, **kwargs)
        self.samples += len(out.canonical)
        self.others += 0 if out.other is None else int(out.other.valid.sum())
        return out


def with_contact(model, cell: float) -> None:
    """Set the avatar's render settings' ``contact_cell`` in place."""
    model.spec = dataclasses.replace(model.spec, render=dataclasses.replace(model.spec.render, contact_cell=cell))


def contact_frames(model, frames) -> list[int]:
    """The frames among ``frames`` whose posed body has surfaces in contact (at a 3-cm probe)."""
    with_contact(model, 0.03)
    out = []
    with torch.no_grad():
        for f in frames:
            if model.posed_mesh(int(f))[0].skinning.touching is not None:
                out.append(int(f))
    return out


def restrict_to_contact(trained, splits) -> None:
    """Leave only the frames with contact in the scored splits (the others get no split)."""
    split = trained.data.split
    scored = [int(f) for f in np.flatnonzero(np.isin(split, [SPLITS[s] for s in splits]))]
    keep = contact_frames(trained.model, scored)
    print(f"{len(keep)} of {len(scored)} frames have surfaces in contact: {keep}")
    trained.data.split = np.where(np.isin(np.arange(len(split)), keep), split, -1)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", required=True)
    p.add_argument("--record", required=True)
    p.add_argument("--body", required=True)
    p.add_argument("--subject", required=True)
    p.add_argument("--splits", nargs="+", default=["test_pose"])
    p.add_argument("--max-frames", type=int, default=0, help="frames a split (0: every one)")
    p.add_argument(
        "--contact-only", action="store_true", help="score only the frames whose pose has surfaces in contact"
    )
    p.add_argument("--cells", default="0,0.03", help="contact_cell values to score (0: the plain blend)")
    p.add_argument("--supersample", type=int, default=2)
    p.add_argument("--perceptual", default="resources/models/stlpips")
    p.add_argument("--csv", required=True)
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    trained = load_trained(a.model, a.record, a.body)
    if a.contact_only:
        restrict_to_contact(trained, a.splits)
    st = EvalSettings(splits=tuple(a.splits), max_frames=a.max_frames, refine_steps=0, report_unrefined=False,
                      supersample=a.supersample, worst=0, perceptual_dir=a.perceptual)  # fmt: skip
    rows = []
    for cell in (float(c) for c in a.cells.split(",")):
        with_contact(trained.model, cell)
        counter = CountingDeform()
        hybrid.deformer.deform = counter
        t0 = time.process_time()
        try:
            df = evaluate(trained, a.record, st, subject=a.subject)
        finally:
            hybrid.deformer.deform = counter.inner
        cpu = time.process_time() - t0
        df.insert(0, "contact_cell", cell)
        keep = ["contact_cell", "subject", "frame", "frame_id", "split", "psnr", "ssim", "stlpips_alex", "nerf_iou"]
        df = df[[c for c in keep if c in df.columns]]
        mean = {"contact_cell": cell, "subject": a.subject, "frame": "mean", "split": " ".join(a.splits)}
        mean |= {c: df[c].mean() for c in ("psnr", "ssim", "stlpips_alex", "nerf_iou") if c in df.columns}
        mean |= {"second_candidates": counter.others / max(counter.samples, 1), "process_s": round(cpu, 1),
                 "machine": f"{platform.machine()} {torch.get_num_threads()} threads"}  # fmt: skip
        rows += df.to_dict("records") + [mean]
        print({k: mean[k] for k in ("contact_cell", "psnr", "nerf_iou", "second_candidates", "process_s")})
    save_table(pd.DataFrame(rows), a.csv)


if __name__ == "__main__":
    main()
