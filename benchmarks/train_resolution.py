"""What the training resolution buys a subject, scored at the capture's size: its stages retrained with
the workflow's own settings for it (its stages' settings.json, which hold its scene's decisions) and the variant's
changes (``--resolution``, any ``--settings``, e.g. a coarse-to-fine switch), then evaluated (as the
workflow evaluates, or by ``--eval``); and a table of each variant's means.

    python benchmarks/train_resolution.py run --dataset real --subject head_shorthair \\
        --body resources/body/anny_sub1_face.npz --resolution 256 --work /tmp/head_shorthair_256
    python benchmarks/train_resolution.py table --subject head_shorthair \\
        --metrics 128=results/real/head_shorthair/eval/metrics.csv 256=/tmp/head_shorthair_256/metrics.csv \\
        --out benchmarks/train_resolution.csv
    python benchmarks/train_resolution.py run --dataset synthetic --subject tight --stages 1 \\
        --settings '{"stage1": {"fine_from": 0.5}}' --eval '{"splits": ["test_view"], "refine_steps": 0, \\
        "max_frames": 5, "supersample": 2, "stage": 1, "worst": 0}' --work /tmp/tight_fine
    python benchmarks/train_resolution.py run --dataset synthetic --subject gen4 --first 2 \\
        --settings '{"stage2": {"plateau_window": 100}}' --work /tmp/gen4_plateau

``--first 2`` retrains stage 2 alone, from the workflow's stage 1. ``--fit`` runs the init fit again with other
settings (the fit's silhouette on the dancer: ``docs/real_footage.md``) and trains from it:

    python benchmarks/train_resolution.py run --dataset real --subject dress_dance --body resources/body/anny_sub1.npz \\
        --stages 1 --fit '{"static_weight": 10, "exterior_fill": 0.3, "still_torso": 0.05, "sil_weight": 3000}' \\
        --eval '{"splits": ["train", "test_view"], "refine_steps": 0, "max_frames": 3, "supersample": 2, "stage": 1, \\
        "worst": 3}' --work /tmp/dancer_sil3000

``--truth`` trains from the synthetic capture's true body in place of the init fit: the generator's shape,
poses and translations written over the fit's ``params.npz`` (what a perfect init fit would buy the avatar):

    python benchmarks/train_resolution.py run --dataset synthetic --subject tight --body resources/body/anny_sub1.npz \\
        --stages 1 --truth data/synthetic/tight/gt --eval '{"splits": ["train", "test_view"], "refine_steps": 0, \\
        "max_frames": 4, "supersample": 2, "stage": 1, "worst": 0}' --work /tmp/tight_true_body

Each row: subject, variant, held-out split, refined or not, the means of PSNR, SSIM, ST-LPIPS, the region PSNRs, the
NeRF-mask IoU, the outline band's PSNR and error share and (a synthetic subject's) body error over the held-out
frames; a variant that ran its own init fit also its seconds and mean keypoint residual.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402

from delta.training.presets import deep_merge  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SCORES = [
    "psnr",
    "ssim",
    "stlpips_alex",
    "psnr_face",
    "psnr_hair",
    "psnr_clothing",
    "psnr_body",
    "nerf_iou",
    "psnr_outline",
    "outline_error_share",
    "body_err_mm",
    "body_err_pa_mm",
    "hair_layer_iou",
    "clothing_layer_iou",
]
EVAL = {"max_frames": 5, "refine_lr": 0.0005, "refine_rays": 4096, "refine_steps": 30, "refine_tol": 0.0,
        "report_unrefined": True, "splits": ["test_view", "test_pose"], "stage": 2, "supersample": 2, "worst": 0}  # fmt: skip


def run(a: argparse.Namespace) -> None:
    res = ROOT / "results" / a.dataset / a.subject
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    # no --scene: a stage's settings.json holds the scene's decisions already, and a decision the scene scales
    # (stage 2's length) would be scaled again
    common = ["--record", str(res / "frames.h5"), "--body", a.body,
              "--perceptual", str(ROOT / "resources/models/stlpips"), "--threads", str(a.threads)]  # fmt: skip
    start = str(res / "init/params.npz" if a.first == 1 else res / "stage1/model.pt")
    if a.fit is not None:  # the init fit again with these settings, the stages from it
        if a.first != 1:
            sys.exit("--fit retrains from the init fit: it needs --first 1")
        clock = time.perf_counter()
        with open(work / "fit.log", "w") as log:
            subprocess.run(["delta", "fit-init", "--record", str(res / "frames.h5"), "--body", a.body, "--out",
                            str(work / "init"), "--settings", a.fit, "--threads", str(a.threads)],
                           check=True, stdout=log, stderr=log)  # fmt: skip
        summary = json.loads((work / "init/summary.json").read_text())
        (work / "fit.json").write_text(json.dumps({"fit_s": round(time.perf_counter() - clock, 1),
                                                   "fit_residual_px": summary["residual_px_mean"]}))  # fmt: skip
        start = str(work / "init/params.npz")
    if a.truth is not None:
        if a.first != 1 or a.fit is not None:
            sys.exit("--truth replaces the init fit: it needs --first 1 and no --fit")
        start = str(true_body_start(res / "init/params.npz", Path(a.truth), work / "init"))
    for stage in range(a.first, a.stages + 1):
        saved = json.loads((res / f"stage{stage}/settings.json").read_text())
        settings = deep_merge(saved["settings"], json.loads(a.settings))
        settings["preset"] = saved["preset"]
        if a.resolution:
            settings["resolution"] = a.resolution
        out = work / f"stage{stage}"
        with open(work / f"stage{stage}.log", "w") as log:
            subprocess.run(["delta", "train", "--stage", str(stage), "--start", start, "--out", str(out),
                            "--settings", json.dumps(settings), *common], check=True, stdout=log, stderr=log)  # fmt: skip
        start = str(out / "model.pt")
    with open(work / "eval.log", "w") as log:
        subprocess.run(["delta", "evaluate", "--model", start, "--record", str(res / "frames.h5"), "--body", a.body,
                        "--subject", a.subject, "--out", str(work / "metrics.csv"), "--settings", a.eval or json.dumps(EVAL),
                        "--perceptual", str(ROOT / "resources/models/stlpips"), "--threads", str(a.threads)],
                       check=True, stdout=log, stderr=log)  # fmt: skip


def true_body_start(fit: Path, truth: Path, out: Path) -> Path:
    """``out/params.npz``: the init fit's file with the synthetic truth's shape, poses and translations of the
    same frames in place of the fitted ones (the truth's camera is the record's: a synthetic capture's)."""
    params = dict(np.load(fit))
    gt = np.load(truth / "params.npz")
    ids = params["frame_ids"]
    if gt["poses"].shape[1:] != params["poses"].shape[1:] or gt["betas"].shape != params["betas"].shape:
        sys.exit(f"{truth}: not the truth of this fit's body (poses {gt['poses'].shape[1:]} against "
                 f"{params['poses'].shape[1:]}, shape {gt['betas'].shape} against {params['betas'].shape})")  # fmt: skip
    if ids.max() >= len(gt["poses"]):
        sys.exit(f"{truth}: holds {len(gt['poses'])} frames; the fit names frame {int(ids.max())}")
    for key, value in (("betas", gt["betas"]), ("poses", gt["poses"][ids]), ("transl", gt["transl"][ids])):
        params[key] = value.astype(params[key].dtype)
    out.mkdir(parents=True, exist_ok=True)
    np.savez(out / "params.npz", **params)
    return out / "params.npz"


def stage_lengths(metrics: Path) -> dict:
    """The steps and the trainer's seconds of each stage beside a metrics.csv: a variant's (``work/stage{s}``)
    or the workflow's (``eval/metrics.csv`` beside ``stage{s}``); a variant's own init fit's seconds and mean
    keypoint residual (``work/fit.json``)."""
    fit = metrics.parent / "fit.json"
    out = json.loads(fit.read_text()) if fit.is_file() else {}
    for stage in (1, 2):
        for folder in (metrics.parent, metrics.parent.parent):
            losses = folder / f"stage{stage}" / "losses.csv"
            if losses.is_file():
                last = pd.read_csv(losses).iloc[-1]
                out |= {f"stage{stage}_steps": int(last["step"]), f"stage{stage}_s": float(last["seconds"])}
                break
    return out


def table(a: argparse.Namespace) -> None:
    rows = []
    for item in a.metrics:
        variant, path = item.split("=", 1)
        df = pd.read_csv(path)
        lengths = stage_lengths(Path(path))
        for (split, refined), part in df.groupby(["split", "refined"]):
            row = {"subject": a.subject, "variant": variant, "split": split, "refined": bool(refined),
                   "frames": len(part), "image": part["resolution"].iloc[0], **lengths}  # fmt: skip
            row.update({k: round(float(part[k].mean()), 4) for k in SCORES if k in part})
            rows.append(row)
    print(save_table(pd.DataFrame(rows), a.out, a.append).to_string(index=False))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--dataset", required=True)
    r.add_argument("--subject", required=True)
    r.add_argument("--body", required=True)
    r.add_argument("--resolution", type=int, default=0, help="the training resolution (0: the run's own)")
    r.add_argument("--settings", default="{}", help="JSON deep-merged over the run's settings")
    r.add_argument("--stages", type=int, choices=[1, 2], default=2, help="retrain stage 1 only, or both")
    r.add_argument(
        "--first",
        type=int,
        choices=[1, 2],
        default=1,
        help="the first stage retrained (2: stage 2 alone, from the workflow's stage 1)",
    )
    r.add_argument("--eval", default=None, help="JSON of the evaluation's settings (default: the workflow's)")
    r.add_argument(
        "--fit",
        default=None,
        help="JSON of the init fit's settings (every key: FitConfig): the fit is "
        "run again with them and the stages train from it (default: the workflow's fit)",
    )
    r.add_argument(
        "--truth",
        default=None,
        help="a synthetic capture's gt/ folder: train from its true body "
        "(shape, poses, translations) in place of the init fit",
    )
    r.add_argument("--work", required=True)
    r.add_argument("--threads", type=int, default=2)
    t = sub.add_parser("table")
    t.add_argument("--subject", required=True)
    t.add_argument("--metrics", nargs="+", required=True, help="VARIANT=metrics.csv of a variant")
    t.add_argument("--out", required=True)
    t.add_argument("--append", action="store_true")
    a = ap.parse_args()
    run(a) if a.cmd == "run" else table(a)


if __name__ == "__main__":
    main()
