"""A training step's time and a stage's peak memory with the host's allocator holding freed memory
(``delta.host_memory``, what every ``delta`` command does) and with glibc's own settings, written as CSV.

Each run is its own process (the allocator is set once a process): a fresh stage 1 from a run's
settings.json and init fit, ``--steps`` training steps, the mean seconds a step after the first
``--skip`` (the trainer's clock) and the process's peak RSS. The variants alternate, ``--repeats`` times,
so that a machine's changing pace falls on both. Run it on a quiet machine.

    python benchmarks/host_allocator.py --settings results/synthetic/loose/stage1/settings.json \\
        --init results/synthetic/loose/init/params.npz --record results/synthetic/loose/frames.h5 \\
        --body resources/body/anny_sub1.npz --subject loose --out benchmarks/host_allocator.csv
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402

VARIANTS = {"hold": "freed memory held (every delta command)", "system": "glibc's own settings"}


def child(a: argparse.Namespace) -> None:
    """One run in this process: print its step time and peak RSS as one JSON line."""
    import resource

    import torch

    from delta.host_memory import hold_freed_memory
    from delta.training.trainer import train_stage
    from step_profile import fresh_model

    held = hold_freed_memory()
    torch.set_num_threads(a.threads)
    override = json.loads(a.override)
    override.setdefault("stage1", {})["checkpoint_every"] = 10**9  # no checkpoint inside the timed steps
    m = fresh_model(a.settings, json.dumps(override), a.record, a.body, a.init, "cpu")
    with tempfile.TemporaryDirectory() as out:
        res = train_stage(1, m.model, m.data, m.settings, Path(out), None, max_steps=a.steps, origin="bench")
    sec = res.losses["seconds"].to_numpy()
    per_step = (sec[-1] - sec[a.skip - 1]) / (len(sec) - a.skip)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # kB on Linux
    print(json.dumps({"held": held, "seconds_per_step": round(float(per_step), 4), "peak_rss_gb": round(peak, 3)}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--settings", required=True, help="a stage 1's settings.json")
    ap.add_argument("--init", required=True, help="the subject's init/params.npz")
    ap.add_argument("--record", required=True)
    ap.add_argument("--body", required=True)
    ap.add_argument("--subject", required=True)
    ap.add_argument("--override", default="{}", help="JSON settings merged over the run's")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--skip", type=int, default=10, help="steps left out of the mean (the first ones)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--label", default="", help="a name for the runs' settings in the CSV")
    ap.add_argument("--out", help="CSV to write")
    ap.add_argument("--append", action="store_true")
    ap.add_argument("--child", choices=sorted(VARIANTS), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if not 0 < a.skip < a.steps:
        ap.error(f"--skip {a.skip}: expected 0 < skip < steps ({a.steps})")
    if a.child:
        return child(a)
    if not a.out:
        ap.error("--out is required")
    rows = []
    for rep in range(a.repeats):
        for variant, meaning in VARIANTS.items():
            env = {**os.environ, "DELTA_HOST_MALLOC": variant}
            cmd = [sys.executable, __file__, "--child", variant, *sys.argv[1:]]
            res = subprocess.run(cmd, env=env, capture_output=True, text=True)
            if res.returncode:
                raise SystemExit(f"{variant} run {rep + 1} failed:\n{res.stderr[-3000:]}")
            got = json.loads(res.stdout.strip().splitlines()[-1])
            if got["held"] != (variant == "hold"):
                raise SystemExit(f"{variant} run {rep + 1}: the allocator held freed memory: {got['held']}")
            rows.append({"subject": a.subject, "settings": a.label or ("the run's own" if a.override == "{}" else a.override), "variant": variant,
                         "allocator": meaning, "repeat": rep + 1, "steps": a.steps, "skipped": a.skip,
                         "seconds_per_step": got["seconds_per_step"], "peak_rss_gb": got["peak_rss_gb"],
                         "device": f"cpu ({a.threads} threads)"})  # fmt: skip
            print(rows[-1], flush=True)
    save_table(pd.DataFrame(rows), a.out, append=a.append)


if __name__ == "__main__":
    main()
