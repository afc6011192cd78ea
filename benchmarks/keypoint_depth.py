"""What the body landmarker's depths give the init fit of a synthetic capture, against its truth.

The workflow's keypoint step is run on the capture's video for the record's frames (MediaPipe's body
landmarker: its metric landmarks' depths, ``keypoint_depth``); a copy of the record gets them beside the
shipped keypoints, the init fit runs on it with the given settings, and ``init_fit_depth.py`` scores the fit
per frame (rows labelled ``--fit``). Also written: how often the detector's depth order of each of the fit's
bones (``fitting.fit.DEPTH_BONES``) agrees with the truth's, per split, for bones whose true extent along
the viewing axis exceeds 10 cm; with ``--pairs``, the same for the bones across the torso (shoulder to
shoulder, hip to hip) where the detector's difference exceeds a margin, the fit's rule (``--no-fit``: these
tables alone).

    PYTHONPATH=$PWD python3 benchmarks/keypoint_depth.py --subject tight --record results/synthetic/tight/frames.h5 \\
        --video data/synthetic/tight/tight.mp4 --gt data/synthetic/tight/gt --body resources/body/anny_sub1.npz \\
        --model resources/models/mediapipe/pose_landmark_full.onnx --settings '[{"static_weight": 10}, {}]' \\
        --work /tmp/kd --csv benchmarks/init_fit_depth.csv --signs benchmarks/keypoint_depth_signs.csv --append
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import h5py
import numpy as np
import pandas as pd

from delta.cli import main as delta_main
from delta.fitting.fit import DEPTH_BONES
from delta.preprocess.steps import run_keypoints

sys.path.insert(0, str(Path(__file__).resolve().parent))
import init_fit_depth  # noqa: E402
from table import save_table  # noqa: E402


def camera_depths(keypoints3d: np.ndarray, gt) -> np.ndarray:
    """(F, K) true depths along the viewing axis of (F, K, 3) world keypoints."""
    if str(gt["camera_model"]) == "pinhole":
        return (keypoints3d @ gt["R"].T + gt["t"])[..., 2]
    return -keypoints3d[..., 2]  # the orthographic camera looks down -z


#: OpenPose-18's bones across the torso
PAIRS = {"shoulders": (2, 5), "hips": (8, 11)}


def pair_agreement(depth: np.ndarray, keypoints3d: np.ndarray, gt, ids: np.ndarray, subject: str,
                   margins=(0.03, 0.05, 0.08)) -> pd.DataFrame:  # fmt: skip
    """Per pair across the torso and margin: the frames whose detected depth difference exceeds the margin,
    the share of them on the truth's side, and the largest true difference among those on the wrong side."""
    true, rows = camera_depths(keypoints3d, gt), []
    for name, (a, b) in PAIRS.items():
        dt, dd = true[:, b] - true[:, a], depth[:, b] - depth[:, a]
        for margin in margins:
            m = np.isfinite(dd) & (np.abs(dd) > margin)
            wrong = m & (np.sign(dd) != np.sign(dt))
            rows.append({"subject": subject, "pair": name, "margin_m": margin, "frames": int(m.sum()),
                         "same_side": float(1 - wrong.sum() / max(m.sum(), 1)),
                         "wrong_frames": " ".join(str(i) for i in ids[wrong]),
                         "wrong_max_true_m": float(np.abs(dt[wrong]).max()) if wrong.any() else 0.0})  # fmt: skip
    return pd.DataFrame(rows)


def sign_agreement(depth: np.ndarray, keypoints3d: np.ndarray, gt, split: np.ndarray, subject: str) -> pd.DataFrame:
    """Per split: the share of bones longer than 10 cm along the viewing axis whose detected depth difference has
    the truth's sign (and their correlation), of (F, 18) detected depths and (F, 18, 3) true keypoints (world);
    over every bone, the detected differences' least-squares scale to the true ones and the residual's spread."""
    true = camera_depths(keypoints3d, gt)
    bones = np.array(DEPTH_BONES)
    dt = true[:, bones[:, 1]] - true[:, bones[:, 0]]
    dd = depth[:, bones[:, 1]] - depth[:, bones[:, 0]]
    long = np.abs(dt) > 0.1
    rows = []
    for name, code in (("capture", [0, 1]), ("test_pose", [2])):
        m = long & np.isin(split, code)[:, None]
        agree = np.sign(dt[m]) == np.sign(dd[m])
        every = np.isin(split, code)[:, None] & np.isfinite(dd)
        scale = float((dd[every] * dt[every]).sum() / (dt[every] ** 2).sum())  # detected ~ scale x true
        rows.append({"subject": subject, "frames": "capture (train, test_view)" if code != [2] else "held-out poses",
                     "bones": int(m.sum()), "same_side": float(agree.mean()),
                     "correlation": float(np.corrcoef(dt[m], dd[m])[0, 1]), "scale": scale,
                     "residual_m": float(np.std(dd[every] - scale * dt[every]))})  # fmt: skip
    return pd.DataFrame(rows)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    for name in ("--subject", "--record", "--video", "--gt", "--body", "--model", "--work", "--csv", "--signs"):
        ap.add_argument(name, required=True)
    ap.add_argument("--settings", default="{}", help="the init fit's settings (JSON), as the workflow passes them")
    ap.add_argument("--fit", default="with keypoint depths", help="the rows' fit column")
    ap.add_argument("--pairs", default=None, help="a CSV for the bones across the torso")
    ap.add_argument("--no-fit", action="store_true", help="the detector's tables only")
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args(argv)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    with h5py.File(a.record) as rec:
        ids, split = rec["frame_ids"][:], rec["split"][:]
    steps = work / "keypoints.h5"
    run_keypoints(Path(a.video), set(ids.tolist()), "mediapipe", a.model, steps, threads=2)
    record = work / "frames.h5"
    shutil.copy(a.record, record)
    with h5py.File(steps) as f, h5py.File(record, "a") as rec:
        depth = f["keypoint_depth"][:][ids]
        if "keypoint_depth" in rec:
            del rec["keypoint_depth"]
        rec.create_dataset("keypoint_depth", data=depth)
    gt = np.load(Path(a.gt) / "params.npz")
    with h5py.File(Path(a.gt) / "frames.h5") as f:
        truth = f["keypoints3d"][:][ids]
    signs = sign_agreement(depth, truth, gt, split, a.subject)
    print(signs.round(3).to_string(index=False))
    save_table(signs, a.signs, a.append)
    if a.pairs:
        pairs = pair_agreement(depth, truth, gt, ids, a.subject)
        print(pairs.round(3).to_string(index=False))
        save_table(pairs, a.pairs, a.append)
    if a.no_fit:
        return
    out = work / "init"
    if delta_main(["fit-init", "--record", str(record), "--body", a.body, "--out", str(out),
                   "--settings", a.settings, "--threads", "2"]) != 0:  # fmt: skip
        raise SystemExit("the init fit failed")
    init_fit_depth.main(["--params", str(out / "params.npz"), "--gt", a.gt, "--body", a.body, "--subject", a.subject,
                         "--fit", a.fit, "--csv", a.csv] + ["--append"] * a.append)  # fmt: skip
    print(json.dumps(json.loads((out / "summary.json").read_text())["residual_px_mean"]))


if __name__ == "__main__":
    main()
