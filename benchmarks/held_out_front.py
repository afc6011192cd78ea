"""Time to a held-out PSNR per variant, and where each stands against the measured front.

Reads the rows of ``benchmarks/held_out_curve.py`` (a variant's stage 1 stopped at several steps, each
snapshot scored on held-out views) and writes, per subject and variant: its last snapshot's seconds
and PSNR, the best PSNR any snapshot of any variant of that subject reached in at most as many seconds
(the front at its time) and how far below it the variant ends, and the seconds it took to reach each
target (linear between snapshots; nan where it never did). The targets are the subject's best final
PSNR less each ``--below-best`` (dB), so the same command sets them on any subject. A snapshot counts
as a point of the front like a run of that many steps (its learning rate had not yet fallen as a
run that short would have let it).

    python benchmarks/held_out_front.py --curves benchmarks/held_out_curve_capture.csv \\
        --out benchmarks/held_out_front_capture.csv
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from delta.eval.tradeoff import curve_time_to, front_at

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402

#: how far below the front a preset may end and still count as on it (the issue's tolerance)
ON_FRONT_DB = 0.2


def front_rows(curves: pd.DataFrame, below_best: list[float]) -> pd.DataFrame:
    rows = []
    for subject, g in curves.groupby("subject", sort=False):
        finals = g.sort_values("step").groupby("variant", sort=False).tail(1)
        best = float(finals["held_out_psnr"].max())
        for variant, v in g.groupby("variant", sort=False):
            v = v.sort_values("step")
            last = v.iloc[-1]
            front = front_at(g["seconds"], g["held_out_psnr"], float(last["seconds"]))
            row = {
                "subject": subject,
                "variant": variant,
                "device": last.get("device", ""),
                "steps": int(last.get("trained_steps", last["step"])),
                "seconds": round(float(last["seconds"]), 1),
                "held_out_psnr": round(float(last["held_out_psnr"]), 3),
                "front_psnr_at_seconds": round(front, 3),
                "below_front_db": round(front - float(last["held_out_psnr"]), 3),
                "on_front": front - float(last["held_out_psnr"]) <= ON_FRONT_DB,
            }
            for d in below_best:
                target = best - d
                t = curve_time_to(v["seconds"], v["held_out_psnr"], target)
                row[f"target_{d:g}db_below_best"] = round(target, 3)
                row[f"seconds_to_{d:g}db_below_best"] = round(t, 1)
            rows.append(row)
    return pd.DataFrame(rows)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--curves", nargs="+", required=True, help="held_out_curve.py CSVs")
    ap.add_argument("--below-best", nargs="+", type=float, default=[1.0, 0.5])
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    curves = pd.concat([pd.read_csv(c) for c in args.curves], ignore_index=True)
    table = save_table(front_rows(curves, args.below_best), args.out)
    print(table.to_string(index=False))


if __name__ == "__main__":
    main()
