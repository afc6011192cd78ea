"""Time the workflow's own command, ``snakemake --cores 2 results/peoplesnapshot/metrics.csv``, as a user runs
it on a fresh clone with the default config, and keep what it scored.

The workflow's files are copied into a fresh folder (``--work``, a temporary one by default) and the
command runs there, with the default config plus only what the options below change:

- ``--subjects``: the People Snapshot subjects to run (default: the four the config declares; with no
  copy of the dataset configured they are its synthetic stand-ins);
- ``--preset``: the training preset (default: the config's, ``fast``);
- ``--reuse-builds``: take Anny's build cache and the converted MediaPipe models from this clone's
  ``resources/`` instead of building them in the copy (they are built once per machine: ~2 min and
  ~2 min on 2 cores, timed in their own rows when not reused).

- ``--prepared DIR``: start from an earlier run's folder (a ``--work`` of this script): its generated
  captures, converted body models and, for each subject, what comes before training (frames, parsing,
  init fit, scene analysis) are copied, so the command trains, scores and exports only — for another
  preset on the same subjects (its job rows then lack the steps it did not run).

One CSV row per job (``kind=job``: the rule, its wildcards, wall and CPU seconds and peak memory from the
rule's Snakemake benchmark file; CPU seconds hold when other work shared the cores), one per rule
(``kind=rule``: jobs and seconds summed), one per
subject (``kind=subject``: its row of the metrics table's scores), and one ``kind=total`` row: the
command's wall time, the subjects, preset, cores, the machine, and the mean row of
``results/peoplesnapshot/metrics.csv`` (its full-frame scores and their convention). Run from the
repository root::

    PYTHONPATH=$PWD python3 benchmarks/default_target.py --reuse-builds                       # the default target
    PYTHONPATH=$PWD python3 benchmarks/default_target.py --reuse-builds --subjects male-3-casual \\
        --csv benchmarks/default_target_one_subject.csv
    PYTHONPATH=$PWD python3 benchmarks/default_target.py --reuse-builds --preset balanced \\
        --csv benchmarks/default_target_balanced.csv
    PYTHONPATH=$PWD python3 benchmarks/default_target.py --reuse-builds --preset balanced --subjects male-3-casual \\
        --prepared /tmp/fast-run --csv benchmarks/default_target_balanced.csv
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
from pathlib import Path

import pandas as pd
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from workflow_run import REPO, job_rows, run_snakemake, workflow_copy, write_rows  # noqa: E402

TARGET = "results/peoplesnapshot/metrics.csv"
#: the columns of the metrics table's mean row kept in the total row
SCORES = ("source", "preset", "image", "resolution", "train_resolution", "background", "refinement",
          "test_view_psnr", "test_view_ssim", "test_view_stlpips_alex",
          "test_view_psnr_refined", "test_view_ssim_refined", "test_view_stlpips_alex_refined",
          "train_body_err_mm", "clothing_chamfer_mm")  # fmt: skip


def without_subjects(applications: dict, dropped: set[str]) -> dict:
    """The config's ``applications`` without what names a dropped People Snapshot subject: an avatar's jobs
    (``<application>.avatars``), a motion or an exterior taken from it, and the jobs that use those."""
    gone = {f"peoplesnapshot/{s}" for s in dropped}
    out = dict(applications)
    for kind in ("motions", "exteriors"):
        taken = out.get(kind) or {}
        out[kind] = {name: src for name, src in taken.items() if str(src).split(":")[0] not in gone}
        gone |= set(taken) - set(out[kind])
    for name, section in out.items():
        if isinstance(section, dict) and isinstance(section.get("avatars"), dict):
            kept = {a: [x for x in uses if x not in gone] for a, uses in section["avatars"].items() if a not in gone}
            out[name] = dict(section, avatars={a: uses for a, uses in kept.items() if uses})
    return out


def extra_config(work: Path, subjects: list[str] | None, preset: str | None, reuse: bool) -> list[str]:
    """``--configfile`` arguments for what the options change (none for the plain default)."""
    extra: dict = {}
    if subjects:
        main = yaml.safe_load((work / "config/config.yaml").read_text())
        declared = main["datasets"]["peoplesnapshot"]["subjects"]
        unknown = sorted(set(subjects) - set(declared))
        if unknown:
            sys.exit(f"--subjects: {unknown} are not declared in config/config.yaml ({sorted(declared)})")
        main["datasets"]["peoplesnapshot"]["subjects"] = {s: declared[s] for s in subjects}
        main["applications"] = without_subjects(main.get("applications", {}), set(declared) - set(subjects))
        (work / "config/config.yaml").write_text(yaml.safe_dump(main, sort_keys=False))
    if preset:
        extra["preset"] = preset
    if reuse:
        extra["body_model"] = {"anny": {"cache_dir": str(REPO / "resources" / "anny_cache")}}
        extra["preprocess"] = {"models_dir": str(REPO / "resources" / "models")}
    if not extra:
        return []
    (work / "benchmark.yaml").write_text(yaml.safe_dump(extra))
    return ["--configfile", "config/config.yaml", "benchmark.yaml"]


#: what a subject's folder holds before training, copied by ``--prepared``
BEFORE_TRAINING = ("frames.h5", "frames.json", "parsing.h5", "init", "scene.json")


def copy_prepared(source: Path, work: Path) -> None:
    """An earlier run's generated data, body models and each subject's steps before training, into ``work``
    (modification times kept, so Snakemake takes them as done)."""
    for name in ("data", "resources", "results/body"):
        if (source / name).exists():
            shutil.copytree(source / name, work / name, dirs_exist_ok=True)
    for subject in (source / "results" / "peoplesnapshot").iterdir():
        for name in BEFORE_TRAINING:
            src = subject / name
            dst = work / "results" / "peoplesnapshot" / subject.name / name
            dst.parent.mkdir(parents=True, exist_ok=True)
            if src.is_dir():
                shutil.copytree(src, dst, dirs_exist_ok=True)
            elif src.is_file():
                shutil.copy2(src, dst)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--subjects", nargs="+", help="People Snapshot subjects (default: the config's four)")
    ap.add_argument("--preset", help="training preset (default: the config's)")
    ap.add_argument("--reuse-builds", action="store_true", help="reuse this clone's Anny cache and MediaPipe models")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--work", type=Path, help="folder to run in (default: a temporary one, removed afterwards)")
    ap.add_argument("--csv", type=Path, default=REPO / "benchmarks" / "default_target.csv")
    ap.add_argument("--prepared", type=Path, help="an earlier run's folder whose steps before training are reused")
    a = ap.parse_args()
    work = a.work or Path(tempfile.mkdtemp(prefix="delta-default-"))
    work.mkdir(parents=True, exist_ok=True)
    workflow_copy(work)
    if a.prepared:
        copy_prepared(a.prepared, work)
    wall = run_snakemake(work, TARGET, *extra_config(work, a.subjects, a.preset, a.reuse_builds), cores=a.cores)
    rows = job_rows(work)
    by_rule = pd.DataFrame(rows).groupby("rule").agg(count=("seconds", "count"), seconds=("seconds", "sum"),
                                                     cpu=("cpu_seconds", "sum"))  # fmt: skip
    rows += [{"kind": "rule", "rule": r, "jobs": int(v["count"]), "seconds": round(float(v["seconds"]), 1),
              "cpu_seconds": round(float(v["cpu"]), 1)} for r, v in by_rule.iterrows()]  # fmt: skip
    table = pd.read_csv(work / TARGET)
    mean = table[table["subject"] == "mean"].iloc[0]
    subjects = [s for s in table["subject"] if s != "mean"]
    for _, row in table[table["subject"] != "mean"].iterrows():
        rows.append({"kind": "subject", "rule": "all", "subjects": row["subject"]}
                    | {k: row[k] for k in SCORES if k in row.index})  # fmt: skip
    total = {"kind": "total", "rule": "all", "seconds": round(wall, 1), "minutes": round(wall / 60, 1),
             "subjects": " ".join(subjects), "cores": a.cores, "reused_builds": a.reuse_builds,
             "prepared_from": str(a.prepared or ""),
             "machine": f"{platform.machine()} {os.cpu_count()} CPUs", "python": platform.python_version()}  # fmt: skip
    total |= {k: mean[k] for k in SCORES if k in mean.index}
    rows.append(total)
    write_rows(a.csv, rows)
    print(json.dumps(total, default=str, indent=1))
    if a.work is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
