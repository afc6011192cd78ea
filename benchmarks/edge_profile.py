"""Where the body mesh's edge lies against the person's edge on the visible body, pixel by pixel.

For training frames of a trained avatar, the mesh's silhouette (4×4 rays a pixel) and the person mask
the avatar was trained on are averaged over the skin pixels (interior, away from clothing and hair) in
bands of distance from the mask's edge (negative: inside the person). An edge on the person's edge
covers what the mask covers in every band; a mesh one pixel too wide covers ~0.6 of the first pixel
outside where the mask covers ~0.2. Three bodies are measured under the same frames: the trained one,
the init fit's (its shape, poses and camera), and, for a synthetic capture, the true one (the
generator's shape and poses under the record's camera): the last tells how far the frames themselves
(the crop's resampling) put the truth from the mask.

    python benchmarks/edge_profile.py --model results/synthetic/loose/stage1/model.pt \\
        --record results/synthetic/loose/frames.h5 --body resources/body/anny_sub1.npz \\
        --init results/synthetic/loose/init/params.npz --truth data/synthetic/loose/gt/params.npz \\
        --subject loose --frames 4 --out benchmarks/edge_profile.csv [--append]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402

BANDS = ((-3, -2), (-2, -1), (0, 1), (1, 2), (2, 3))


def skin_bands(person: np.ndarray, interior: np.ndarray, exterior: np.ndarray) -> dict[str, np.ndarray]:
    """(H, W) bool per band: skin pixels (interior within 3 px, no exterior within 4 px) at a signed
    distance (px, Euclidean, + outside) from the person mask's 0.5 contour in (lo, hi]."""
    import cv2

    inside = (person > 0.5).astype(np.uint8)
    signed = np.where(inside > 0, -cv2.distanceTransform(inside, cv2.DIST_L2, 5),
                      cv2.distanceTransform(1 - inside, cv2.DIST_L2, 5))  # fmt: skip
    skin = cv2.dilate((interior > 0.5).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    skin &= cv2.dilate((exterior > 0.5).astype(np.uint8), np.ones((9, 9), np.uint8)) == 0
    return {f"({lo},{hi}]": skin & (signed > lo) & (signed <= hi) for lo, hi in BANDS}


def mesh_coverage(model, frame: int) -> np.ndarray:
    import torch

    from delta.models.image import render_image

    with torch.no_grad():
        return render_image(model, frame, supersample=4, soft_silhouette=False)["silhouette"].numpy()


def set_body(model, frame: int, betas, pose, transl, camera=None) -> None:
    """The avatar's shape (None: kept) and one frame's pose and translation (and orthographic camera)."""
    import torch

    with torch.no_grad():
        if betas is not None:
            model.betas.copy_(torch.as_tensor(betas, dtype=model.betas.dtype))
        model.poses[frame] = torch.as_tensor(pose, dtype=model.poses.dtype)
        model.transl[frame] = torch.as_tensor(transl, dtype=model.transl.dtype)
        if camera is not None and not model.pinhole:
            model.ortho_scale[frame] = float(camera[0])
            model.ortho_trans[frame] = torch.as_tensor(camera[1], dtype=model.ortho_trans.dtype)


def profile(args) -> pd.DataFrame:
    import h5py
    import torch

    from delta.training.run import load_trained

    torch.set_num_threads(args.threads)
    tr = load_trained(args.model, args.record, args.body)
    model, data = tr.model, tr.data
    train = np.flatnonzero(np.asarray(data.split) == 0)
    frames = [int(train[i]) for i in np.linspace(0, len(train) - 1, args.frames).round().astype(int)]
    init = np.load(args.init) if args.init else None
    truth = np.load(args.truth) if args.truth else None
    with h5py.File(args.record) as rec:
        record_camera = (rec["ortho_scale"][:], rec["ortho_trans"][:]) if "ortho_scale" in rec else None
    trained = {k: v.detach().clone() for k, v in (("betas", model.betas), ("poses", model.poses),
                                                  ("transl", model.transl))}  # fmt: skip
    if not model.pinhole:
        trained |= {"scale": model.ortho_scale.detach().clone(), "trans": model.ortho_trans.detach().clone()}
    offsets = model.offsets
    with torch.no_grad():
        zero = torch.zeros_like(offsets())
    rows = []
    for f in frames:
        person, interior = data.person[f].numpy(), data.interior[f].numpy()
        bands = skin_bands(person, interior, data.exterior[f].numpy())
        bodies = {"trained": mesh_coverage(model, f)}
        model.offsets = lambda: zero  # the init fit's and the true body carry no learnt offsets
        if init is not None:
            cam = (init["ortho_scale"][f], init["ortho_trans"][f]) if "ortho_scale" in init.files else None
            set_body(model, f, init["betas"], init["poses"][f], init["transl"][f], cam)
            bodies["init fit"] = mesh_coverage(model, f)
        if truth is not None:
            fid = int(data.frame_ids[f])
            cam = (record_camera[0][f], record_camera[1][f]) if record_camera is not None else None
            set_body(model, f, truth["betas"], truth["poses"][fid], truth["transl"][fid], cam)
            bodies["truth"] = mesh_coverage(model, f)
        model.offsets = offsets  # the trained body (and camera) back
        cam = None if model.pinhole else (float(trained["scale"][f]), trained["trans"][f])
        set_body(model, f, trained["betas"], trained["poses"][f], trained["transl"][f], cam)
        for body, cover in bodies.items():
            means = {band: float(cover[m].mean()) for band, m in bands.items()}
            rows += [{"subject": args.subject, "frame_id": int(data.frame_ids[f]), "body": body, "band_px": band,
                      "pixels": int(m.sum()), "mask": round(float(person[m].mean()), 4),
                      "mesh": round(means[band], 4)} for band, m in bands.items()]  # fmt: skip
            print(f"frame {int(data.frame_ids[f])} {body}: " + " ".join(f"{v:.2f}" for v in means.values()), flush=True)
    return pd.DataFrame(rows)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--record", required=True)
    ap.add_argument("--body", required=True)
    ap.add_argument("--init", default="", help="the init fit's params.npz (its body is measured too)")
    ap.add_argument("--truth", default="", help="a synthetic capture's gt/params.npz (the true body)")
    ap.add_argument("--subject", default="")
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", required=True)
    ap.add_argument("--append", action="store_true")
    args = ap.parse_args(argv)
    df = save_table(profile(args), args.out, args.append)
    summary = df.groupby(["subject", "body", "band_px"], sort=False)[["mask", "mesh"]].mean().round(3)
    print(summary.to_string())


if __name__ == "__main__":
    main()
