"""Held-out PSNR along a training run: #8's 10x read on held-out views, not on training rays.

The sweep scores each variant's held-out views once, at its end, and times it to a PSNR on its
training rays. This script reruns a finished stage 1 from its own settings.json (the same preset,
subject keys and seed; with --run-losses each snapshot's losses are compared with the run's), stops it at the given steps through the trainer's exact-resume path, saves each
snapshot and scores it with the sweep's scoring (test views, no refinement, 2x2 rays a pixel).
Seconds are the trainer's clock at that step (this rerun's, and with --run-losses the finished
run's); scoring is not counted.

    python benchmarks/held_out_curve.py --settings results/synthetic/upper/stage1/settings.json \\
        --record results/synthetic/upper/frames.h5 --body resources/body/anny_sub1.npz \\
        --init results/synthetic/upper/init/params.npz --gt-meshes data/synthetic/upper/gt/meshes.h5 \\
        --subject upper --run-losses results/synthetic/upper/stage1/losses.csv \\
        --steps 25,50,100,200,400,800 --out /tmp/held_out_upper --csv benchmarks/held_out_curve.csv --append

``--override`` merges settings over the run's to take another variant's curve from the same start
(``--label`` names it); the GPU rows of tight at the capture's 512² (held_out_curve_gpu.csv):

    python benchmarks/held_out_curve.py --settings results/synthetic/tight/stage1/settings.json \
        --record results/synthetic/tight/frames.h5 --body resources/body/anny_sub1.npz \
        --init results/synthetic/tight/init/params.npz --subject tight --perceptual "" --device cuda --threads 8 \
        --override '{"resolution": 512, "nerf": {"levels": 6, "max_res": 192}, "albedo": {"levels": 6, "max_res": 192},
                     "render": {"samples": 32}, "stage1": {"iterations": 1200, "rays": 8192}}' \
        --label "512, grids 192, 32 samples, 8192 rays" --steps 300,600,1200 --out /tmp/hoc --csv benchmarks/held_out_curve_gpu.csv --append

``--preset`` with ``--scene`` takes a preset the workflow did not train for the subject, resolved as the workflow
would resolve it (the scene's decisions for that preset; an ``--override``'s keys win over them as a config's do):

    python benchmarks/held_out_curve.py --preset balanced --scene results/synthetic/tight/scene.json \
        --record results/synthetic/tight/frames.h5 --body resources/body/anny_sub1.npz \
        --init results/synthetic/tight/init/params.npz --gt-meshes data/synthetic/tight/gt/meshes.h5 \
        --subject tight --perceptual "" --steps 200,400,800,1600,2500 --out /tmp/hoc --csv CURVES.csv --append

Each row: subject, variant, device, step, the trainer's seconds at it, the smoothed training-ray PSNR, and the
held-out PSNR / SSIM / ST-LPIPS / NeRF IoU of the snapshot.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import pandas as pd
import torch

from delta.body.model import load_body_model
from delta.eval.evaluate import evaluate, summarize
from delta.eval.settings import EvalSettings
from delta.eval.plots import smooth
from delta.eval.tradeoff import PSNR_WINDOW
from delta.scene.settings import set_keys
from delta.training.presets import resolve
from delta.training.run import (
    build_avatar,
    stage_settings,
    load_init,
    load_trained,
    pick_device,
    save_model,
    stage_frames,
)
from delta.training.trainer import train_stage

from delta.host_memory import hold_freed_memory

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import device_name, save_table  # noqa: E402


def main() -> None:
    hold_freed_memory()  # the host allocator as every delta command has it, so the clocks are the workflow's
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--settings", default=None, help="settings.json of the finished stage 1")
    p.add_argument("--preset", default=None, help="in place of --settings: a preset as the workflow would train it ...")
    p.add_argument("--scene", default=None, help="... with the decisions of this scene.json")
    p.add_argument("--record", required=True)
    p.add_argument("--body", required=True)
    p.add_argument("--init", required=True)
    p.add_argument("--gt-meshes", default=None)
    p.add_argument("--subject", required=True)
    p.add_argument("--run-losses", default=None, help="the finished run's losses.csv: its first rows are compared")
    p.add_argument("--steps", required=True, help="comma-separated steps to score at")
    p.add_argument("--max-frames", type=int, default=5)
    p.add_argument("--perceptual", default="resources/models/stlpips")
    p.add_argument("--out", required=True, help="a directory for the checkpoint and the snapshots")
    p.add_argument("--csv", required=True)
    p.add_argument("--append", action="store_true")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--override", default="{}", help="JSON settings merged over the run's (another variant)")
    p.add_argument("--label", default="", help="the variant's name in the CSV (default: the preset's)")
    args = p.parse_args()

    if (args.settings is None) == (args.preset is None):
        raise SystemExit("give one of --settings (a finished stage 1) and --preset (with --scene)")
    override = json.loads(args.override)
    if args.settings:
        saved = json.loads(Path(args.settings).read_text())
        st = resolve(saved["preset"], saved["settings"], override)
    else:  # the scene decides for the keys the override does not set, as it does for a config's keys
        st = stage_settings(args.preset, [override], args.scene, set_keys([override]))
        saved, override = {"preset": args.preset}, {}
    steps = sorted({int(s) for s in args.steps.split(",")})
    if steps[-1] > st.stage1.iterations:
        raise SystemExit(f"--steps: {steps[-1]} is past the run's {st.stage1.iterations} iterations")
    torch.set_num_threads(args.threads)
    dev = pick_device(args.device)
    data = stage_frames(args.record, st)
    model = build_avatar(load_body_model(args.body), st, load_init(args.init, data), data, 1, dev)
    out = Path(args.out)
    scoring = EvalSettings(splits=("test_view",), max_frames=args.max_frames, refine_steps=0, supersample=2,
                           perceptual_dir=args.perceptual)  # fmt: skip
    run = pd.read_csv(args.run_losses) if args.run_losses else None
    rows = []
    for step in steps:
        losses = train_stage(1, model, data, st, out, max_steps=step).losses
        snapshot = out / f"step_{step:06d}.pt"
        save_model(snapshot, model, 1, saved["preset"], st, step)
        scores = summarize(evaluate(load_trained(snapshot, args.record, args.body, args.device), args.record, scoring,
                                    args.gt_meshes, args.subject))["test_view"]["unrefined"]  # fmt: skip
        row = {
            "subject": args.subject,
            "preset": saved["preset"],
            "variant": args.label or saved["preset"],
            "device": device_name(dev, args.threads),
            "step": step,
            "trained_steps": int(losses["step"].iloc[-1]),  # fewer than step where a plateau ended the stage
            "seconds": float(losses["seconds"].iloc[-1]),
            "train_psnr": float(smooth(losses["psnr"].to_numpy(), PSNR_WINDOW)[-1]),
            **{f"held_out_{k}": scores.get(k, float("nan")) for k in ("psnr", "ssim", "stlpips_alex", "nerf_iou")},
            # where the image is wrong: the ground truth's regions (face, hair, clothing, skin)
            **{f"held_out_{k}": v for k, v in scores.items() if k.startswith("psnr_") or k == "outline_error_share"},
        }
        # the finished run's clock at this step, and how closely the rerun follows it (the same settings only)
        if run is not None and not override:
            ran = run.head(step)
            row["run_seconds"] = float(ran["seconds"].iloc[-1])
            row["max_loss_rel_diff_to_run"] = float(((losses["loss"] - ran["loss"]).abs() / ran["loss"]).max())
        rows.append(row)
        print(json.dumps(row), flush=True)
    save_table(pd.DataFrame(rows), args.csv, args.append)


if __name__ == "__main__":
    main()
