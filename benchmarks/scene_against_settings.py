"""What a shipped subject's hand-set training settings buy over the scene analysis's own decisions.

For every synthetic subject named (default: those ``training.subjects`` sets something for), the
workflow runs twice in one fresh copy: as configured (``{name}``, its own settings) and as a new
user's subject would run (``{name}-scene``: the same capture, no settings of its own; the scene
analysis decides the exterior's room and samples). ``snakemake --cores N results/synthetic/metrics.csv``
scores both on held-out views and poses at the capture's size. One CSV row per run: the settings,
the scene's decisions, the scores and training seconds. Run from the repository root::

    PYTHONPATH=$PWD python3 benchmarks/scene_against_settings.py --reuse-builds    # ~50 min for loose, 2 cores
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import pandas as pd
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from generalization import SCORES, prepare_workflow  # noqa: E402
from workflow_run import REPO, run_snakemake  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--subjects", nargs="*", help="shipped synthetic subjects (default: those with settings)")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--reuse-builds", action="store_true", help="reuse this clone's Anny cache and MediaPipe models")
    ap.add_argument("--work", type=Path, help="folder to run in (default: a temporary one)")
    ap.add_argument("--csv", type=Path, default=REPO / "benchmarks" / "scene_against_settings.csv")
    a = ap.parse_args()
    config = yaml.safe_load((REPO / "config/config.yaml").read_text())
    own = (config.get("training") or {}).get("subjects") or {}
    names = a.subjects or sorted(own)
    shipped = config["datasets"]["synthetic"]["subjects"]
    missing = [n for n in names if n not in shipped]
    if missing or not names:
        sys.exit(f"no such shipped synthetic subjects: {missing or '(none has settings of its own)'}")
    subjects = {n: shipped[n] for n in names} | {f"{n}-scene": shipped[n] for n in names}
    work = a.work or Path(tempfile.mkdtemp(prefix="delta-scene-settings-"))
    work.mkdir(parents=True, exist_ok=True)
    prepare_workflow(work, subjects, tiny=False, reuse=a.reuse_builds)
    cfg_path = work / "config/config.yaml"
    cfg = yaml.safe_load(cfg_path.read_text())
    cfg["training"]["subjects"] = {n: own[n] for n in names if n in own}  # the configured runs keep theirs
    cfg_path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    wall = run_snakemake(work, "results/synthetic/metrics.csv", cores=a.cores)
    table = pd.read_csv(work / "results/synthetic/metrics.csv").set_index("subject")
    rows = []
    for name in subjects:
        base = name.removesuffix("-scene")
        settings = own.get(base, {}) if name == base else {}
        scene = json.loads((work / "results/synthetic" / name / "scene.json").read_text())["decisions"]
        row = {"subject": base, "run": "configured" if name == base else "scene", "settings": json.dumps(settings),
               "scene_max_dist": scene["render"]["max_dist"], "scene_samples": scene["render"]["samples"]}  # fmt: skip
        row |= {k: table.loc[name, k] for k in SCORES if k in table.columns}
        rows.append(row)
    df = pd.DataFrame(rows)
    df["wall_s"] = round(wall, 1)
    df.to_csv(a.csv, index=False)
    print(df.to_string())


if __name__ == "__main__":
    main()
