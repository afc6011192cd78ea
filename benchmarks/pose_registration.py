"""How far training registers the capture's frames: each trained model's per-frame root turn against the truth.

A trained stage keeps a pose per training frame, started at the init fit's and refined with the model. The
fit's root turn wanders about the truth's from frame to frame (a turning subject's heading a degree or
two either way), and a frame drawn with the wrong heading smears what its pixels teach the canonical
model along the turn. Per model (and the init fit itself) over a synthetic subject's training frames:
the root's rotation relative to the truth's (fit · truth⁻¹), its mean over the frames (a constant offset
the body's own frame may carry) and each frame's deviation from that mean — the part training could
register — as the mean angle, the spread about the vertical axis (yaw) and across it; and how far the
model's poses moved from the init fit's (root and all joints, mean over frames, in degrees).

    PYTHONPATH=$PWD python3 benchmarks/pose_registration.py --truth data/synthetic/loose/gt \\
        --init results/synthetic/loose/init/params.npz --subject loose \\
        --models "fast=results/synthetic/loose/stage2/model.pt" --csv benchmarks/pose_registration.csv
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402


def root_deviation(poses: np.ndarray, truth: np.ndarray) -> dict:
    """(F, J, 3) axis-angle poses against the truth's: the constant offset of the root's rotation and each
    frame's deviation from it (degrees; yaw about the vertical y axis, tilt across it)."""
    fit, true = Rotation.from_rotvec(poses[:, 0]), Rotation.from_rotvec(truth[:, 0])
    offset = (fit * true.inv()).mean()
    dev = (offset.inv() * fit * true.inv()).as_rotvec() * 180 / np.pi  # (F, 3) in the world's axes
    return {"root_offset_deg": float(offset.magnitude() * 180 / np.pi),
            "root_dev_mean_deg": float(np.linalg.norm(dev, axis=1).mean()),
            "root_dev_yaw_std_deg": float(dev[:, 1].std()),
            "root_dev_tilt_std_deg": float(np.linalg.norm(dev[:, [0, 2]] - dev[:, [0, 2]].mean(0), axis=1).std())}  # fmt: skip


def moved(poses: np.ndarray, start: np.ndarray) -> dict:
    """How far (F, J, 3) poses lie from the init fit's: the root's and every joint's angle, mean over frames."""
    turn = Rotation.from_rotvec(poses.reshape(-1, 3)) * Rotation.from_rotvec(start.reshape(-1, 3)).inv()
    deg = (turn.magnitude() * 180 / np.pi).reshape(poses.shape[:2])
    return {"root_moved_deg": float(deg[:, 0].mean()), "joints_moved_deg": float(deg[:, 1:].mean())}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--truth", required=True, type=Path, help="the subject's gt folder (params.npz, splits.json)")
    p.add_argument("--init", required=True, type=Path, help="the init fit's params.npz")
    p.add_argument("--subject", required=True)
    p.add_argument("--models", nargs="*", default=[], help="label=model.pt of trained stages")
    p.add_argument("--csv", required=True, type=Path)
    p.add_argument("--append", action="store_true")
    a = p.parse_args(argv)
    truth = np.load(a.truth / "params.npz")["poses"]
    train = json.loads((a.truth / "splits.json").read_text())["train"]
    start = np.load(a.init)["poses"]
    rows = []
    for label, poses in [("init fit", start)] + [
        (lbl, torch.load(path, map_location="cpu", weights_only=True)["model"]["poses"].numpy())
        for lbl, path in (m.split("=", 1) for m in a.models)
    ]:
        rows.append({"subject": a.subject, "variant": label, "frames": len(train),
                     **root_deviation(poses[train], truth[train]), **moved(poses[train], start[train])})  # fmt: skip
        print({k: round(v, 3) if isinstance(v, float) else v for k, v in rows[-1].items()})
    save_table(pd.DataFrame(rows).round(4), a.csv, a.append)


if __name__ == "__main__":
    main()
