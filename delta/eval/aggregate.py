"""``results/{dataset}/metrics.csv``: one row per subject plus a ``mean`` row.

Columns: the convention (preset, stage, background, image — the full frame —, resolution scored at,
training resolution, supersampling, data range, perceptual metric, test-time refinement),
wall time and peak memory of each training stage (from the rules' benchmark files), the
mean of every score per test split — ``{split}_{score}`` before test-time refinement and
``{split}_{score}_refined`` after it, with the refinement's steps taken and its loss before and after
(``{split}_refine_steps_refined``, ``{split}_refine_loss_start_refined``, ``..._end_refined``) — the body error
(and a tracked face's expression error, ``train_expr_*``) over the training frames, and the
export's numbers (``export_*``: mesh sizes, line-up IoUs), and the clothing surface against ground
truth where there is one (``clothing_*``: Chamfer / normal consistency, sample to sample, and the exact
point-to-surface distance ``clothing_p2s_*``).
"""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from delta import DeltaError
from delta.io import atomic_path, load_json


#: the parts of export.json that become columns
EXPORT_KEYS = ("body", "clothing", "lineup")


def _flatten(d: dict, prefix: str) -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}_{k}"
        if isinstance(v, dict):
            out |= _flatten(v, key)
        elif isinstance(v, bool):
            out[key] = v
        elif isinstance(v, (int, float)) or v is None:
            out[key] = float("nan") if v is None else v
    return out


def benchmark_row(path: str | Path) -> dict:
    """Wall seconds and peak RSS (MB) from a Snakemake benchmark TSV (the last repeat)."""
    try:
        df = pd.read_csv(path, sep="\t")
    except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError) as e:
        raise DeltaError(f"{path}: not a Snakemake benchmark file ({e})") from None
    if "s" not in df.columns or df.empty:
        raise DeltaError(f"{path}: no 's' column; not a Snakemake benchmark file")
    last = df.iloc[-1]
    return {"s": round(float(last["s"]), 1), "max_rss_mb": float(last.get("max_rss", math.nan))}


def subject_row(dataset: str, subject: str, summary: dict, export: dict | None, benchmarks: dict[str, str]) -> dict:
    row = {"dataset": dataset, "subject": subject, "preset": summary.get("preset"), "stage": summary.get("stage"),
           "refine_steps": summary.get("settings", {}).get("refine_steps")}  # fmt: skip
    row |= summary.get("convention", {})
    for rule, path in sorted(benchmarks.items()):
        b = benchmark_row(path)
        row[f"{rule}_s"], row[f"{rule}_max_rss_mb"] = b["s"], b["max_rss_mb"]
    for split, passes in summary.get("scores", {}).items():
        for name, scores in passes.items():
            tag = "_refined" if name == "refined" else ""
            for k, v in scores.items():
                row[f"{split}_{k}{tag}"] = math.nan if v is None else v
    for key in ("train_body_err_mm", "train_body_err_pa_mm", "train_expr_mae", "train_expr_err_mm"):
        if key in summary:
            row[key] = summary[key]
    row |= {k: v for k, v in summary.get("geometry", {}).items() if isinstance(v, (int, float))}
    row["eval_s"] = summary.get("seconds")
    if export:  # mesh sizes and line-up IoUs; the export's own settings and per-frame lists stay in its json
        row |= _flatten({k: export[k] for k in EXPORT_KEYS if k in export}, "export")
        row["export_s"] = export.get("seconds", {}).get("total")
    return row


def aggregate(dataset: str, subjects: list[str], summaries: list[str], exports: list[str], benchmarks: list[str],
              out: str | Path, source: str = "") -> pd.DataFrame:  # fmt: skip
    """Write ``out``; ``benchmarks`` are ``SUBJECT/RULE=PATH``; ``source`` (what the figures were measured
    on) goes in a column of every row."""
    if len(summaries) != len(subjects) or (exports and len(exports) != len(subjects)):
        raise DeltaError(
            f"aggregate: {len(subjects)} subjects but {len(summaries)} summaries and {len(exports)} exports"
        )
    bench: dict[str, dict[str, str]] = {s: {} for s in subjects}
    for item in benchmarks:
        key, _, path = item.partition("=")
        subject, _, rule = key.partition("/")
        if not path or subject not in bench:
            raise DeltaError(f"aggregate: benchmark '{item}' is not SUBJECT/RULE=PATH for a listed subject")
        bench[subject][rule] = path
    rows = [subject_row(dataset, s, load_json(summaries[i]), load_json(exports[i]) if exports else None, bench[s])
            for i, s in enumerate(subjects)]  # fmt: skip
    df = pd.DataFrame(rows)
    numeric = df.select_dtypes("number").columns.drop(["stage", "refine_steps"], errors="ignore")
    mean = {"dataset": dataset, "subject": "mean"} | df[numeric].mean().to_dict()
    same = [c for c in df.columns if c not in ("dataset", "subject") and c not in numeric and df[c].nunique() == 1]
    mean |= {c: df[c].iloc[0] for c in ["stage", "refine_steps", *same] if c in df and df[c].nunique() == 1}
    df = pd.concat([df, pd.DataFrame([mean])], ignore_index=True)
    if source:
        df.insert(2, "source", source)
    with atomic_path(out) as tmp:
        df.to_csv(tmp, index=False)
    return df
