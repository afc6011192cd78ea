"""How long and how fast the test-time refinement of held-out frames should run (``evaluation.refine_*``).

Held-out frames were never trained on: their pose, translation and camera are the init fit's, and the
evaluation refines them with the model frozen before scoring (``delta/eval/heldout.py``). Held-out views
come from the capture's own sequence, whose fit the training already corrected; held-out poses are fitted
free, further from the truth. This scores one trained model under several (steps, learning rate) pairs
by the workflow's own evaluation (whole frames at the capture's size, refined rows), each from the same
start. Rows: one per (setting, split) with the mean PSNR, SSIM, ST-LPIPS, NeRF-mask IoU, the refinement's
probe loss before and after, and the evaluation's process seconds.

    PYTHONPATH=$PWD python3 benchmarks/refinement.py --model results/synthetic/gen2/stage2/model.pt \\
        --record results/synthetic/gen2/frames.h5 --body resources/body/anny_sub1.npz --subject gen2 \\
        --settings 30:5e-4 150:2e-3 150:2e-3:1e-4 --csv benchmarks/refinement.csv

A setting is STEPS:LR, or STEPS:LR:LR_END for a rate falling geometrically to LR_END by the last step;
a suffix @CHECK keeps the pose of the lowest probe loss measured every CHECK steps (``refine_check``), e.g.
150:2e-3:1e-4@10. ``--per-frame`` writes each frame's row as well (its steps, the step kept, its scores, and
its probe loss at each check as STEP:LOSS pairs). With ``--device cuda`` the scores are the same evaluation's
on a GPU (the refinement's losses match the CPU's to float rounding) and the seconds are wall-clock there.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import pandas as pd
import torch

import delta.eval.evaluate as evaluation
from delta.eval.evaluate import evaluate
from delta.eval.settings import EvalSettings
from delta.training.run import load_trained

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import device_name, trained_model_arguments  # noqa: E402

SCORES = ("psnr", "ssim", "stlpips_alex", "nerf_iou", "body_err_mm", "body_err_visible_mm", "refine_steps",
          "refine_loss_start", "refine_loss_end", "refine_kept_step", "refine_overruled")  # fmt: skip


def main(argv=None) -> None:
    ap = trained_model_arguments(argparse.ArgumentParser(description=__doc__.split("\n\n")[0]))
    ap.add_argument(
        "--settings", nargs="+", required=True, help="STEPS:LR[:LR_END][@CHECK], e.g. 30:5e-4 150:2e-3:1e-4@10"
    )
    ap.add_argument("--gt-meshes", default=None, help="the subject's gt/meshes.h5: body error columns too")
    ap.add_argument("--csv", required=True)
    ap.add_argument("--rays", type=int, default=4096, help="rays a refinement step draws (refine_rays)")
    ap.add_argument("--per-frame", default=None, help="also write each frame's scores and steps to this CSV")
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args(argv)
    torch.set_num_threads(2)
    rows, before = [], pd.read_csv(a.csv) if a.append and Path(a.csv).is_file() else None
    frame_rows, fits = [], []
    refine = evaluation.refine_frame

    def recorded(model, data, frame, *args, **kwargs):  # each frame's refinement, its checks kept for --per-frame
        fits.append((frame, refine(model, data, frame, *args, **kwargs)))
        return fits[-1][1]

    evaluation.refine_frame = recorded
    for setting in a.settings:
        schedule, _, check = setting.partition("@")
        steps, lr, *end = schedule.split(":")
        lr_end = float(end[0]) if end else float(lr)  # no end: a constant rate
        for split in a.splits:  # one split a pass: each pass's seconds are that split's
            st = EvalSettings(splits=(split,), max_frames=a.max_frames, refine_steps=int(steps), refine_lr=float(lr),
                              refine_lr_end=lr_end, refine_check=int(check or 0), report_unrefined=False,
                              refine_rays=a.rays, supersample=a.supersample, worst=0,
                              perceptual_dir=a.perceptual_dir)  # fmt: skip
            # fresh: refinement moves the frames' poses
            trained = load_trained(a.model, a.record, a.body, device=a.device)
            t0, w0 = time.process_time(), time.perf_counter()
            df = evaluate(trained, a.record, st, subject=a.subject, gt_meshes=a.gt_meshes)
            row = {"subject": a.subject, "refine_steps_budget": int(steps), "refine_rays": a.rays, "refine_lr": float(lr),
                   "refine_lr_end": lr_end, "refine_check": int(check or 0),
                   "split": split,
                   "frames": len(df), **{c: float(df[c].mean()) for c in SCORES if c in df},
                   "eval_cpu_s": round(time.process_time() - t0, 1), "eval_wall_s": round(time.perf_counter() - w0, 1),
                   "device": device_name(a.device, torch.get_num_threads()), "model": a.model, "host": platform.node()}  # fmt: skip
            rows.append(row)
            keys = {k: row[k] for k in ("subject", "refine_steps_budget", "refine_rays", "refine_lr", "refine_lr_end",
                                        "refine_check", "split")}  # fmt: skip
            checks = {f: " ".join(f"{s}:{loss:.7g}" for s, loss in fit.checks) for f, fit in fits}
            frame_rows += [{**keys, "frame": int(r["frame"]), **{c: float(r[c]) for c in SCORES if c in df},
                            "checks": checks.get(int(r["frame"]), "")} for r in df.to_dict("records")]  # fmt: skip
            fits.clear()
            print(pd.DataFrame(rows).drop(columns=["model", "host"]).to_string(), flush=True)
            # written after every row: a run cut short keeps what it measured
            pd.concat([before, pd.DataFrame(rows)], ignore_index=True).to_csv(a.csv, index=False)
            if a.per_frame:
                pd.DataFrame(frame_rows).to_csv(a.per_frame, index=False)


if __name__ == "__main__":
    main()
