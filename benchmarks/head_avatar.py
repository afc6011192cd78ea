"""A talking head through the workflow, against its truth: face tracking, and what modelling expressions buys.

Reads finished workflow runs of a synthetic talking subject (``config/heads.yaml``), each given as
``LABEL=WORK`` (WORK: the folder the workflow ran in). For each run it reports the init fit's face
tracking against the generator's activations (per action: correlation and mean absolute error, over
every frame; all 52: mean absolute error) and the evaluation's held-out scores per split (PSNR, SSIM,
ST-LPIPS, face and hair PSNR, body error, at the capture's 512², as tracked and after test-time
refinement: means over the scored frames), with the training seconds of both stages. A run whose record has no face points (``use_provided`` without ``face_points``) is the
still-face baseline: the same capture trained with no expressions.

    python benchmarks/head_avatar.py --run tracked=/tmp/head-work --run still=/tmp/head-still \\
        --metrics still=/tmp/head-still/eval_still/metrics.csv --subject talker --out benchmarks/head_avatar.csv

(the still run's evaluation scored the test_pose split only, with the same settings).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
from workflow_run import train_benchmark  # benchmarks/ is the script's folder

ACTIONS = ("jawOpen", "eyeBlinkLeft", "mouthFunnel", "mouthSmileLeft", "browInnerUp", "mouthFrownLeft", "cheekPuff")


def tracking_rows(label: str, work: Path, subject: str) -> list[dict]:
    with np.load(work / f"results/synthetic/{subject}/init/params.npz") as p:
        if "expression" not in p.files:
            return [{"run": label, "kind": "tracking", "metric": "tracked", "value": 0.0}]
        fitted, ids = p["expression"], p["frame_ids"]
        names = [str(n) for n in p["expression_names"]]
        flagged = float(sum(bool(f) for f in p["face_flags"]))
        residual = float(np.nanmedian(p["face_residual_px"]))
    with np.load(work / f"data/synthetic/{subject}/gt/params.npz") as g:
        truth = g["expression"][ids]
    rows = [{"run": label, "kind": "tracking", "metric": "tracked", "value": 1.0},
            {"run": label, "kind": "tracking", "metric": "flagged_frames", "value": flagged},
            {"run": label, "kind": "tracking", "metric": "median_residual_px", "value": residual},
            {"run": label, "kind": "tracking", "metric": "mae_all_actions", "value": float(np.abs(fitted - truth).mean())}]  # fmt: skip
    for action in ACTIONS:
        i = names.index(action)
        corr = float(np.corrcoef(fitted[:, i], truth[:, i])[0, 1]) if truth[:, i].std() > 0 else float("nan")
        rows += [{"run": label, "kind": "tracking", "metric": f"{action}_corr", "value": corr},
                 {"run": label, "kind": "tracking", "metric": f"{action}_mae",
                  "value": float(np.abs(fitted[:, i] - truth[:, i]).mean())}]  # fmt: skip
    return rows


def score_rows(label: str, work: Path, subject: str, metrics_path: Path | None) -> list[dict]:
    metrics = pd.read_csv(metrics_path or work / f"results/synthetic/{subject}/eval/metrics.csv")
    rows = []
    keys = ("psnr", "ssim", "stlpips_alex", "psnr_face", "psnr_hair", "body_err_mm")
    for (split, refined), group in metrics.groupby(["split", "refined"]):
        for key in keys:
            if key in group:
                rows.append({"run": label, "kind": "heldout", "metric": f"{split}_{'refined' if refined else 'as_tracked'}_{key}",
                             "value": float(group[key].mean()), "frames": len(group)})  # fmt: skip
    for stage in (1, 2):  # the workflow's own benchmark of the train job (wall seconds)
        seconds = float(pd.read_csv(train_benchmark(work, "synthetic", subject, stage), sep="\t")["s"].iloc[0])
        rows.append({"run": label, "kind": "training", "metric": f"stage{stage}_seconds", "value": seconds})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", action="append", required=True, help="LABEL=WORK, a finished workflow run")
    ap.add_argument("--metrics", action="append", default=[], help="LABEL=CSV: a run's held-out scores elsewhere")
    ap.add_argument("--subject", default="talker")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    metrics = dict(item.partition("=")[::2] for item in args.metrics)
    rows = []
    for item in args.run:
        label, _, work = item.partition("=")
        scores = Path(metrics[label]) if label in metrics else None
        rows += tracking_rows(label, Path(work), args.subject) + score_rows(label, Path(work), args.subject, scores)
    table = pd.DataFrame(rows)
    table.to_csv(args.out, index=False)
    print(table.to_string(index=False))


if __name__ == "__main__":
    main()
