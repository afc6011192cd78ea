"""Quality and speed of the preprocessing models on the synthetic captures, against ground truth.

For each subject under data/synthetic/ (made by `snakemake --cores 2`): person-mask
IoU and OpenPose-18 keypoint error (pixels, on keypoints visible in the ground truth)
of the offline default (MediaPipe pose landmarks in ONNX), clothing / skin / hair IoU
of the default parser, clothing-mask IoU of a U²-Net cloth export when one is given,
and frames per second of each.

    python benchmarks/preprocess_quality.py --out benchmarks/preprocess_quality.csv [--cloth u2net_cloth_seg.onnx]

``--data`` may be given more than once (the People Snapshot stand-ins live under the workflow's
``data/synthetic`` as well); ``--label`` names the code measured in a ``label`` column (say a commit),
and ``--append`` adds the rows to an existing CSV, so two versions of the parser sit side by side.
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import cv2
import h5py
import numpy as np
import pandas as pd

from delta.data.sources import synthetic_source
from delta.preprocess.frames import prepare
from delta.preprocess.onnx_models import ClothSegmentation, clothing_mask
from delta.preprocess.parsing_default import VideoParser
from delta.preprocess.pose_landmarks import PoseLandmarker


def frames(video: Path):
    cap = cv2.VideoCapture(str(video))
    while True:
        ok, f = cap.read()
        if not ok:
            return
        yield cv2.cvtColor(f, cv2.COLOR_BGR2RGB)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data", nargs="+", default=["data/synthetic"])
    parser.add_argument("--label", default="", help="what was measured (e.g. a commit), a column of every row")
    parser.add_argument("--append", action="store_true", help="add the rows to --out instead of replacing it")
    parser.add_argument("--pose-model", default="resources/models/mediapipe/pose_landmark_full.onnx")
    parser.add_argument("--cloth", help="a u2net_cloth_seg.onnx export, if you have one")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", default="benchmarks/preprocess_quality.csv")
    args = parser.parse_args()
    rows = []
    captures = sorted(p for d in args.data for p in Path(d).iterdir() if (p / "gt" / "frames.h5").is_file())
    for capture in captures:
        name = capture.name
        pose = PoseLandmarker(args.pose_model, threads=args.threads)
        parser = VideoParser()
        cloth = ClothSegmentation(args.cloth, threads=args.threads) if args.cloth else None
        ious, errs, cloth_ious, t_pose, t_cloth, t_parse = [], [], [], 0.0, 0.0, 0.0
        parts = {"clothing": [], "skin": [], "hair": []}
        with h5py.File(capture / "gt" / "frames.h5") as gt:
            for i, rgb in enumerate(frames(capture / f"{name}.mp4")):
                t0 = time.perf_counter()
                r = pose(rgb)
                t_pose += time.perf_counter() - t0
                ious.append(iou(r.mask > 0.5, gt["person"][i] > 0))
                kp, gk = r.openpose18(), gt["keypoints"][i]
                seen = (gk[:, 2] == 1) & (kp[:, 2] > 0.5)
                errs += np.linalg.norm(kp[seen, :2] - gk[seen, :2], axis=1).tolist()
                t0 = time.perf_counter()
                masks = parser(rgb, r.mask, r)
                t_parse += time.perf_counter() - t0
                for part, scores in parts.items():
                    if gt[part][i].sum() > 50:
                        scores.append(iou(masks[part] > 0, gt[part][i] > 0))
                if cloth is not None:
                    t0 = time.perf_counter()
                    cloth_ious.append(iou(clothing_mask(cloth(rgb)), gt["clothing"][i] > 0))
                    t_cloth += time.perf_counter() - t0
            n, res = len(ious), gt["person"].shape[1]
        with tempfile.TemporaryDirectory() as tmp:  # frame extraction: decode, crop, resize, write
            t0 = time.perf_counter()
            prepare(synthetic_source(capture, name), Path(tmp) / "frames.h5", 512)
            t_prepare = time.perf_counter() - t0
        rows.append(dict(label=args.label, subject=name, frames=n, resolution=res, person_iou_mean=np.mean(ious),
                         person_iou_min=np.min(ious), keypoint_err_px_mean=np.mean(errs),
                         keypoint_err_px_median=np.median(errs), pose_fps=n / t_pose,
                         default_clothing_iou=np.mean(parts["clothing"]), default_skin_iou=np.mean(parts["skin"]),
                         default_hair_iou=np.mean(parts["hair"]) if parts["hair"] else np.nan,
                         default_parser_fps=n / t_parse, prepare_frames_fps=n / t_prepare,
                         clothing_iou_mean=np.mean(cloth_ious) if cloth_ious else np.nan,
                         cloth_fps=n / t_cloth if t_cloth else np.nan, threads=args.threads,
                         peak_rss_mb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)))  # fmt: skip
        print(rows[-1], flush=True)
    table = pd.DataFrame(rows)
    if args.append and Path(args.out).is_file():
        table = pd.concat([pd.read_csv(args.out), table], ignore_index=True)
    table.to_csv(args.out, index=False)


if __name__ == "__main__":
    main()
