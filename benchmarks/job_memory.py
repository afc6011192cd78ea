"""Peak memory and time of a run's jobs, from the Snakemake benchmark files its rules write
(``results/benchmarks/{rule}/{job}.tsv``; the last run of each job), against the 4-GB budget a job at the
capture's size is held to (docs/development.md, "Memory").

The applications' jobs of the default config, and of the heads' made in another folder (after the
workflow has made them; docs/development.md has the commands)::

    PYTHONPATH=$PWD python3 benchmarks/job_memory.py --rules animate dress reshape tryon reenact \\
        --label "the default config's, fast" --out benchmarks/application_memory.csv
    PYTHONPATH=$PWD python3 benchmarks/job_memory.py --work /tmp/headmem --rules dress reenact \\
        --label "heads, 30 steps a stage" --out benchmarks/application_memory.csv --append

Each row: the rule, the job (``{rule}/{dataset}_{subject}_{variant}``), wall and CPU seconds, peak
resident memory (MB), ``--label``, whether it is under the budget, the resolution it rendered at where its
summary names it, and the machine. Exits non-zero when a job is over the budget or no job matched.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402
from workflow_run import REPO, job_rows  # noqa: E402

BUDGET_MB = 4096.0


def rendered_resolutions(work: Path) -> dict[str, str]:
    """Job -> the ``WxH`` its summary says it rendered at, for every summary
    ``results/{dataset}/{subject}/{rule}/{variant}/*.json`` of a run folder that names one."""
    out = {}
    for summary in (work / "results").glob("*/*/*/*/*.json"):
        dataset, subject, rule, variant = summary.parts[-5:-1]
        data = json.loads(summary.read_text())
        resolution = data.get("resolution") if isinstance(data, dict) else None
        if isinstance(resolution, str):
            out[f"{rule}/{dataset}_{subject}_{variant}"] = resolution
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=REPO, help="the run's folder (default: this clone)")
    ap.add_argument("--rules", nargs="+", default=[], help="only these rules' jobs (default: every rule's)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--label", default="", help="what the rows' run was (written in a column)")
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args()
    rows = job_rows(a.work, tuple(a.rules))
    if not rows:
        sys.exit(f"no benchmark file of {a.rules or 'any rule'} under {a.work / 'results' / 'benchmarks'}")
    machine = f"{platform.machine()} {os.cpu_count()} CPUs"
    resolutions = rendered_resolutions(a.work)
    for row in rows:
        row |= {"label": a.label, "under_budget": row["max_rss_mb"] < BUDGET_MB,
                "resolution": resolutions.get(row["job"], ""), "machine": machine}  # fmt: skip
    table = pd.DataFrame(rows).drop(columns="kind")
    save_table(table, a.out, append=a.append)
    print(table.to_string(index=False))
    if not table["under_budget"].all():
        sys.exit(f"over {BUDGET_MB:.0f} MB: {', '.join(table.loc[~table['under_budget'], 'job'])}")


if __name__ == "__main__":
    main()
