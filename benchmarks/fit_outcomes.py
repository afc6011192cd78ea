"""What an init fit decided and what its avatar scored, one row a run (the silhouette's weight, how the keypoints
meet the body, the held-out scores).

``delta.fitting.balance`` decides the silhouette's weight from the keypoints' scatter; a run's settings
(``fitting.settings``) may differ otherwise, as the rows' labels say.

Reads each run's ``init/summary.json`` (the decision: the keypoints' median residual, the reference, the
factor) and, where given, its evaluation's ``summary.json`` (held-out PSNR, SSIM, as fitted and refined),
one row a run:

    python3 benchmarks/fit_outcomes.py --run dancer-weight-as-set=<run> --run dancer-decided=<run> \\
        --run tight=<run> --run loose=<run> --out benchmarks/silhouette_balance.csv

A run folder holds ``init/`` and, when scored, ``eval/``. A fit written before the decision was recorded gets the
one the default settings take on its report's residuals (``decided_now``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import pandas as pd
import torch

from delta.fitting.balance import silhouette_balance
from delta.fitting.settings import FitConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402


def decided_now(run: Path) -> dict:
    """The decision the default settings take on a fit written before the fit recorded it: from its report's
    per-frame residuals at the record's 512² (it was not refitted, so no ``scatter_px_after``)."""
    report = pd.read_csv(run / "init" / "report.csv")
    return silhouette_balance(torch.tensor(report["residual_px"].to_numpy()), torch.tensor(report["flagged"].to_numpy()),
                              512, FitConfig())  # fmt: skip


def row(label: str, run: Path) -> dict:
    fit = json.loads((run / "init" / "summary.json").read_text())
    recorded = "silhouette_balance" in fit
    balance = fit["silhouette_balance"] if recorded else decided_now(run)
    # refitted: the run's fit took the decision (a fit written before it was recorded used the weight as set)
    out = {"run": label, "frames": fit["frames"], "residual_px_mean": round(fit["residual_px_mean"], 3),
           "refitted": recorded and balance["factor"] > 1,
           **{k: balance.get(k) for k in ("scatter_px", "reference_px", "legs_seen", "factor", "sil_weight", "scatter_px_after")}}  # fmt: skip
    scored = run / "eval" / "summary.json"
    if scored.is_file():
        summary = json.loads(scored.read_text())
        out["resolution"] = summary["convention"]["resolution"]
        for split, kinds in summary["scores"].items():
            for kind, scores in kinds.items():
                for metric in ("psnr", "ssim", "psnr_body", "psnr_outline", "body_err_mm"):
                    if metric in scores:
                        out[f"{split}_{kind}_{metric}"] = scores[metric]
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", action="append", required=True, help="label=folder holding init/ (and eval/)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args(argv)
    rows = [row(label, Path(folder)) for label, folder in (r.split("=", 1) for r in a.run)]
    print(save_table(pd.DataFrame(rows), a.out, append=a.append).to_string())


if __name__ == "__main__":
    main()
