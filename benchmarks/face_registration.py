"""How far a head avatar's rendered face lies from the frame's, in pixels, and how much that blurs it.

A face rendered from many frames is their consensus: where a frame's pose and expression put the mesh a
few pixels off, its eyes and lips land on other vertices than in the next frame, and the albedo learns
their average. This script measures that per frame. MediaPipe's face mesh (the workflow's own ONNX model)
is run on the frame and on the avatar's render of it, both cut by the same crop (the frame's stored face
points give it), and the two sets of 468 points are compared by part of the face (eyes, brows, lips, nose,
outline). With the same crop and the same model, what the detector gets wrong it gets wrong alike in
both, so the difference is where the render's features lie against the frame's.

Beside it: the face's PSNR (inside the outline of the frame's face points) and how sharp the render is
there against the frame (the variance of the Laplacian, render over frame: 1 is as sharp). With
``--alone STEPS`` each frame's albedo is also trained on that frame alone (everything else frozen, with a
free per-vertex detail; ``benchmarks/vertex_detail.py``'s training) and scored the same way: the face
that frame's registration allows when no other frame has to agree with it. Run from the repository root::

    PYTHONPATH=$PWD python3 benchmarks/face_registration.py --model results/real/head_shorthair/stage2/model.pt \\
        --record results/real/head_shorthair/frames.h5 --body resources/body/anny_sub1_face.npz \\
        --subject head_shorthair --frames 4 --alone 200 --csv benchmarks/face_registration.csv
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import h5py
import numpy as np
import pandas as pd
import torch

from delta.data import SPLITS
from delta.models.image import render_image
from delta.preprocess.face_tracking import EYE_CORNERS, FaceTracker, crop_from_points, eye_angle
from delta.training.run import load_trained

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import model_arguments, save_table  # noqa: E402
from vertex_detail import train_albedo  # noqa: E402

#: MediaPipe face-mesh points by part of the face (the face mesh's own contours)
PARTS = {
    "eyes": (33, 7, 163, 144, 145, 153, 154, 155, 133, 246, 161, 160, 159, 158, 157, 173,
             263, 249, 390, 373, 374, 380, 381, 382, 362, 466, 388, 387, 386, 385, 384, 398),
    "brows": (46, 53, 52, 65, 55, 70, 63, 105, 66, 107, 276, 283, 282, 295, 285, 300, 293, 334, 296, 336),
    "lips": (61, 146, 91, 181, 84, 17, 314, 405, 321, 375, 291, 185, 40, 39, 37, 0, 267, 269, 270, 409,
             78, 95, 88, 178, 87, 14, 317, 402, 318, 324, 308, 191, 80, 81, 82, 13, 312, 311, 310, 415),
    "nose": (1, 2, 4, 5, 6, 19, 45, 48, 64, 94, 97, 98, 115, 168, 195, 197, 220, 275, 278, 294, 326, 327, 344, 440),
    "outline": (10, 338, 297, 332, 284, 251, 389, 356, 454, 323, 361, 288, 397, 365, 379, 378, 400, 377, 152,
                148, 176, 149, 150, 136, 172, 58, 132, 93, 234, 127, 162, 21, 54, 103, 67, 109),
}  # fmt: skip


def face_mask(points: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W) bool inside the outline of (468, 2) face points (pixel centres at +0.5)."""
    hull = cv2.convexHull(np.round(points[list(PARTS["outline"])] - 0.5).astype(np.int32))
    mask = np.zeros((height, width), np.uint8)
    cv2.fillConvexPoly(mask, hull, 1)
    return mask.astype(bool)


def compare(tracker: FaceTracker, truth: np.ndarray, render: np.ndarray, stored: np.ndarray) -> dict:
    """Part-by-part distances (px) between the face points found on ``truth`` and on ``render`` (H, W, 3
    uint8, one crop from the ``stored`` (468, 2) points), the face's PSNR and sharpness ratio."""
    crop = crop_from_points(stored, eye_angle(stored[EYE_CORNERS[0]], stored[EYE_CORNERS[1]]))
    found_truth, p_truth = tracker.landmarks(truth, crop)
    found_render, p_render = tracker.landmarks(render, crop)
    dist = np.linalg.norm(found_render - found_truth, axis=1)
    row = {f"{part}_px": float(np.median(dist[list(ids)])) for part, ids in PARTS.items()}
    row |= {
        "all_px": float(np.median(dist)),
        "presence_render": round(p_render, 3),
        "presence_truth": round(p_truth, 3),
    }
    mask = face_mask(found_truth, *truth.shape[:2])
    a, b = truth.astype(np.float64) / 255, render.astype(np.float64) / 255
    mse = float(((a - b)[mask] ** 2).mean())
    row["face_psnr"] = 10 * np.log10(1 / max(mse, 1e-12))
    lap = [cv2.Laplacian(cv2.cvtColor(x, cv2.COLOR_RGB2GRAY), cv2.CV_64F)[mask].var() for x in (render, truth)]
    row["sharpness_ratio"] = float(lap[0] / max(lap[1], 1e-12))
    return row


def rendered(model, frame: int) -> np.ndarray:
    with torch.no_grad():
        rgb = render_image(model, frame)["rgb"].clamp(0, 1).cpu().numpy()
    return (rgb * 255 + 0.5).astype(np.uint8)


def main() -> None:
    ap = model_arguments(argparse.ArgumentParser(description=__doc__.split("\n\n")[0]))
    ap.add_argument("--splits", nargs="+", default=["train", "test_view"])
    ap.add_argument("--frames", type=int, default=4, help="frames a split, evenly spaced")
    ap.add_argument("--alone", type=int, default=0, help="also train each frame's albedo alone this many steps")
    ap.add_argument("--models-dir", type=Path, default=Path("resources/models/mediapipe"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--csv", type=Path, default=Path("benchmarks/face_registration.csv"))
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    tracker = FaceTracker(a.models_dir / "face_detection_short_range.onnx", a.models_dir / "face_landmark.onnx")
    with h5py.File(a.record, "r") as f:
        stored, split = np.asarray(f["face_landmarks"])[..., :2], np.asarray(f["split"])
    trained = load_trained(a.model, a.record, a.body)
    state = {k: v.clone() for k, v in trained.model.state_dict().items()}
    rows = []
    for name in a.splits:
        idx = np.flatnonzero(split == SPLITS.index(name))
        for frame in idx[np.linspace(0, len(idx) - 1, min(a.frames, len(idx))).round().astype(int)]:
            frame = int(frame)
            truth = trained.data.images.bytes[frame].numpy()
            variants = [("avatar", 0)] + ([("albedo alone", a.alone)] if a.alone else [])
            for variant, steps in variants:
                if steps:
                    train_albedo(trained, steps, 4096, 5e-3, detail=True, frames=[frame])
                row = {"subject": a.subject, "split": name, "frame": frame, "variant": variant, "steps": steps}
                row |= compare(tracker, truth, rendered(trained.model, frame), stored[frame])
                rows.append(row)
                print({k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
                trained.model.albedo_field.detail = None
                trained.model.load_state_dict(state)
    table = pd.DataFrame(rows)
    table["machine"] = f"cpu ({torch.get_num_threads()} threads)"
    save_table(table, a.csv, a.append)
    print(table.groupby(["split", "variant"]).mean(numeric_only=True).round(3).to_string())


if __name__ == "__main__":
    main()
