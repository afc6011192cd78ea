"""What the mouth's prior (``training.mouth_shade``) gives a head avatar whose training frames never open the
mouth as wide as its held-out frames do, and what colour the inside of the capture's open mouths has.

Two kinds of row:

- ``kind=colour``: per split of the record, over the frames whose inner-lip contour (MediaPipe's, the
  record's ``face_landmarks``) encloses ``--min-area`` pixels or more, the median colour inside the contour
  and the median skin colour of those frames (the record's ``skin`` mask), and their ratio.
- ``kind=score``: a trained avatar scored on its held-out frames, unrefined (no refinement to blur the
  comparison), three ways: as trained; with the prior added at the ``mouth`` vertices that no training
  frame's ray reaches first (the vertices that training with the prior would have left at it: a seen
  vertex keeps what training made of it); and with the prior added at every ``mouth`` vertex. A model
  trained with the prior (``model.pt`` format 3) already has it: its "as trained" row is the one to read.

Run from the repository root::

    PYTHONPATH=$PWD python3 benchmarks/mouth_prior.py --model results/real/head_longhair/stage2/model.pt \\
        --record results/real/head_longhair/frames.h5 --body resources/body/anny_sub1_face.npz \\
        --subject head_longhair --splits test_view --csv benchmarks/mouth_prior.csv
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import torch

from delta.body.model import REGION
from delta.data import SPLITS
from delta.eval.evaluate import evaluate
from delta.eval.settings import EvalSettings
from delta.geometry.raymesh import ray_mesh_hits
from delta.models.avatar import HybridAvatar, mouth_prior
from delta.models.image import pixel_grid
from delta.scene.mouth import open_mouths
from delta.training.run import load_trained

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table, trained_model_arguments  # noqa: E402


def mouth_colours(record: str | Path, min_area: int) -> list[dict]:
    """Per split, the median colour inside the inner-lip contour of the frames where it encloses at least
    ``min_area`` pixels (eroded by one: :func:`delta.scene.mouth.open_mouths`), the median skin colour of
    those frames (the record's ``skin`` mask) and the ratio."""
    rows = []
    with h5py.File(record, "r") as h5:
        split = h5["split"][:]
        found = {}
        for i, area, colour in open_mouths(record, range(len(split)), min_area):
            image = h5["images"][i].astype(np.float32)
            image = image / 255.0 if h5["images"].dtype == np.uint8 else image
            skin = h5["skin"][i] > 0.5
            found.setdefault(int(split[i]), []).append((area, colour, np.median(image[skin], 0)))
    for code, items in sorted(found.items()):
        inside = np.median([c for _, c, _ in items], 0)
        skin = np.median([s for _, _, s in items], 0)
        rows.append({"kind": "colour", "split": SPLITS[code], "frames": len(items),
                     "area_px": float(np.median([a for a, _, _ in items])),
                     **{f"inside_{c}": round(float(v), 4) for c, v in zip("rgb", inside)},
                     **{f"skin_{c}": round(float(v), 4) for c, v in zip("rgb", skin)},
                     **{f"ratio_{c}": round(float(v), 3) for c, v in zip("rgb", inside / skin)}})  # fmt: skip
    return rows


@torch.no_grad()
def seen_vertices(model: HybridAvatar, frames, stride: int = 2) -> torch.Tensor:
    """(V,) bool: the vertices of the triangles that a ray through every ``stride``-th pixel of one of
    ``frames`` hits first (the body alone: an exterior does not cover the inside of a mouth).

    Not :func:`delta.geometry.sight.visible_vertices` (a clear line of sight to the vertex): what training
    reaches is what its pixel rays hit, and through a lip gap narrower than a pixel a vertex can be in
    sight and still meet no ray."""
    seen = torch.zeros(model.body.num_vertices, dtype=torch.bool, device=model.background.device)
    pixels = pixel_grid(model.resolution // stride, device=seen.device) * stride
    offsets = model.offsets()
    for frame in frames:
        vertices = model.pose_body(int(frame), offsets).vertices[0]
        origins, dirs = model.camera(int(frame)).rays(pixels)
        hits = ray_mesh_hits(vertices, model.body.faces, origins, dirs)
        seen[model.body.faces[hits.face[hits.hit]].reshape(-1)] = True
    return seen


def main() -> None:
    ap = trained_model_arguments(argparse.ArgumentParser(description=__doc__.split("\n\n")[0]))
    ap.add_argument("--shade", type=float, default=0.3, help="the prior's mouth_shade")
    ap.add_argument("--min-area", type=int, default=30, help="pixels inside the contour for an open mouth")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--csv", required=True)
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    rows = [dict(r, subject=a.subject) for r in mouth_colours(a.record, a.min_area)]
    trained = load_trained(a.model, a.record, a.body, a.device)
    model, data = trained.model, trained.data
    mouth = model.body.regions == REGION["mouth"]
    seen = seen_vertices(model, np.nonzero(np.asarray(data.split) == SPLITS.index("train"))[0])
    own = model.albedo_field.prior
    prior = mouth_prior(model.body, data.skin_color, a.shade)
    if prior is None:
        sys.exit(f"{a.body}: no mouth region, or --shade 1: no prior to add")
    prior = prior.to(seen.device)
    st = EvalSettings(splits=tuple(a.splits), max_frames=a.max_frames, refine_steps=0, supersample=a.supersample,
                      perceptual_dir=a.perceptual_dir, worst=0)  # fmt: skip
    variants = [("as trained", own)]
    if own is None:  # trained without a prior: add it, where unseen and everywhere
        variants += [("prior at the unseen mouth", prior * (~seen)[:, None]), ("prior at every mouth vertex", prior)]
    for variant, added in variants:
        model.albedo_field.prior = added
        df = evaluate(trained, a.record, st, subject=a.subject)
        for split, part in df.groupby("split"):
            rows.append({"kind": "score", "subject": a.subject, "split": split, "variant": variant, "frames": len(part),
                         "shade": None if added is None else model.spec.mouth_shade if own is not None else a.shade,
                         "mouth_vertices": int(mouth.sum()), "mouth_seen": int((mouth & seen).sum()),
                         **{k: round(float(part[k].mean()), 4) for k in
                            ("psnr", "ssim", "stlpips_alex", "psnr_face", "psnr_head", "l1_face") if k in part}})  # fmt: skip
        print(rows[-1], flush=True)
    print(save_table(pd.DataFrame(rows), a.csv, a.append).to_string(index=False))


if __name__ == "__main__":
    main()
