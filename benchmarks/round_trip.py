"""What the round trip of backward skinning (``render.round_trip``) does to a trained avatar.

The same trained model is scored with the test off and on, by the workflow's own evaluation (whole
frames at the capture's size, refined and unrefined rows), on its held-out views and poses. An avatar
trained without the test measures what it does at render time: the views should not move, the new
poses (crossed arms, an arm across the body) lose the clothing that backward skinning carries into
empty space beside another part. Rows: one per (setting, split, refined) with the split's mean PSNR,
SSIM, ST-LPIPS, NeRF-mask IoU, NeRF opacity off the person and the evaluation's process seconds.

    PYTHONPATH=$PWD python3 benchmarks/round_trip.py --model results/synthetic/gen2/stage2/model.pt \\
        --record results/synthetic/gen2/frames.h5 --body resources/body/anny_sub1.npz --subject gen2 \\
        --csv benchmarks/round_trip.csv
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import sys
import time
from pathlib import Path

import pandas as pd
import torch

from delta.eval.evaluate import evaluate
from delta.eval.settings import EvalSettings
from delta.training.run import load_trained

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table, trained_model_arguments  # noqa: E402

SCORES = ("psnr", "ssim", "stlpips_alex", "nerf_iou", "nerf_off_person", "psnr_clothing", "body_err_mm")


def with_round_trip(model, on: bool) -> None:
    """Set the avatar's render settings' ``round_trip`` in place."""
    model.spec = dataclasses.replace(model.spec, render=dataclasses.replace(model.spec.render, round_trip=on))


def main(argv=None) -> None:
    ap = trained_model_arguments(argparse.ArgumentParser(description=__doc__.split("\n\n")[0]))
    ap.add_argument("--refine-steps", type=int, default=30)
    ap.add_argument("--frames-csv", help="also write every scored frame's row here")
    ap.add_argument("--csv", required=True)
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args(argv)
    torch.set_num_threads(2)
    st = EvalSettings(splits=tuple(a.splits), max_frames=a.max_frames, refine_steps=a.refine_steps,
                      supersample=a.supersample, worst=0, perceptual_dir=a.perceptual_dir)  # fmt: skip
    rows, frames = [], []
    for on in (False, True):
        trained = load_trained(a.model, a.record, a.body, device=a.device)  # fresh: refinement moves poses
        with_round_trip(trained.model, on)
        t0 = time.process_time()
        df = evaluate(trained, a.record, st, subject=a.subject)
        seconds = time.process_time() - t0
        df.insert(0, "round_trip", on)
        frames.append(df)
        for (split, refined), g in df.groupby(["split", "refined"]):
            row = {"subject": a.subject, "round_trip": on, "split": split, "refined": bool(refined), "frames": len(g)}
            row |= {c: float(g[c].mean()) for c in SCORES if c in g}
            rows.append(row | {"eval_cpu_s": round(seconds, 1), "model": a.model, "host": platform.node()})
        print(pd.DataFrame(rows).to_string(), flush=True)
    save_table(pd.DataFrame(rows), a.csv, a.append)
    if a.frames_csv:
        save_table(pd.concat(frames), a.frames_csv, a.append)


if __name__ == "__main__":
    main()
