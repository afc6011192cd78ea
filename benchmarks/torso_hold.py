"""A talking head's init fit and avatar with the limbs' hold and with the torso's, against the truth.

Reads a synthetic talking subject's results folders (``results/synthetic/{subject}`` of a finished
workflow run: ``init/``, ``stage1/``, ``stage2/``), each given as ``LABEL=FOLDER``, and the generator's
truth. For each it reports the init fit against the truth (the root's turn about its mean over the
frames, mean and largest, degrees: the truth's torso is still; the turn of the neck's chain about the
vertical against the truth's, correlation and largest error; the translation's spread per axis, mm; the
fit's keypoint residual, mean and largest, and the face tracking's median residual, px), each stage's
training-ray PSNR over its last 5 % of steps and its seconds, and the held-out scores of the run's
``metrics.csv`` (``LABEL=CSV``, the evaluation's: means per split, refined and not).

The committed rows: ``limbs`` (the limbs' hold, the fit turning the whole body with the head), ``torso``
(the torso pulled toward its mean by ``static_weight``), ``torso-face-place-frozen`` (the same with the face
tracking's translation frozen) and ``torso-tied`` (one torso for every frame, the workflow's; its face
tracking kept the body's place, where the workflow's fit corrects it once for every frame), all of the short-haired
talker, and ``long-hair-torso-tied`` (the long-haired talker, ``results/synthetic/talker``, fitted and
trained the workflow's way; its stage 1 ran beside other jobs: its seconds are not a measure). Rows of the
short-haired talker from one fit, each retrained through both stages (docs/heads.md, "The shirt's collar
and the chin"): ``short-base`` (the presets' ``clothing_on_head: yes``: any vertex carries the clothing), ``short-tied-training``
(the fit's tied torso kept one value for every frame through training and refinement; not adopted: its
held-out scores are those of a throwaway patch, the same fit), ``short-canonical-bar`` (the clothing layer
barred from the canonical space nearest the head's vertices; not adopted) and ``short-head-carries-none``
(``clothing_on_head: no``, what ``auto`` decides here: the clothing layer has no density at points the head's
vertices carry; not the presets'). Their metrics are
the evaluation's (``delta.eval.evaluate.evaluate``, which ``delta evaluate`` runs; ``short-base``'s and
``short-tied-training``'s called it from a script) at 2 frames a split (30 refinement steps, supersample 2,
no ST-LPIPS); the first three
ran one at a time except ``short-tied-training``'s stage 1, which ran beside an evaluation. The rows ending
``-six-unrefined`` score ``short-base``'s and ``short-head-carries-none``'s models on 6 held-out frames unrefined.

    python benchmarks/torso_hold.py --truth data/synthetic/talker-short/gt/params.npz \\
        --record results/synthetic/talker-short/frames.h5 --body resources/body/anny_sub1_face.npz \\
        --run limbs=/work/exp/talker-short-base --metrics limbs=/work/exp/talker-short-base/eval2/metrics.csv \\
        --run torso=/work/exp/talker-short-torso --out benchmarks/torso_hold.csv
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402

NECK = ("neck01", "neck02", "neck03", "head")
SCORES = ("psnr", "ssim", "stlpips_alex", "psnr_face", "psnr_clothing", "psnr_hair", "psnr_head")


def neck_yaw(poses: np.ndarray, names: list[str]) -> np.ndarray:
    """(F,) degrees: the turn about the vertical of the neck's chain composed (its joints' local rotations)."""
    turn = Rotation.identity(len(poses))
    for name in NECK:
        turn = turn * Rotation.from_rotvec(poses[:, names.index(name)])
    return turn.as_euler("YXZ", degrees=True)[:, 0]


def fit_rows(folder: Path, truth: Path) -> dict[str, float]:
    with np.load(folder / "init" / "params.npz") as p, np.load(truth) as g:
        names, ids = [str(n) for n in p["joint_names"]], p["frame_ids"]
        poses, transl, face = p["poses"], p["transl"], p["face_residual_px"]
        true = g["poses"][ids]
    root = Rotation.from_rotvec(poses[:, 0])
    about_mean = np.degrees((root.inv() * Rotation.from_rotvec(poses[:, 0].mean(0))).magnitude())
    fitted, wanted = neck_yaw(poses, names), neck_yaw(true, names)
    residual = pd.read_csv(folder / "init" / "report.csv")["residual_px"]
    summary_path = folder / "init" / "summary.json"  # the command's summary (absent where run() ran alone)
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    out = {"root_turn_mean_deg": about_mean.mean(), "root_turn_max_deg": about_mean.max(),
           "neck_yaw_corr": np.corrcoef(fitted, wanted)[0, 1], "neck_yaw_max_err_deg": np.abs(fitted - wanted).max(),
           "keypoint_residual_mean_px": residual.mean(), "keypoint_residual_max_px": residual.max(),
           "face_residual_median_px": float(np.median(face)),
           "hold": summary.get("static_hold", {}).get("holds", "")}  # fmt: skip
    out |= {f"transl_std_{axis}_mm": 1000 * s for axis, s in zip("xyz", transl.std(0))}
    return out


def shoulder_rows(folder: Path, record: Path, body: Path) -> dict[str, float]:
    """The final fit's neck and shoulder keypoints (body, expressions, place as written) against the
    record's: pixels, mean over the three, then mean and largest over the frames, and the frames beyond 10 px."""
    import torch

    from delta.body.keypoints import openpose18_map
    from delta.body.lbs import lbs
    from delta.body.model import load_body_model
    from delta.data.record import FrameRecord

    model = load_body_model(body, dtype=torch.float64)
    with FrameRecord(record) as rec:
        detected, camera = torch.from_numpy(rec.h5["keypoints"][:]).double(), rec.camera(0)
    with np.load(folder / "init" / "params.npz") as p, torch.no_grad():
        F = len(p["poses"])
        out = lbs(model, torch.from_numpy(p["betas"])[None].expand(F, -1), torch.from_numpy(p["poses"]),
                  torch.from_numpy(p["expression"]), transl=torch.from_numpy(p["transl"]))  # fmt: skip
        uv = camera.project(openpose18_map(model)(out.joints, out.vertices))[0]
    err = (uv - detected[..., :2]).norm(dim=-1)[:, [1, 2, 5]].mean(1).numpy()
    return {
        "shoulders_mean_px": err.mean(),
        "shoulders_max_px": err.max(),
        "shoulders_frames_over_10px": int((err > 10).sum()),
    }


