"""Whether each capture's subject keeps one pose: the evidence the init fit's hold is decided on.

For each frame record: the spread over its held frames (those not in a novel-pose sequence) of its
limbs' extent along the torso, in torso lengths (:mod:`delta.fitting.hold`), per limb and the largest,
and the decision at the default threshold. With ``--fits`` (an init/summary.json per record, same
order) the fit's own keypoint residual is added: a fit that holds a dancer's limbs to their mean pose
cannot reach her keypoints.

    python benchmarks/static_hold.py results/synthetic/tight/frames.h5 results/synthetic/loose/frames.h5 \\
        results/real/dress_dance/frames.h5 --out benchmarks/static_hold.csv
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import h5py
import pandas as pd

from delta.body.keypoints import OPENPOSE18
from delta.data import SPLITS
from delta.fitting.hold import LIMBS, hold_decision, limb_spreads
from delta.fitting.settings import FitConfig


def row(record: Path, fit_summary: Path | None) -> dict:
    with h5py.File(record, "r") as f:
        kp, split = f["keypoints"][:], f["split"][:]
    held = split != SPLITS.index("test_pose")  # a novel-pose sequence is never held
    cfg = FitConfig()
    out = {"record": str(record), "held_frames": int(held.sum())}
    spreads = limb_spreads(kp[held], cfg.conf_threshold)
    for a, b in LIMBS:
        out[f"{OPENPOSE18[a]}-{OPENPOSE18[b]}"] = round(spreads[(a, b)], 4) if (a, b) in spreads else None
    decision = hold_decision(kp, held, cfg.static_spread, 10.0, cfg.conf_threshold)
    out |= {"limb_spread": decision["limb_spread"], "threshold": cfg.static_spread, "hold": decision["hold"]}
    if fit_summary is not None:
        summary = json.loads(fit_summary.read_text())
        out |= {"fit": str(fit_summary), "fit_held": summary.get("static_hold", {}).get("hold"),
                "fit_residual_px_mean": round(summary["residual_px_mean"], 3)}  # fmt: skip
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("records", nargs="+", type=Path)
    p.add_argument("--fits", nargs="*", type=Path, default=[], help="init/summary.json per record, same order")
    p.add_argument("--out", required=True, type=Path)
    args = p.parse_args()
    fits = args.fits or [None] * len(args.records)
    if len(fits) != len(args.records):
        raise SystemExit(f"{len(args.records)} records but {len(fits)} fit summaries")
    table = pd.DataFrame([row(r, f) for r, f in zip(args.records, fits)])
    table.to_csv(args.out, index=False)
    print(table.to_string())


if __name__ == "__main__":
    main()
