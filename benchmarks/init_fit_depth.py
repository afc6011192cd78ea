"""How far the init fit's body is from the truth on each split of a synthetic capture, and along which axis.

The held-out poses are fitted free (``static_weight`` holds only the capture's own turn), from keypoints and
masks alone. This scores the workflow's fit (``results/{dataset}/{subject}/init/params.npz``) against the
generator's body parameters on the same body model: per frame, the body's mean vertex error after centroid
alignment, and the joint furthest from its true place (relative to the root) with the part of that error
along the camera's viewing axis: a limb swung toward the camera and one swung away from it project alike.

    PYTHONPATH=$PWD python3 benchmarks/init_fit_depth.py --params results/synthetic/tight/init/params.npz \\
        --gt data/synthetic/tight/gt --body resources/body/anny_sub1.npz --subject tight \\
        --csv benchmarks/init_fit_depth.csv
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from delta.body.lbs import lbs
from delta.body.model import load_body_model
from delta.data.record import FrameRecord
from delta.geometry.sight import visible_vertices

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402

LIMBS = ("upperarm01", "lowerarm01", "upperleg01", "lowerleg01", "foot", "head")
"""Joints whose place the rows report (both sides): the ends of the limbs' first bones, and the head."""


def posed(model, params, frames: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """(F, V, 3) vertices and (F, J, 3) joints of ``params`` (betas, poses, transl) at ``frames``."""
    betas = torch.from_numpy(params["betas"]).double()[None].expand(len(frames), -1)
    out = lbs(model, betas, torch.from_numpy(params["poses"][frames]).double(),
              transl=torch.from_numpy(params["transl"][frames]).double())  # fmt: skip
    return out.vertices, out.joints


def viewing_axis(gt, frame: int) -> torch.Tensor:
    """(3,) the camera's viewing axis in the world (a pinhole's third row of R; +z for the orthographic)."""
    if str(gt["camera_model"]) == "pinhole":
        return torch.from_numpy(gt["R"]).double()[2]
    return torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def seen_errors(model, fitted: torch.Tensor, true: torch.Tensor, record: str) -> np.ndarray:
    """(F,) mean error (mm) of the vertices of each frame's fitted body (F, V, 3) that the record's pinhole
    camera sees, against the same vertices of the true body, both centred on those vertices' centroid."""
    with FrameRecord(record) as rec:
        if rec.h5.attrs["camera_model"] != "pinhole":
            raise SystemExit(f"{record}: --record takes a pinhole capture (its camera is the fit's)")
        camera = rec.camera(0)
    out = []
    for fit_v, true_v in zip(fitted, true):
        seen = visible_vertices(fit_v, model.faces, camera)
        a, b = fit_v[seen], true_v[seen]
        out.append(1000 * float(((a - a.mean(0)) - (b - b.mean(0))).norm(dim=-1).mean()) if len(a) else np.nan)
    return np.array(out)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--params", required=True, help="the init fit's params.npz")
    ap.add_argument("--gt", required=True, help="the capture's gt/ folder (params.npz, splits.json)")
    ap.add_argument("--body", required=True)
    ap.add_argument("--subject", required=True)
    ap.add_argument("--fit", default="from rest", help="what the rows' fit is, for the CSV's fit column")
    ap.add_argument("--csv", required=True)
    ap.add_argument("--append", action="store_true")
    ap.add_argument("--record", help="the capture's frames.h5 (pinhole): adds the seen part's error")
    a = ap.parse_args(argv)
    torch.set_num_threads(2)
    model = load_body_model(a.body, dtype=torch.float64)
    gt, fit = np.load(Path(a.gt) / "params.npz"), np.load(a.params)
    if list(gt["joint_names"]) != list(fit["joint_names"]):
        raise SystemExit(f"{a.params}: its joints are not the truth's ({Path(a.gt) / 'params.npz'})")
    splits = json.loads((Path(a.gt) / "splits.json").read_text())
    frames = np.arange(len(fit["poses"]))
    gv, gj = posed(model, gt, frames)
    fv, fj = posed(model, fit, frames)
    centred = lambda v: v - v.mean(1, keepdim=True)  # noqa: E731
    body = 1000 * (centred(fv) - centred(gv)).norm(dim=-1).mean(1)
    joint_err = (fj - fj[:, :1]) - (gj - gj[:, :1])  # relative to the root
    names = [str(n) for n in gt["joint_names"]]
    limbs = [j for j, n in enumerate(names) if n.split(".")[0] in LIMBS]
    split_of = {int(f): s for s, ids in splits.items() for f in ids}
    seen_err = seen_errors(model, fv, gv, a.record) if a.record else np.full(len(frames), np.nan)
    rows = []
    for f in frames:
        err = joint_err[f, limbs].norm(dim=-1)
        j = limbs[int(err.argmax())]
        depth = float((joint_err[f, j] @ viewing_axis(gt, int(f))).abs())
        rows.append({"subject": a.subject, "fit": a.fit, "frame": int(f), "split": split_of.get(int(f), "?"),
                     "body_err_mm": float(body[f]), "worst_joint": names[j],
                     "worst_joint_err_mm": 1000 * float(joint_err[f, j].norm()), "worst_joint_depth_mm": 1000 * depth,
                     "seen_body_err_mm": float(seen_err[f])})  # fmt: skip
    df = pd.DataFrame(rows)
    summary = df.groupby("split").agg(frames=("frame", "size"), body_err_mm=("body_err_mm", "mean"),
                                      body_err_median_mm=("body_err_mm", "median"), worst_joint_mm=("worst_joint_err_mm", "mean"),
                                      seen_body_err_mm=("seen_body_err_mm", "mean"),
                                      seen_body_err_median_mm=("seen_body_err_mm", "median"),
                                      depth_share=("worst_joint_depth_mm", "sum"))  # fmt: skip
    summary["depth_share"] /= df.groupby("split")["worst_joint_err_mm"].sum()
    print(summary.round(3).to_string())
    print(df[df.split == "test_pose"].sort_values("body_err_mm").tail(8).round(1).to_string(index=False))
    save_table(df, a.csv, a.append)


if __name__ == "__main__":
    main()