def training_rows(folder: Path) -> dict[str, float]:
    """Each finished stage's training-ray PSNR over its last 5 % of steps, its steps and seconds."""
    out = {}
    for stage in (1, 2):
        if not (folder / f"stage{stage}" / "model.pt").is_file():
            continue
        losses = pd.read_csv(folder / f"stage{stage}" / "losses.csv")
        tail = max(5, len(losses) // 20)
        out[f"stage{stage}_train_psnr"] = losses["psnr"].iloc[-tail:].mean()
        out[f"stage{stage}_steps"] = len(losses)
        out[f"stage{stage}_seconds"] = losses["seconds"].iloc[-1]
    return out


def score_rows(metrics: Path) -> dict[str, float]:
    table, out = pd.read_csv(metrics), {}
    for (split, refined), group in table.groupby(["split", "refined"]):
        for key in SCORES:
            if key in group:
                out[f"{split}_{'refined' if refined else 'unrefined'}_{key}"] = group[key].mean()
        out[f"{split}_frames"] = len(group)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--truth", required=True, help="the generator's params.npz")
    ap.add_argument("--record", required=True, help="the subject's frames.h5")
    ap.add_argument("--body", required=True, help="the body model with expressions")
    ap.add_argument("--run", action="append", required=True, help="LABEL=FOLDER, a subject's results folder")
    ap.add_argument("--metrics", action="append", default=[], help="LABEL=CSV, the run's evaluation")
    ap.add_argument("--out", required=True)
    ap.add_argument("--append", action="store_true")
    args = ap.parse_args()
    metrics = dict(item.partition("=")[::2] for item in args.metrics)
    rows = []
    for item in args.run:
        label, _, folder = item.partition("=")
        row = {"run": label} | fit_rows(Path(folder), Path(args.truth))
        row |= shoulder_rows(Path(folder), Path(args.record), Path(args.body)) | training_rows(Path(folder))
        if label in metrics:
            row |= score_rows(Path(metrics[label]))
        rows.append(row)
    table = save_table(pd.DataFrame(rows), args.out, args.append)
    print(table.T.to_string())


if __name__ == "__main__":
    main()
