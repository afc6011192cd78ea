"""What the whole-workflow benchmarks share: a fresh copy of the workflow, one Snakemake command run in it
with this clone's package, and the CSV they write (``default_target.py``, ``generalization.py``,
``scene_against_settings.py``)."""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd

REPO = Path(__file__).resolve().parents[1]


def workflow_copy(work: Path) -> None:
    """The files a user's clone has that the workflow reads (over those of an earlier copy: a run in a kept
    folder resumes where it stopped)."""
    for name in ("Snakefile", "rules", "workflow", "config"):
        src = REPO / name
        if src.is_dir():
            shutil.copytree(src, work / name, dirs_exist_ok=True)
        else:
            shutil.copy(src, work / name)


def run_snakemake(work: Path, *args: str, cores: int = 2) -> float:
    """``snakemake --cores N ARGS`` in ``work`` (log: ``work/snakemake.log``); its wall seconds. Exits with
    a message naming the log when the command fails."""
    cmd = [sys.executable, "-m", "snakemake", "--cores", str(cores), *args]
    print("running", " ".join(cmd), "in", work, flush=True)
    t0 = time.perf_counter()
    with open(work / "snakemake.log", "w") as log:
        res = subprocess.run(cmd, cwd=work, stdout=log, stderr=subprocess.STDOUT,
                             env={**os.environ, "PYTHONPATH": str(REPO)})  # fmt: skip
    if res.returncode != 0:
        sys.exit(f"the workflow failed (exit {res.returncode}); see {work / 'snakemake.log'}")
    return time.perf_counter() - t0


def write_rows(path: Path, rows: list[dict]) -> None:
    """Rows of differing keys as one CSV (the union of the keys, in first-seen order)."""
    fields = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        w.writerows(rows)


def train_benchmark(work: Path, dataset: str, subject: str, stage: int) -> Path:
    """The workflow's benchmark TSV of a subject's training stage in a run folder (rules/common.smk's
    ``benchmark`` pattern, as the train rule names it)."""
    return work / f"results/benchmarks/train/{dataset}_{subject}_stage{stage}.tsv"


def eval_summary(work: Path, dataset: str, subject: str) -> Path:
    """A subject's evaluation summary in a run folder (rules/common.smk's ``eval_summary``)."""
    return work / f"results/{dataset}/{subject}/eval/summary.json"


def job_rows(work: Path, rules: tuple[str, ...] = ()) -> list[dict]:
    """One row per job of a run folder (``kind=job``), from its rules' Snakemake benchmark files
    (``results/benchmarks/{rule}/{job}.tsv``, the last run of each): wall and CPU seconds, peak memory.
    ``rules``: only these rules' jobs (default: every rule's)."""
    rows = []
    for tsv in sorted((work / "results" / "benchmarks").rglob("*.tsv")):
        rel = tsv.relative_to(work / "results" / "benchmarks")
        if rules and rel.parts[0] not in rules:
            continue
        last = pd.read_csv(tsv, sep="\t").iloc[-1]
        rows.append({"kind": "job", "rule": rel.parts[0], "job": str(rel.with_suffix("")),
                     "seconds": round(float(last["s"]), 1), "cpu_seconds": round(float(last.get("cpu_time", float("nan"))), 1),
                     "max_rss_mb": float(last.get("max_rss", float("nan")))})  # fmt: skip
    return rows
