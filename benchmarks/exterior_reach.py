"""How far from the body a trained avatar's exterior lies, against how far the capture shows it.

The scene analysis measures the exterior's reach sideways, in the silhouette (``scene.json``: the 98th percentile
of the person's pixels beyond the fitted body, metres). Along the camera's rays nothing measures it: a capture
that never turns leaves the depth of its hair or clothing to the NeRF, which may spread it through the whole room
(``render.max_dist``), a slab no view from the front can tell from a shell. This tool samples the trained
exterior's density on a grid of canonical cells within the room of the framed canonical body and reports, per band
of distance from the body, the share of the exterior's opacity there (each cell's 1 - exp(-sigma * cell), the
occupancy grid's empty cells counting nothing) and the cells more than half opaque; with ``--scene`` also the share
beyond the reach the silhouette shows.

    PYTHONPATH=$PWD python3 benchmarks/exterior_reach.py --model results/real/head_shorthair/stage1/model.pt \\
        --record results/real/head_shorthair/frames.h5 --body resources/body/anny_sub1_face.npz \\
        --subject head_shorthair --scene results/real/head_shorthair/scene.json --csv benchmarks/exterior_reach.csv
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from delta.geometry.nearest import PointIndex
from delta.training.run import load_trained

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402

EDGES = (0.0, 0.01, 0.02, 0.04, 0.06, 0.08, 0.1, 0.15, 0.2, 0.3, 0.45, 0.6)
"""Band edges (m) of the distance from the canonical body."""
MOST_CELLS = 6_000_000
"""The grid's cells are as small as ``--cell`` asks, or larger where the box would hold more than this many."""


@torch.no_grad()
def opacity_by_distance(model, cell: float) -> tuple[np.ndarray, np.ndarray, float]:
    """(N,) each canonical cell centre's distance (m) to the framed canonical body and (N,) the exterior's opacity
    across the cell, for the cells within ``render.max_dist``; and the cell's edge used."""
    cano = model.canonical_vertices.detach().double().cpu()[model.framed.cpu()]
    room = float(model.spec.render.max_dist)
    lo, hi = cano.amin(0) - room, cano.amax(0) + room
    cell = max(cell, float(((hi - lo).prod() / MOST_CELLS) ** (1 / 3)))
    axes = [torch.arange(float(lo[i]), float(hi[i]), cell, dtype=torch.float64) + cell / 2 for i in range(3)]
    index = PointIndex(cano)
    dist, opacity = [], []
    for x in axes[0].split(8):  # slabs along x: a few hundred thousand cells at a time
        pts = torch.stack(torch.meshgrid(x, axes[1], axes[2], indexing="ij"), -1).reshape(-1, 3)
        d = index.query(pts, 1)[0].reshape(-1)
        near = d <= room
        pts, d = pts[near].float().to(model.background.device), d[near]
        if not len(pts):
            continue
        _, sigma = model.nerf(pts)
        if model.occupancy is not None:
            sigma = torch.where(model.occupancy.contains(pts), sigma, torch.zeros_like(sigma))
        dist.append(d.numpy())
        opacity.append((1 - torch.exp(-sigma.double().cpu() * cell)).numpy())
    return np.concatenate(dist), np.concatenate(opacity), cell


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True)
    ap.add_argument("--record", required=True)
    ap.add_argument("--body", required=True)
    ap.add_argument("--subject", required=True)
    ap.add_argument("--label", default="", help="what this model is (a variant's name)")
    ap.add_argument("--scene", default="", help="the subject's scene.json: the reach its silhouette shows")
    ap.add_argument("--cell", type=float, default=0.004, help="the grid's cell (m), at least")
    ap.add_argument("--csv", required=True)
    ap.add_argument("--append", action="store_true")
    args = ap.parse_args()
    model = load_trained(args.model, args.record, args.body).model
    if model.nerf is None:
        raise SystemExit(f"{args.model}: no exterior")
    dist, opacity, cell = opacity_by_distance(model, args.cell)
    total = float(opacity.sum())
    room = float(model.spec.render.max_dist)
    base = {"subject": args.subject, "label": args.label, "room_m": room, "cell_m": round(cell, 4)}
    rows = []
    for a, b in zip(EDGES[:-1], EDGES[1:]):
        if a >= room:
            break
        band = (dist > a) & (dist <= b)
        rows.append(base | {"band": f"{100 * a:g}-{100 * b:g} cm", "opacity_share": float(opacity[band].sum()) / total,
                            "opaque_cells": int((opacity[band] > 0.5).sum())})  # fmt: skip
    if args.scene:
        reach = float(json.loads(Path(args.scene).read_text())["evidence"]["reach"]["reach_m"])
        beyond = dist > reach
        rows.append(base | {"band": f"beyond the silhouette's reach ({100 * reach:.1f} cm)",
                            "opacity_share": float(opacity[beyond].sum()) / total,
                            "opaque_cells": int((opacity[beyond] > 0.5).sum())})  # fmt: skip
    table = pd.DataFrame(rows).round(4)
    save_table(table, args.csv, append=args.append)
    print(table.to_string(index=False))


if __name__ == "__main__":
    main()
