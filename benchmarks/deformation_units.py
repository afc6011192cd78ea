"""What a trained avatar's F_e (stage 2's deformation) can still do: its head's active units and its output.

A ReLU unit that is below zero on every input the field meets gets no gradient again; when the last hidden
layer has lost its units, F_e's output is its output layer's bias, one offset for every point and time,
whatever training asks of it. Per model: the units active somewhere in F_e's box at the training frames'
times per hidden layer (what the stage log's ``deformation_units_active`` says), and over points drawn in
that box (each its own pose cue) F_e's mean displacement and how far it moves over the training sequence
(mean and largest distance of a point's displacement at 41 times to its mean over them), in mm.

    PYTHONPATH=$PWD python3 benchmarks/deformation_units.py --record results/synthetic/gen2/frames.h5 \\
        --body resources/body/anny_sub1.npz --subject gen2 \\
        --models "fast (1e-2)=results/synthetic/gen2/stage2/model.pt" "1e-3=/tmp/gen2_lr1e3/stage2/model.pt" \\
        --csv benchmarks/deformation_units.csv
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd
import torch

from delta.fields.networks import time_features
from delta.training.run import deformation_units, load_trained

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402


@torch.no_grad()
def displacement_mm(field, points: int = 4096, times: int = 41, seed: int = 0) -> dict:
    """F_e's mean displacement over ``points`` in its box and its motion over ``times`` even training times."""
    x = field.box_points(points, seed)
    taus = torch.linspace(0, 1, times)
    codes = [time_features(t, field.time_freqs) if field.time_freqs else None for t in taus]
    out = torch.stack([field(x, x, c) for c in codes])  # (T, N, 3)
    moved = (out - out.mean(0)).norm(dim=-1)
    return {"displacement_mean_mm": round(1000 * float(out.norm(dim=-1).mean()), 3),
            "time_motion_mean_mm": round(1000 * float(moved.mean()), 3),
            "time_motion_max_mm": round(1000 * float(moved.max()), 3)}  # fmt: skip


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--record", required=True)
    ap.add_argument("--body", required=True)
    ap.add_argument("--subject", required=True)
    ap.add_argument("--models", nargs="+", required=True, help="LABEL=model.pt of a stage-2 avatar")
    ap.add_argument("--csv", required=True)
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args(argv)
    rows = []
    for item in a.models:
        label, path = item.split("=", 1)
        tr = load_trained(path, a.record, a.body)
        field = tr.model.deformation
        if field is None:
            sys.exit(f"{path}: a stage-1 model has no F_e")
        units = deformation_units(tr.model, tr.data.train)
        rows.append({"subject": a.subject, "variant": label, "width": field.head.hidden[0].out_features,
                     "units_active": " ".join(map(str, units)), "last_layer_active": units[-1],
                     "lr_deformation": tr.settings.stage2.lr.get("deformation"),
                     **displacement_mm(field)})  # fmt: skip
    print(save_table(pd.DataFrame(rows), a.csv, a.append).to_string(index=False))


if __name__ == "__main__":
    main()
