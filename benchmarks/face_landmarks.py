"""How well MediaPipe's face-mesh landmarks are placed on the body mesh, and how the face tracker and the
close-up mask fare on real clips.

Synthetic rows (``case = held_out_view``): the body rendered as the calibration renders it, from views
and shapes the calibration never saw, with the mouth closed and opened (``--jaw``: ``jawOpen`` amounts;
the calibration's faces are closed); the tracker's points against the embedded points of the rendered
mesh projected (median and 90th percentile, pixels and share of the face's width), and the inner lips'
centres alone (landmarks 13 upper, 14 lower: ``upper_lip_px``, ``lower_lip_px``) against the opening the
tracker sees between them (``opening_px``). One ``case = jaw_motion`` row: how far the embedded inner-lip
centres and the lower lip's outer centre (17) move with the jaw fully open (mm): a lower inner-lip point
placed on the upper lip does not follow the jaw. Init-fit rows (``case = init_fit``, ``--fit``): a real
clip's init fit against its record's detected face points, the median residual (px) by part of the
face, and the fitted ``jawOpen`` / ``mouthClose`` (median over the clip, and over its held-out frames).
Real rows
(``case = real_clip``): every frame of each clip tracked from the start, the share of frames with a face,
the frames that began without a tracked face (detected afresh), milliseconds a frame for the tracker and for the GrabCut mask.

    python benchmarks/face_landmarks.py --body resources/body/anny_sub1_face.npz \
        --embedding resources/body/anny_sub1_face_landmarks.npz --models resources/models/mediapipe \
        --real ../shared/real --out benchmarks/face_landmarks.csv
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from delta.body.face_points import LandmarkEmbedding
from delta.body.lbs import lbs
from delta.body.model import load_body_model
from delta.data.record import FrameRecord
from delta.data.video import iter_video
from delta.preprocess.face_tracking import INNER_LIP_CONTOUR, FaceTracker, head_mask
from delta.synthetic.landmark_embedding import View, render_head

HELD_OUT = ((-25, 0), (-12, 6), (0, -12), (8, 10), (18, -4), (30, 0))


#: MediaPipe's inner lips' centres (upper, lower) and the lower lip's outer centre
UPPER_INNER, LOWER_INNER, LOWER_OUTER = 13, 14, 17


def jaw(body, amount: float) -> torch.Tensor | None:
    """(E,) ``jawOpen`` at ``amount``; None for a closed mouth or a body model without the action."""
    if not amount or "jawOpen" not in body.expression_names:
        return None
    e = torch.zeros(body.num_expression, dtype=torch.float64)
    e[body.expression_names.index("jawOpen")] = amount
    return e


def held_out(body, embedding, tracker, seeds: int, resolution: int, jaws=(0.0,)) -> list[dict]:
    rows = []
    kept = list(embedding.landmarks)
    for seed in range(seeds):
        rng = np.random.default_rng(100 + seed)
        betas = torch.from_numpy(rng.normal(0, 0.7, body.num_shape))
        for (yaw, pitch), amount in ((v, a) for v in HELD_OUT for a in jaws):
            shot = render_head(body, View(betas, yaw, pitch), resolution, jaw(body, amount),
                               skin=tuple(rng.uniform(0.35, 0.9, 3)), background=tuple(rng.uniform(0.2, 0.9, 3)),
                               seed=seed + 10)  # fmt: skip
            tracker.reset()
            found = tracker(shot.image)
            row = dict(case="held_out_view", shape_seed=seed, yaw_deg=yaw, pitch_deg=pitch, jaw_open=amount,
                       face_width_px=round(shot.face_width_px, 1), found=bool(found[0, 2] > 0.5))  # fmt: skip
            if row["found"]:
                uv = shot.camera.project(embedding.points(torch.from_numpy(shot.vertices)[None])[0])[0].numpy()
                gap = np.linalg.norm(uv - found[embedding.landmarks, :2], axis=1)
                row.update(median_px=round(float(np.median(gap)), 2), p90_px=round(float(np.percentile(gap, 90)), 2),
                           median_share_of_face=round(float(np.median(gap)) / shot.face_width_px, 4))  # fmt: skip
                if {UPPER_INNER, LOWER_INNER} <= set(kept):
                    row.update(opening_px=round(float(np.linalg.norm(found[UPPER_INNER, :2] - found[LOWER_INNER, :2])), 2),
                               upper_lip_px=round(float(gap[kept.index(UPPER_INNER)]), 2),
                               lower_lip_px=round(float(gap[kept.index(LOWER_INNER)]), 2))  # fmt: skip
            rows.append(row)
    return rows


def jaw_motion(body, embedding) -> dict:
    """How far (mm) the embedded inner lips' centres and the lower lip's outer centre move with the jaw open."""
    opened = jaw(body, 1.0)
    if opened is None:
        return {}
    zero = torch.zeros(1, body.num_joints, 3, dtype=torch.float64)
    shape = torch.zeros(1, body.num_shape, dtype=torch.float64)
    shut, wide = (lbs(body, shape, zero, e).vertices for e in (None, opened[None]))
    moved = 1000 * (embedding.points(wide) - embedding.points(shut))[0].norm(dim=1).numpy()
    kept = list(embedding.landmarks)
    return {"case": "jaw_motion", **{f"moves_mm_{i}": round(float(moved[kept.index(i)]), 1)
                                     for i in (UPPER_INNER, LOWER_INNER, LOWER_OUTER) if i in kept}}  # fmt: skip


#: MediaPipe face-mesh points by part of the face, for the init fit's residuals
FIT_PARTS = {
    "lips_inner": INNER_LIP_CONTOUR,
    "lips_outer": (61, 185, 40, 39, 37, 0, 267, 269, 270, 409, 291, 146, 91, 181, 84, 17, 314, 405, 321, 375),
    "eyes": (33, 7, 163, 144, 145, 153, 154, 155, 133, 246, 161, 160, 159, 158, 157, 173,
             263, 249, 390, 373, 374, 380, 381, 382, 362, 466, 388, 387, 386, 385, 384, 398),
    "nose": (1, 2, 98, 327, 4, 5, 195, 197, 6),
}  # fmt: skip


def fit_residuals(body, label: str, record: str, params: str, embedding_path: str) -> dict:
    """The init fit ``params`` (init/params.npz) against the detected face points of ``record`` (frames.h5,
    written with the embedding at ``embedding_path``)."""
    with FrameRecord(record) as rec, np.load(params) as p:
        points, camera, detected = rec.face_embedding(), rec.camera(), rec.h5["face_points"][:]
        split = rec.h5["split"][:]
        fit = {k: torch.from_numpy(p[k]).double() for k in ("betas", "poses", "transl", "expression")}
        names = [str(n) for n in p["expression_names"]]
    kept = list(LandmarkEmbedding.load(embedding_path, body.num_vertices).landmarks)
    n = len(detected)
    with torch.no_grad():
        verts = lbs(
            body, fit["betas"][None].expand(n, -1), fit["poses"], fit["expression"], transl=fit["transl"]
        ).vertices
        uv = torch.stack([camera.project(points(verts[i : i + 1]).to(camera.K.dtype))[0][0] for i in range(n)])
    err = np.linalg.norm(uv.numpy() - detected[..., :2], axis=-1)
    err[detected[..., 2] <= 0.5] = np.nan
    row = {"case": "init_fit", "embedding": label, "landmarks_kept": len(kept), "clip": Path(record).parent.name,
           "frames": n}  # fmt: skip
    for part, ids in FIT_PARTS.items():
        row[f"fit_{part}_px"] = round(float(np.nanmedian(err[:, [kept.index(i) for i in ids if i in kept]])), 2)
    for action in ("jawOpen", "mouthClose"):
        a = fit["expression"][:, names.index(action)].numpy()
        row[f"{action}_median"] = round(float(np.median(a)), 3)
        row[f"{action}_held_out_median"] = round(float(np.median(a[split > 0])), 3) if (split > 0).any() else np.nan
    return row


def real_clip(video: Path, tracker) -> dict:
    tracker.reset()
    frames, found, detections, t_track, t_mask = 0, 0, 0, 0.0, 0.0
    for _, rgb in iter_video(video, None):
        had = tracker.crop is not None
        t0 = time.perf_counter()
        face = tracker(rgb)
        t1 = time.perf_counter()
        frames += 1
        detections += not had
        if face[0, 2] > 0:
            found += 1
            head_mask(rgb, face)
            t_mask += time.perf_counter() - t1
        t_track += t1 - t0
    return dict(case="real_clip", clip=video.name, frames=frames, found_share=round(found / max(frames, 1), 4),
                detections=detections, track_ms=round(1000 * t_track / max(frames, 1), 2),
                mask_ms=round(1000 * t_mask / max(found, 1), 1))  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--body", required=True)
    ap.add_argument("--embedding", required=True)
    ap.add_argument("--models", required=True, help="the folder of the converted MediaPipe models")
    ap.add_argument("--real", help="a folder of real clips (head_*.mp4 are tracked)")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--resolution", type=int, default=512)
    ap.add_argument("--jaw", type=float, nargs="+", default=[0.0, 0.3, 0.8], help="jawOpen amounts of the views")
    ap.add_argument("--fit", nargs=4, action="append", default=[], metavar=("LABEL", "RECORD", "PARAMS", "EMBEDDING"),
                    help="score a clip's init fit (init/params.npz) against its record's face points")  # fmt: skip
    ap.add_argument("--label", help="the embedding's name in the table (default: its file's)")
    ap.add_argument("--append", action="store_true", help="add the rows to --out")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    body = load_body_model(args.body, dtype=torch.float64)
    embedding = LandmarkEmbedding.load(args.embedding, body.num_vertices)
    models = Path(args.models)
    tracker = FaceTracker(models / "face_detection_short_range.onnx", models / "face_landmark.onnx")
    rows = held_out(body, embedding, tracker, args.seeds, args.resolution, tuple(args.jaw))
    rows += [r for r in (jaw_motion(body, embedding),) if r and args.seeds]
    rows += [fit_residuals(body, *f) for f in args.fit]
    if args.real:
        rows += [real_clip(v, tracker) for v in sorted(Path(args.real).glob("head_*.mp4"))]
    table = pd.DataFrame(rows)
    label = args.label or Path(args.embedding).name
    named = table.pop("embedding") if "embedding" in table else pd.Series(np.nan, index=table.index, dtype=object)
    kept = table.pop("landmarks_kept") if "landmarks_kept" in table else pd.Series(np.nan, index=table.index)
    table.insert(0, "landmarks_kept", kept.fillna(len(embedding.landmarks)).astype(int))
    table.insert(0, "embedding", named.fillna(label))
    if args.append and Path(args.out).exists():
        table = pd.concat([pd.read_csv(args.out), table], ignore_index=True)
    table.to_csv(args.out, index=False)
    print(table.to_string(index=False))


if __name__ == "__main__":
    main()
