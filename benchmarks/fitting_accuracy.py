"""Accuracy of the init fitting on the synthetic captures (keypoints from the ground truth).

For each subject under data/synthetic/ (made by `snakemake --cores 2`), fits every k-th
frame from the mean pose to the ground-truth keypoints and person masks (alpha) and reports,
against the ground-truth body: 2D keypoint reprojection error, per-joint 3D error of the
OpenPose-18 points after root alignment (MPJPE) and after a similarity (Procrustes)
alignment (PA-MPJPE), the root position error, the body's mean vertex error after centroid
alignment (what the avatar's interior starts from), the IoU of the fitted coarse mesh's
silhouette with the person mask (at --iou-size pixels), and seconds per frame (2 threads).
Before-fitting numbers use the initialisation (mean shape and pose, facing the camera,
placed from the torso's size). The person mask includes clothing and hair, so even the
ground-truth body's IoU is below 1 (its row "truth" gives that ceiling).

    python benchmarks/fitting_accuracy.py --every 5 --out benchmarks/fitting_accuracy.csv
    python benchmarks/fitting_accuracy.py --exterior-fill 0.1 --label exterior_0.1 --append ...
    python benchmarks/fitting_accuracy.py --facing-starts 1 --unobserved-weight 0 --label one_start_no_unobserved_prior --append ...

``--exterior-fill`` weighs the mask pixels that the ground truth labels clothing or hair
(as the workflow's fit does with the record's parsing).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import torch

from delta.body.keypoints import openpose18_map
from delta.body.lbs import lbs
from delta.body.model import load_body_model
from delta.cameras.models import OrthographicCamera, PinholeCamera
from delta.fitting import silhouette as sil
from delta.fitting.fit import FitResult, fit
from delta.fitting.settings import FitConfig
from delta.fitting.run import EXTERIOR

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402

HIPS = [8, 11]


def procrustes_error(truth: torch.Tensor, pred: torch.Tensor) -> torch.Tensor:
    """(F, K, 3) mean per-point error after a per-frame similarity alignment of pred onto truth."""
    errors = []
    for x, y in zip(truth, pred):
        x0, y0 = x - x.mean(0), y - y.mean(0)
        U, S, Vt = torch.linalg.svd(y0.T @ x0)
        D = torch.diag(torch.tensor([1.0, 1.0, torch.sign(torch.det(U @ Vt)).item()], dtype=x.dtype))
        R = U @ D @ Vt
        s = (S * torch.diag(D)).sum() / y0.square().sum()
        errors.append((s * y0 @ R + x.mean(0) - x).norm(dim=-1).mean())
    return torch.stack(errors)


def mask_iou(model, coarse, camera, masks, vertices, size: int) -> float:
    """Mean IoU of the hard (coverage > 0.5) coarse-mesh silhouette with the mask (> 0.5) at size x size."""
    uv = camera.project(vertices[:, coarse.vertex_ids])[0]
    small = sil.downsample_masks(masks, size)
    rendered = sil.frames_silhouette(uv, coarse.faces, size, (camera.width, camera.height), sigma=1e-3, masks=small)
    return sil.soft_iou((rendered > 0.5).double(), (small > 0.5).double()).mean().item()


def scores(model, kp_map, camera, detected, truth, truth_verts, betas, pose, transl, masks, coarse, iou_size) -> dict:
    out = lbs(model, betas[None].expand(len(pose), -1), pose, transl=transl)
    verts = out.vertices - out.vertices.mean(1, keepdim=True) + truth_verts.mean(1, keepdim=True)
    pred = kp_map(out.joints, out.vertices)
    uv = camera.project(pred)[0]
    conf = detected[..., 2] > 0
    reproj = ((uv - detected[..., :2]).norm(dim=-1) * conf).sum() / conf.sum()
    centred = lambda p: p - p[:, HIPS].mean(1, keepdim=True)  # noqa: E731
    return dict(reproj_px=reproj.item(), mpjpe_mm=1000 * (centred(pred) - centred(truth)).norm(dim=-1).mean().item(),
                pa_mpjpe_mm=1000 * procrustes_error(truth, pred).mean().item(),
                root_mm=1000 * (pred[:, HIPS].mean(1) - truth[:, HIPS].mean(1)).norm(dim=-1).mean().item(),
                body_err_mm=1000 * (verts - truth_verts).norm(dim=-1).mean().item(),
                mask_iou=mask_iou(model, coarse, camera, masks, out.vertices, iou_size))  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data", default="data/synthetic")
    parser.add_argument("--body", default="resources/body/anny_sub1.npz")
    parser.add_argument("--every", type=int, default=5)
    parser.add_argument("--pose-weight", type=float, default=FitConfig.pose_weight)
    parser.add_argument("--shape-weight", type=float, default=FitConfig.shape_weight)
    parser.add_argument("--limit-weight", type=float, default=FitConfig.limit_weight)
    parser.add_argument("--sil-weight", type=float, default=FitConfig.sil_weight)
    parser.add_argument("--exterior-fill", type=float, default=FitConfig.exterior_fill)
    parser.add_argument("--facing-starts", type=int, default=FitConfig.facing_starts)
    parser.add_argument("--unobserved-weight", type=float, default=FitConfig.unobserved_weight)
    parser.add_argument("--label", default="default", help="names this configuration in the CSV")
    parser.add_argument("--append", action="store_true", help="add rows to --out instead of replacing it")
    parser.add_argument("--iou-size", type=int, default=128)
    parser.add_argument("--subjects", nargs="*", help="capture names (default: all)")
    parser.add_argument("--out", default="benchmarks/fitting_accuracy.csv")
    args = parser.parse_args()
    torch.set_num_threads(2)
    model = load_body_model(args.body, dtype=torch.float64)
    kp_map = openpose18_map(model)
    knees = [model.joint_names.index(n) for n in ("lowerleg01.L", "lowerleg01.R")]
    coarse = sil.coarse_mesh(model, FitConfig.sil_cell)
    cfg = FitConfig(pose_weight=args.pose_weight, shape_weight=args.shape_weight, limit_weight=args.limit_weight,
                    sil_weight=args.sil_weight, exterior_fill=args.exterior_fill, facing_starts=args.facing_starts,
                    unobserved_weight=args.unobserved_weight)  # fmt: skip
    rows = []
    for capture in sorted(p for p in Path(args.data).iterdir() if (p / "gt" / "params.npz").is_file()):
        if args.subjects and capture.name not in args.subjects:
            continue
        with np.load(capture / "gt" / "params.npz") as p:
            gt = {k: p[k] for k in p.files}
        with h5py.File(capture / "gt" / "frames.h5") as f:
            sel = np.arange(0, f["keypoints"].shape[0], args.every)
            detected = torch.from_numpy(f["keypoints"][:][sel]).double()
            masks = f["alpha"][:][sel]
            layers = [f[k][:][sel] for k in EXTERIOR if k in f]
            exterior = np.maximum.reduce(layers) if layers else None
        if str(gt["camera_model"]) == "pinhole":
            camera = PinholeCamera(*(torch.from_numpy(gt[k]) for k in ("K", "R", "t", "dist")), int(gt["width"]),
                                   int(gt["height"]))  # fmt: skip
            template = camera
        else:
            camera = OrthographicCamera(torch.from_numpy(gt["ortho_scale"][sel]), torch.from_numpy(gt["ortho_trans"][sel]),
                                        int(gt["width"]), int(gt["height"]))  # fmt: skip
            template = OrthographicCamera(torch.tensor(1.0), torch.zeros(2), camera.width, camera.height)
        out = lbs(model, torch.from_numpy(gt["betas"])[None].expand(len(sel), -1), torch.from_numpy(gt["poses"][sel]),
                  transl=torch.from_numpy(gt["transl"][sel]))  # fmt: skip
        truth = kp_map(out.joints, out.vertices)
        before = fit(model, kp_map, detected, template, FitConfig(iterations=(0, 0, 0)), knees=knees)
        t0 = time.perf_counter()
        after = fit(model, kp_map, detected, template, cfg, knees=knees, masks=masks, exterior=exterior)
        seconds = time.perf_counter() - t0
        gt_res = FitResult(torch.from_numpy(gt["betas"]), torch.from_numpy(gt["poses"][sel]),
                           torch.from_numpy(gt["transl"][sel]), camera, *[None] * 4)  # fmt: skip
        for stage, res in (("truth", gt_res), ("before", before), ("after", after)):
            cam = res.camera if isinstance(res.camera, OrthographicCamera) else camera
            row = dict(
                config=args.label, subject=capture.name, stage=stage, frames=len(sel), camera=str(gt["camera_model"])
            )
            row.update(scores(model, kp_map, cam, detected, truth, out.vertices, res.betas, res.pose, res.transl, masks, coarse,
                              args.iou_size))  # fmt: skip
            row["seconds_per_frame"] = seconds / len(sel) if stage == "after" else 0.0
            rows.append(row)
            print(row, flush=True)
    save_table(pd.DataFrame(rows), args.out, args.append)


if __name__ == "__main__":
    main()
