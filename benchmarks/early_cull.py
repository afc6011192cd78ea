"""What the early cull (before the kNN query) drops, and whether it drops samples the exact tests keep.

For each trained stage given, runs ``--steps`` training steps (forward, losses, backward; the
parameters are not changed) with the early cull off, and at each backward-skinning call counts,
over the samples that reach the kNN query: those the exact tests keep (kNN distance within
``max_dist`` and canonical point in an occupied cell), those the early cull would pass, and
those the exact tests keep but the early cull would drop (``lost``). One row per step, CSV.

    python benchmarks/early_cull.py --out benchmarks/early_cull.csv \
        results/synthetic/loose/stage1/model.pt:results/synthetic/loose/frames.h5 \
        results/synthetic/tight/stage1/model.pt:results/synthetic/tight/frames.h5
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd
import torch

ROOT = Path(__file__).resolve().parents[1]


def count(model, data, st, stage: int, steps: int, seed: int = 0) -> list[dict]:
    from delta.render import hybrid
    from delta.training.profile import _step

    rs = model.spec.render
    occ = model.occupancy if model.occupancy is not None and bool(model.occupancy.active) else None
    deform = hybrid.deformer.deform
    rows: list[dict] = []

    def counting(frame, points, *args):
        d = deform(frame, points, *args)
        exact = d.valid & (occ.contains(d.canonical) if occ is not None else True)
        early = hybrid.early_cull(frame, points, rs.max_dist, occ.contains if occ is not None else None)
        rows.append({"reached_knn": len(points), "exact_kept": int(exact.sum()), "early_passed": int(early.sum()),
                     "lost": int((exact & ~early).sum())})  # fmt: skip
        return d

    was, rs.early_cull = rs.early_cull, False
    hybrid.deformer.deform = counting
    try:
        g = torch.Generator().manual_seed(seed)
        for _ in range(steps):
            _step(model, data, st, stage, g)
    finally:
        hybrid.deformer.deform = deform
        rs.early_cull = was
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("stages", nargs="+", help="MODEL.pt:FRAMES.h5 pairs")
    ap.add_argument("--body", default=str(ROOT / "resources/body/anny_sub1.npz"))
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", required=True, help="CSV to write")
    a = ap.parse_args()
    from delta.training.run import load_trained

    torch.set_num_threads(a.threads)
    tables = []
    for pair in a.stages:
        model_path, record = pair.split(":")
        tr = load_trained(model_path, record, a.body)
        model = tr.model.train()
        table = pd.DataFrame(count(model, tr.data, tr.settings, tr.stage, a.steps))
        table.insert(0, "model", model_path)
        table.insert(1, "step", range(len(table)))
        tables.append(table)
    table = pd.concat(tables, ignore_index=True)
    table.to_csv(a.out, index=False)
    print(table.groupby("model")[["reached_knn", "exact_kept", "early_passed", "lost"]].sum().to_string())


if __name__ == "__main__":
    main()
