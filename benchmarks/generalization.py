"""Generalisation: a family of synthetic subjects the config does not hold, each run with the default
config and no settings of its own, scored on held-out views and held-out poses at the capture's size.

The script draws the family (``--count`` subjects, 8 by default, from ``--seed``): each crosses a top
(T-shirt, long sleeves, a dress), a bottom (trousers, shorts, a skirt; none under a dress), a pattern,
hair (none, short, long), a phenotype and a camera model (pinhole with lens distortion, or
orthographic), with a generator seed of its own, cycling through the garment and camera choices so
that every one appears. It copies the workflow into a fresh folder (``--work``), replaces the
synthetic dataset's subjects with the family and drops every per-subject training setting (what a
user's new subject gets), and runs ``snakemake --cores N results/synthetic/metrics.csv`` there.

One CSV row per subject (its description, held-out-view and held-out-pose PSNR / SSIM / ST-LPIPS before
and after test-time refinement, the scoring resolution, body error, clothing Chamfer, training seconds,
and the scene analysis's decisions), then a ``summary`` row: the mean, the spread (best - worst) and the
worst subject of each PSNR column, and how many subjects lie within 2 dB of the best. Run from the
repository root::

    PYTHONPATH=$PWD python3 benchmarks/generalization.py --reuse-builds                # ~20-30 min a subject on 2 cores

``--training '{"resolution": 512}'`` runs every subject with those training overrides (a variant; the
rows name it in ``training``). A kept ``--work`` folder resumes: run again with it (and fewer subjects, say) and only what is missing runs.
    PYTHONPATH=$PWD python3 benchmarks/generalization.py --reuse-builds --tiny --count 2 \\
        --csv /tmp/generalization_tiny.csv                                               # the script's own check

A family run in parts (``--only``, one CSV a part) becomes one table with ``--combine part1.csv part2.csv``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from workflow_run import REPO, eval_summary, run_snakemake, train_benchmark, workflow_copy, write_rows  # noqa: E402

from delta.eval.aggregate import subject_row  # noqa: E402

TOPS = ("tshirt", "longsleeve", "dress")
BOTTOMS = ("trousers", "shorts", "skirt")
PATTERNS = ("stripes", "checker", "dots", "plaid", "plain")
HAIR = ("none", "short", "long")
CAMERAS = ("pinhole", "orthographic")
SCORES = ("test_view_psnr", "test_view_psnr_refined", "test_pose_psnr", "test_pose_psnr_refined",
          "test_view_ssim", "test_view_stlpips_alex", "test_pose_ssim", "test_pose_stlpips_alex",
          "train_body_err_mm", "clothing_chamfer_mm", "stage1_s", "stage2_s", "resolution")  # fmt: skip
#: the tiny configuration's sizes (the script's own check, not a measurement)
TINY = {"resolution": 64, "turn_frames": 8, "novel_frames": 2, "test_view_every": 4}
TINY_TRAINING = {"resolution": 32, "render": {"samples": 8},
                 "stage1": {"iterations": 6, "rays": 128, "checkpoint_every": 3, "preview_every": 0},
                 "stage2": {"iterations": 4, "rays": 128, "patch": 16, "checkpoint_every": 2, "preview_every": 0}}  # fmt: skip


def family(count: int, seed: int) -> dict[str, dict]:
    """``count`` subject specs, named ``gen{k}``: every top, bottom and camera appears (they cycle), the
    rest is drawn."""
    rng = np.random.default_rng(seed)
    outfits = [(t, None if t == "dress" else b) for t, b in itertools.product(TOPS, BOTTOMS)]
    outfits = list(dict.fromkeys(outfits))  # a dress has no bottom: one entry
    rng.shuffle(outfits)
    out = {}
    for k in range(count):
        top, bottom = outfits[k % len(outfits)]
        garments = [{"kind": top, "pattern": str(rng.choice(PATTERNS))}]
        if bottom:
            garments.append({"kind": bottom, "pattern": str(rng.choice(PATTERNS))})
        camera = CAMERAS[k % len(CAMERAS)]
        spec = {"seed": int(rng.integers(100, 10_000)), "garments": garments, "hair": str(rng.choice(HAIR)),
                "camera": camera,
                "phenotype": {"gender": round(float(rng.uniform(0, 1)), 2), "age": round(float(rng.uniform(0.2, 0.6)), 2),
                              "weight": round(float(rng.uniform(0.3, 0.7)), 2), "height": round(float(rng.uniform(0.3, 0.7)), 2)}}  # fmt: skip
        if camera == "pinhole":
            spec["distortion"] = [round(float(rng.uniform(-0.06, 0.0)), 3), 0.01, 0.0, 0.0, 0.0]
        out[f"gen{k}"] = spec
    return out


def describe(spec: dict) -> str:
    clothes = " + ".join(f"{g['kind']} ({g['pattern']})" for g in spec["garments"])
    return f"{clothes}, hair {spec['hair']}, {spec['camera']}"


def prepare_workflow(work: Path, subjects: dict[str, dict], tiny: bool, reuse: bool, training: dict) -> list[str]:
    workflow_copy(work)
    main = yaml.safe_load((work / "config/config.yaml").read_text())
    main["datasets"] = {"synthetic": {"subjects": {n: (s | TINY if tiny else s) for n, s in subjects.items()}}}
    main.setdefault("training", {})["subjects"] = {}  # a new subject has no settings of its own
    main.setdefault("fitting", {}).pop("subjects", None)
    main.pop("applications", None)  # they name the shipped subjects; scored here: the avatars themselves
    if training:  # one variant for every subject, as a user's training.overrides
        main["training"]["overrides"] = training
    if tiny:
        main["training"]["overrides"] = TINY_TRAINING
        main["preprocess"]["resolution"] = 64
        main["body_model"]["anny"].update({"num_shape": 8, "num_samples": 64})
        main["fitting"]["settings"] = {"iterations": [20, 30, 20]}
    if reuse:
        main["body_model"]["anny"]["cache_dir"] = str(REPO / "resources" / "anny_cache")
        main["preprocess"]["models_dir"] = str(REPO / "resources" / "models")
    (work / "config/config.yaml").write_text(yaml.safe_dump(main, sort_keys=False))
    return []


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--count", type=int, default=8)
    ap.add_argument("--only", nargs="*", help="run only these of the family (names gen0, gen1, ...)")
    ap.add_argument(
        "--shipped",
        nargs="*",
        default=[],
        help="shipped synthetic subjects run beside the family, as the config holds them (no settings of their own)",
    )
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--tiny", action="store_true", help="tiny sizes: checks the script, measures nothing")
    ap.add_argument("--reuse-builds", action="store_true", help="reuse this clone's Anny cache and MediaPipe models")
    ap.add_argument("--work", type=Path, help="folder to run in (default: a temporary one, removed afterwards)")
    ap.add_argument("--csv", type=Path, default=REPO / "benchmarks" / "generalization.csv")
    ap.add_argument(
        "--training", type=json.loads, default={}, help="JSON training.overrides for every subject (a variant)"
    )
    ap.add_argument("--scores-only", action="store_true",
                    help="run each subject to its evaluation, not its videos (the table's figures, ~9 min less a subject)")  # fmt: skip
    ap.add_argument("--combine", type=Path, nargs="+", metavar="CSV",
                    help="run nothing: write --csv from these runs' CSVs (parts of one family), with one summary")  # fmt: skip
    a = ap.parse_args()
    if a.combine:
        return combine(a.combine, a.csv)
    drawn = family(a.count, a.seed)
    shipped = yaml.safe_load((REPO / "config/config.yaml").read_text())["datasets"]["synthetic"]["subjects"]
    for flag, names, known in (("--shipped", a.shipped, shipped), ("--only", a.only or [], drawn)):
        if unknown := [n for n in names if n not in known]:
            sys.exit(f"{flag}: {unknown} not among {sorted(known)}")
    subjects = {n: s for n, s in drawn.items() if a.only is None or n in a.only} | {n: shipped[n] for n in a.shipped}
    work = a.work or Path(tempfile.mkdtemp(prefix="delta-generalization-"))
    work.mkdir(parents=True, exist_ok=True)
    prepare_workflow(work, subjects, a.tiny, a.reuse_builds, a.training)
    print(f"{len(subjects)} subjects:", json.dumps({n: describe(s) for n, s in subjects.items()}, indent=1), flush=True)
    if a.scores_only:
        targets = [str(eval_summary(Path(), "synthetic", n)) for n in subjects]
        wall = run_snakemake(work, *targets, cores=a.cores)
        table = scores_table(work, list(subjects))
    else:
        wall = run_snakemake(work, "results/synthetic/metrics.csv", cores=a.cores)
        table = pd.read_csv(work / "results/synthetic/metrics.csv").set_index("subject")
    rows = []
    for name, spec in subjects.items():
        row = {"subject": name, "description": describe(spec) + (" (shipped)" if name in a.shipped else ""),
               "seed": spec["seed"], "camera": spec["camera"], "hair": spec.get("hair", "none"), "tiny": a.tiny,
               "training": json.dumps(a.training) if a.training else "default"}  # fmt: skip
        row |= {k: table.loc[name, k] for k in SCORES if k in table.columns}
        scene = json.loads((work / "results/synthetic" / name / "scene.json").read_text())["decisions"]
        row |= {"scene_max_dist": scene["render"]["max_dist"], "scene_samples": scene["render"]["samples"],
                "scene_stage2_factor": scene.get("stage2", {}).get("length_factor"),
                "scene_exterior": scene["exterior"], "scene_capture": scene["capture"]}  # fmt: skip
        rows.append(row)
    summary = summary_row(pd.DataFrame(rows), f"{len(rows)} subjects, seed {a.seed}", a.tiny, wall)
    write_rows(a.csv, rows + [summary])
    print(json.dumps(summary, indent=1, default=str))
    if a.work is None:
        shutil.rmtree(work, ignore_errors=True)


def scores_table(work: Path, names: list[str]) -> pd.DataFrame:
    """The dataset table's rows of ``names`` (by subject) from their evaluations and training benchmarks
    alone, as the workflow's ``aggregate_metrics`` writes them less the export's columns."""
    rows = []
    for n in names:
        bench = {f"stage{k}": train_benchmark(work, "synthetic", n, k) for k in (1, 2)}
        summary = json.loads(eval_summary(work, "synthetic", n).read_text())
        rows.append(subject_row("synthetic", n, summary, None, bench))
    return pd.DataFrame(rows).set_index("subject")


def summary_row(df: pd.DataFrame, description: str, tiny: bool, wall: float) -> dict:
    """The ``summary`` row of subject rows: each PSNR column's mean, spread (best - worst), worst subject and
    how many subjects lie within 2 dB of the best."""
    summary: dict = {"subject": "summary", "description": description, "tiny": tiny, "wall_s": round(wall, 1)}
    for col in ("test_view_psnr", "test_view_psnr_refined", "test_pose_psnr", "test_pose_psnr_refined"):
        if col in df:
            summary[f"{col}_mean"] = round(float(df[col].mean()), 2)
            summary[f"{col}_spread"] = round(float(df[col].max() - df[col].min()), 2)
            summary[f"{col}_worst"] = f"{df.loc[df[col].idxmin(), 'subject']} {df[col].min():.2f}"
            summary[f"{col}_within_2db_of_best"] = int((df[col] >= df[col].max() - 2).sum())
    return summary


def natural(name: str) -> tuple[str, int]:
    """A subject's sort key: gen2 before gen10."""
    stem = name.rstrip("0123456789")
    return stem, int(name[len(stem) :] or -1)


def combine(parts: list[Path], out: Path) -> None:
    """One table from the CSVs of runs of parts of the family (a subject in a later file replaces the same
    subject in an earlier one), with one summary over all its subjects; the parts' wall times add up."""
    tables = [pd.read_csv(p) for p in parts]
    subjects = pd.concat([t[t.subject != "summary"] for t in tables], ignore_index=True)
    subjects = subjects.drop_duplicates("subject", keep="last")
    subjects = subjects.iloc[sorted(range(len(subjects)), key=lambda i: natural(subjects["subject"].iloc[i]))]
    subjects = subjects.dropna(axis=1, how="all")  # the parts' summary-only columns
    wall = sum(float(t.loc[t.subject == "summary", "wall_s"].sum()) for t in tables)
    tiny = bool(subjects["tiny"].any()) if "tiny" in subjects else False
    rows = subjects.to_dict("records")
    summary = summary_row(subjects, f"{len(rows)} subjects, from {len(parts)} runs", tiny, wall)
    write_rows(out, rows + [summary])
    print(json.dumps(summary, indent=1, default=str))


if __name__ == "__main__":
    main()
