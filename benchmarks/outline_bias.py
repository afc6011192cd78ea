"""Which side of the person's outline a trained avatar's error lies on: its training frames (or any frames)
rendered at the model's own crop, each pixel put in one of four places by the truth's person alpha and the
render's coverage (the exterior's opacity or a mesh hit): both person, both background, the render covering
background the truth shows (*outside*), the render missing person the truth shows (*missing*).

An outline that moves from frame to frame (long hair, a hem) is learnt by the exterior as its frames' median
when the opacity's gradient reaches the density; where a ray is opaque it does not (e^-τ), and the
silhouette keeps the union: more error outside than missing, at a distance from the truth's outline.

    python benchmarks/outline_bias.py --record results/real/head_longhair/frames.h5 \\
        --body resources/body/anny_sub1_face.npz --frames 0,40,80,120 \\
        --model workflow=results/real/head_longhair/stage1/model.pt --model clear=/tmp/lh_clear/stage1/model.pt \\
        --subject head_longhair --out benchmarks/outline_bias.csv

Each row: subject, variant, frame, the crop's PSNR, the shares of its squared error outside and missing, those
pixels' counts and the outside pixels' median and 95th-percentile distance (pixels) from the truth's outline.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402

from delta.models.image import render_image  # noqa: E402
from delta.training.run import load_trained  # noqa: E402


def sides(render: np.ndarray, cover: np.ndarray, truth: np.ndarray, alpha: np.ndarray) -> dict:
    """The error of one (H, W, 3) render against its truth, split by the outline: ``cover`` the render's
    coverage, ``alpha`` the truth's person alpha, (H, W) in [0, 1] each."""
    err = ((render - truth) ** 2).mean(-1)
    total = max(float(err.sum()), 1e-12)
    person, covered = alpha >= 0.5, cover >= 0.5
    outside, missing = covered & ~person, person & ~covered
    away = cv2.distanceTransform((~person).astype(np.uint8), cv2.DIST_L2, 5)[outside]
    return {
        "psnr": float(10 * np.log10(1 / max(err.mean(), 1e-12))),
        "outside_share": float(err[outside].sum()) / total,
        "missing_share": float(err[missing].sum()) / total,
        "outside_px": int(outside.sum()),
        "missing_px": int(missing.sum()),
        "outside_median_px": float(np.median(away)) if away.size else 0.0,
        "outside_p95_px": float(np.percentile(away, 95)) if away.size else 0.0,
    }


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--record", required=True)
    ap.add_argument("--body", required=True)
    ap.add_argument("--model", nargs="+", required=True, help="VARIANT=model.pt")
    ap.add_argument("--frames", default="0", help="comma-separated frame indices of the record")
    ap.add_argument("--subject", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--append", action="store_true")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    frames = [int(f) for f in a.frames.split(",")]
    rows = []
    for spec in a.model:
        variant, path = spec.split("=", 1)
        trained = load_trained(path, a.record, a.body)
        model, data = trained.model, trained.data
        for f in frames:
            img = render_image(model, f)
            cover = np.maximum(img["nerf_mask"].numpy(), img["silhouette"].numpy() >= 0.5)
            row = sides(img["rgb"].numpy(), cover, data.images[f].numpy(), data.person[f].numpy())
            rows.append({"subject": a.subject, "variant": variant, "frame": int(data.frame_ids[f]),
                         "split": int(data.split[f]), **row})  # fmt: skip
            print(rows[-1], flush=True)
    save_table(pd.DataFrame(rows), a.out, a.append)


if __name__ == "__main__":
    main()
