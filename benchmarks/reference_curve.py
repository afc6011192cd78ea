"""The reference configuration's learning curve, for the speed-up of #8 on subjects where 50 steps say nothing.

On 2 CPU cores a step of the reference (the paper's PE(10) 8×256 NeRF, 96 samples, no culling)
takes 5–8 s, so the workflow's sweep runs it 50 steps, in which the loose subject's training-ray
PSNR does not move. This script runs the same configuration (the sweep's own settings.json) for
a wall-clock budget on any device, in chunks that resume from the stage's checkpoint (the
trainer's exact-resume path), then writes model.pt. Steps are device-independent up to float
rounding (benchmarks/cuda_check.csv), so a curve taken on a GPU is projected to 2 CPU cores by
the 2-core seconds per step of the sweep's own run:

    python benchmarks/reference_curve.py train --settings results/synthetic/loose/tradeoff/reference/stage1/settings.json \\
        --record results/synthetic/loose/frames.h5 --body resources/body/anny_sub1.npz \\
        --init results/synthetic/loose/init/params.npz --out /tmp/ref_loose --seconds 900 --device cuda
    python benchmarks/reference_curve.py project --curve /tmp/ref_loose/losses.csv \\
        --cpu-losses results/synthetic/loose/tradeoff/reference/stage1/losses.csv \\
        --variant fast=results/synthetic/loose/stage1/losses.csv --subject loose --out benchmarks/reference_curve.csv --append

``--settings paper --override '{"resolution": 128, "stage1": {"rays": 1024}}'`` trains the same
configuration without a sweep run (the sweep's reference takes no subject's own training keys).

``rebound`` recomputes the lower bounds for a new run of a variant from a stored projection
(the reference's run time and best PSNR), when the long curve itself was not kept:

    python benchmarks/reference_curve.py rebound --reference benchmarks/reference_curve.csv \\
        --variant fast=results/synthetic/loose/stage1/losses.csv --subject loose --out benchmarks/reference_curve.csv --append

``project`` writes one row per (subject, variant, target PSNR): the 2-core seconds for the
reference to first reach the target (smoothed training-ray PSNR, the sweep's definition), the
variant's seconds, and their ratio. Targets: the variant's final PSNR and, when the reference rose at least MIN_GAIN_DB, its best. A
target the reference never reached gives a lower bound (``speedup_at_least``: the whole run's
projected seconds over the variant's).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from delta.body.model import load_body_model
from delta.eval.plots import smooth
from delta.eval.tradeoff import MIN_GAIN_DB, PSNR_WINDOW, hybrid_rows, psnr_gain, time_to_psnr
from delta.training.presets import deep_merge, resolve
from delta.training.run import build_avatar, load_init, pick_device, save_model, stage_frames
from delta.training.trainer import train_stage

from delta.host_memory import hold_freed_memory

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402


def train(args: argparse.Namespace) -> None:
    if Path(args.settings).is_file():  # a stage's settings.json: the preset and every resolved key
        saved = json.loads(Path(args.settings).read_text())
    elif args.settings.endswith(".json") or "/" in args.settings:
        raise SystemExit(f"{args.settings}: no such settings file")
    else:  # a preset's name: its own settings, --override on top
        saved = {"preset": args.settings, "settings": {}}
    raw = deep_merge(saved["settings"], json.loads(args.override))
    raw["stage1"] = {
        **raw.get("stage1", {}),
        "iterations": args.max_steps,
        "checkpoint_every": args.chunk,
        "preview_every": 0,
    }
    st = resolve(saved["preset"], raw)
    if st.stage1.lr_final != 1.0:
        raise SystemExit("the curve is a prefix of a longer run only without learning-rate decay (lr_final 1)")
    torch.set_num_threads(args.threads)
    dev = pick_device(args.device)
    data = stage_frames(args.record, st)
    model = build_avatar(load_body_model(args.body), st, load_init(args.init, data), data, 1, dev)
    out = Path(args.out)
    t0, steps = time.time(), 0
    while steps < args.max_steps:
        t = time.time()
        steps = train_stage(1, model, data, st, out, max_steps=steps + args.chunk).steps
        chunk_s = time.time() - t
        print(f"step {steps}: {time.time() - t0:.0f} s", flush=True)
        if time.time() - t0 + chunk_s > args.seconds:
            break
    save_model(out / "model.pt", model, 1, saved["preset"], st, steps)


def project(args: argparse.Namespace) -> None:
    curve = pd.read_csv(args.curve)
    if args.warmup and "warmup" not in curve.columns:  # a curve written before the trainer marked them
        curve["warmup"] = (curve["step"] <= args.warmup).astype(float)
    cpu = pd.read_csv(args.cpu_losses)
    # 2-core seconds per step of the sweep's run, its first step (warm-up) left out
    per_step = float((cpu["seconds"].iloc[-1] - cpu["seconds"].iloc[0]) / (len(cpu) - 1))
    first = float(cpu["seconds"].iloc[0])
    # a curve taken on 2 cores (--cpu-losses the curve itself) keeps its own clock
    projected = curve if args.measured else curve.assign(seconds=first + (curve["step"] - 1) * per_step)
    head = min(len(cpu), len(curve))
    drift = float(np.abs(cpu["psnr"].to_numpy()[:head] - curve["psnr"].to_numpy()[:head]).max())
    ref_psnr = smooth(hybrid_rows(projected)["psnr"].to_numpy(), PSNR_WINDOW)
    gain = psnr_gain(projected)
    rows = []
    for spec in args.variant:
        name, path = spec.split("=", 1)
        var = pd.read_csv(path)
        var_final = float(smooth(var["psnr"].to_numpy(), PSNR_WINDOW)[-1])
        targets = [("variant_final", var_final)]
        if gain >= MIN_GAIN_DB:  # a curve that never rose has no PSNR of its own to be reached
            targets.append(("reference_best", float(ref_psnr.max())))
        for label, target in targets:
            t_ref, t_var = time_to_psnr(projected, target), time_to_psnr(var, target)
            rows.append({"subject": args.subject, "variant": name, "target": label, "target_psnr": round(target, 3),
                         "reference_steps": len(curve), "reference_best_psnr": round(float(ref_psnr.max()), 3),
                         "reference_gain_db": round(gain, 3),
                         "reference_s_per_step_2cores": round(per_step, 3), "reference_s_2cores": t_ref,
                         "reference_run_s_2cores": float(projected["seconds"].iloc[-1]), "variant_s": t_var,
                         "speedup": t_ref / t_var if t_var > 0 else math.nan,
                         "speedup_at_least": (float(projected["seconds"].iloc[-1]) / t_var
                                              if math.isnan(t_ref) and t_var > 0 else math.nan),
                         "device_curve_vs_cpu_max_psnr_diff": round(drift, 4), "curve_device": args.curve_device})  # fmt: skip
    _write(rows, args.out, args.append)


def _write(rows: list[dict], path: str, append: bool) -> None:
    print(save_table(pd.DataFrame(rows), path, append).to_string(index=False))


def rebound(args: argparse.Namespace) -> None:
    """Lower bounds for a new run of a variant against a stored projection (its reference curve not kept).

    For each stored row of the subject whose target the reference never reached, and for the
    variant's own final PSNR when the reference's best lies below it, the bound is the reference's
    projected run time over the seconds the variant's new run needs to reach that target.
    """
    stored = pd.read_csv(args.reference)
    stored = stored[stored["subject"] == args.subject]
    if stored.empty:
        raise SystemExit(f"{args.reference}: no row for subject {args.subject!r}")
    ref = stored.iloc[0]
    best, run_s = float(ref["reference_best_psnr"]), float(ref["reference_run_s_2cores"])
    rows = []
    for spec in args.variant:
        name, path = spec.split("=", 1)
        var = pd.read_csv(path)
        targets = {f"stored_{r.variant}_final": float(r.target_psnr) for r in stored.itertuples()
                   if r.target == "variant_final" and math.isnan(float(r.reference_s_2cores))}  # fmt: skip
        targets["variant_final"] = float(smooth(var["psnr"].to_numpy(), PSNR_WINDOW)[-1])
        for label, target in targets.items():
            t_var = time_to_psnr(var, target)
            rows.append({"subject": args.subject, "variant": name, "target": label, "target_psnr": round(target, 3),
                         "reference_steps": int(ref["reference_steps"]), "reference_best_psnr": best,
                         "reference_gain_db": float(ref["reference_gain_db"]),
                         "reference_s_per_step_2cores": float(ref["reference_s_per_step_2cores"]),
                         "reference_s_2cores": math.nan, "reference_run_s_2cores": run_s, "variant_s": t_var,
                         "speedup": math.nan,
                         "speedup_at_least": run_s / t_var if target > best and t_var > 0 else math.nan,
                         "device_curve_vs_cpu_max_psnr_diff": float(ref["device_curve_vs_cpu_max_psnr_diff"]),
                         "curve_device": f"{ref['curve_device']} (stored projection)", "variant_losses": path})  # fmt: skip
    _write(rows, args.out, args.append)


def main() -> None:
    hold_freed_memory()  # the host allocator as every delta command has it, so the clocks are the workflow's
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument(
        "--settings",
        required=True,
        help="the sweep's reference stage1/settings.json, or a preset's name (e.g. paper) with --override",
    )
    t.add_argument("--record", required=True)
    t.add_argument("--body", required=True)
    t.add_argument("--init", required=True)
    t.add_argument("--out", required=True)
    t.add_argument("--seconds", type=float, default=600.0, help="wall-clock budget")
    t.add_argument("--max-steps", type=int, default=50000)
    t.add_argument("--chunk", type=int, default=50, help="steps between checkpoints / budget checks")
    t.add_argument("--device", default="cpu")
    t.add_argument("--threads", type=int, default=2)
    t.add_argument("--override", default="{}", help="JSON merged over the saved settings (e.g. a changed preset value)")
    pr = sub.add_parser("project")
    pr.add_argument("--curve", required=True, help="losses.csv of the long run")
    pr.add_argument("--cpu-losses", required=True, help="losses.csv of the sweep's 2-core reference run")
    pr.add_argument("--variant", action="append", required=True, help="NAME=losses.csv of a 2-core run")
    pr.add_argument("--subject", required=True)
    pr.add_argument("--curve-device", default="")
    pr.add_argument("--measured", action="store_true", help="the curve was taken on 2 CPU cores: keep its seconds")
    pr.add_argument(
        "--warmup",
        type=int,
        default=0,
        help="its first steps are a NeRF-only warm-up (for curves written before losses.csv marked them)",
    )
    pr.add_argument("--out", required=True)
    pr.add_argument("--append", action="store_true")
    rb = sub.add_parser("rebound", help="lower bounds of a new variant run against a stored projection")
    rb.add_argument("--reference", required=True, help="a reference_curve.csv written by project")
    rb.add_argument("--variant", action="append", required=True, help="NAME=losses.csv of a 2-core run")
    rb.add_argument("--subject", required=True)
    rb.add_argument("--out", required=True)
    rb.add_argument("--append", action="store_true")
    args = p.parse_args()
    {"train": train, "project": project, "rebound": rebound}[args.cmd](args)


if __name__ == "__main__":
    main()
