"""Train both stages on the synthetic subjects under a preset and measure time, memory and quality.

Needs the main job's outputs (frame records and init fits: `snakemake --cores 2`). Each
(subject, preset) runs in a fresh process so that its peak RSS is its own. Writes
benchmarks/training_quality.csv with, per subject and preset: wall time of each stage, peak RSS,
held-out-view PSNR / L1 (full image, white background; test poses from the init fit, and refined
with the model frozen when --refine > 0), NeRF-mask IoU with the GT clothing mask, mesh-silhouette
IoU, and the body vertex error against the GT body under the clothing (centroid-aligned, training frames).

    python benchmarks/training_quality.py --subjects tight loose --preset fast
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import torch

from delta.io import load_state
from delta.host_memory import hold_freed_memory

ROOT = Path(__file__).resolve().parents[1]


def body_error_mm(model, data, meshes_h5: Path) -> float:
    """Mean vertex distance (mm) of the trained body to the GT body, centroids aligned, over training frames."""

    errs = []
    with h5py.File(meshes_h5) as f, torch.no_grad():
        gt_all = f["body_vertices"]
        offsets = model.offsets()
        for k in data.train[:: max(1, len(data.train) // 10)]:
            v = model.pose_body(int(k), offsets).vertices[0].numpy()
            gt = gt_all[int(data.frame_ids[k])]
            if gt.shape != v.shape:
                return float("nan")
            errs.append(np.linalg.norm((v - v.mean(0)) - (gt - gt.mean(0)), axis=1).mean())
    return 1000 * float(np.mean(errs))


def config_overrides(subject: str) -> list[dict]:
    """The training overrides config/config.yaml gives this subject (as the workflow applies them)."""
    import yaml

    train = yaml.safe_load((ROOT / "config/config.yaml").read_text()).get("training", {})
    own = dict(train.get("subjects", {}).get(subject, {}))
    own.pop("preset", None)
    return [train.get("overrides", {}), own]


def one(subject: str, preset: str, out: Path, extra: dict, refine: int) -> dict:
    from delta.body.model import load_body_model
    from delta.eval.heldout import score_frames
    from delta.training.presets import resolve
    from delta.training.run import build_avatar, load_init_from_state, run_stage, stage_frames

    torch.set_num_threads(2)
    rec = ROOT / f"results/synthetic/{subject}/frames.h5"
    body = ROOT / "resources/body/anny_sub1.npz"
    init = ROOT / f"results/synthetic/{subject}/init/params.npz"
    overrides = config_overrides(subject) + [extra]
    row = {"subject": subject, "preset": preset}
    t = time.time()
    run_stage(1, str(rec), str(body), str(init), str(out / "stage1"), preset, overrides)
    row["stage1_s"] = round(time.time() - t, 1)
    t = time.time()
    run_stage(2, str(rec), str(body), str(out / "stage1" / "model.pt"), str(out / "stage2"), preset, overrides,
              perceptual_dir=str(ROOT / "resources/models/stlpips"))  # fmt: skip
    row["stage2_s"] = round(time.time() - t, 1)
    row["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    st = resolve(preset, *overrides)
    data = stage_frames(rec, st)
    for stage in (1, 2):
        state = load_state(out / f"stage{stage}" / "model.pt")
        model = build_avatar(load_body_model(body), st, load_init_from_state(state["model"], data), data, stage,
                             torch.device("cpu"))  # fmt: skip
        model.load_state_dict(state["model"])
        test = np.flatnonzero(data.split == 1)
        for tag, steps in (("", 0), ("_refined", refine)) if refine and stage == 2 else (("", 0),):
            scores = score_frames(model, data, test, refine_steps=steps)
            row[f"s{stage}_psnr{tag}"] = round(float(np.mean([s.psnr for s in scores])), 2)
            row[f"s{stage}_l1{tag}"] = round(float(np.mean([s.l1 for s in scores])), 4)
            row[f"s{stage}_nerf_iou{tag}"] = round(float(np.nanmean([s.nerf_iou for s in scores])), 3)
            row[f"s{stage}_mesh_iou{tag}"] = round(float(np.mean([s.mesh_iou for s in scores])), 3)
        row[f"s{stage}_body_err_mm"] = round(
            body_error_mm(model, data, ROOT / f"data/synthetic/{subject}/gt/meshes.h5"), 1
        )
    return row


def main() -> None:
    hold_freed_memory()  # the host allocator as every delta command has it, so the clocks are the workflow's
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--subjects", nargs="+", default=["tight", "loose"])
    p.add_argument("--preset", nargs="+", default=["fast"])
    p.add_argument("--overrides", default="{}", help="JSON deep-merged over the preset (after config/config.yaml's)")
    p.add_argument("--refine", type=int, default=0, help="test-time refinement steps per held-out frame")
    p.add_argument("--work", default=str(ROOT / "results/benchmarks/training_quality"))
    p.add_argument("--out", default=str(ROOT / "benchmarks/training_quality.csv"))
    p.add_argument("--one", nargs=2, metavar=("SUBJECT", "PRESET"), help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.one:
        out = Path(a.work) / f"{a.one[0]}_{a.one[1]}"
        print("ROW " + json.dumps(one(a.one[0], a.one[1], out, json.loads(a.overrides), a.refine)))
        return
    rows = []
    for preset in a.preset:
        for subject in a.subjects:
            cmd = [sys.executable, __file__, "--one", subject, preset, "--overrides", a.overrides,
                   "--refine", str(a.refine), "--work", a.work]  # fmt: skip
            res = subprocess.run(cmd, capture_output=True, text=True)
            line = [x for x in res.stdout.splitlines() if x.startswith("ROW ")]
            if not line:
                sys.exit(f"{subject}/{preset} failed:\n{res.stderr[-3000:]}")
            rows.append(json.loads(line[0][4:]))
            print(rows[-1], flush=True)
    pd.DataFrame(rows).to_csv(a.out, index=False)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
