"""Peak memory of each stage at a training resolution: both training stages and the evaluation, each a
`delta` command in its own process, its maximum resident set size read from the OS. A few steps show
the peak (the frames are loaded and every per-step buffer is live by the first step), so the stages
run shortened; the evaluation scores --frames held-out frames at the capture's size with refinement.

    python benchmarks/stage_memory.py --subject tight --resolution 512 --out benchmarks/stage_memory.csv
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def run(cmd: list[str]) -> tuple[float, float]:
    """(seconds, peak RSS in MB) of one command, the only child of this process (the OS reports the
    largest child's peak)."""
    t = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--subject", default="tight")
    ap.add_argument("--dataset", default="synthetic")
    ap.add_argument("--body", default=str(ROOT / "resources/body/anny_sub1.npz"))
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--resolution", type=int, default=512)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--stage", choices=["1", "2", "eval"], required=True,
                    help="one measurement a process (the OS reports the largest child's peak)")  # fmt: skip
    ap.add_argument("--train-settings", default="{}",
                    help="the workflow's --settings JSON of the subject's train job (its config keys: a head's layers, "
                    "weights); the shortened steps and --resolution go over it")  # fmt: skip
    ap.add_argument(
        "--scene", default=None, help="the subject's scene.json, passed to delta train as the workflow does"
    )
    ap.add_argument("--eval-settings", default="{}", help="JSON over the evaluation's shortened settings")
    ap.add_argument("--work", default=None, help="folder for the shortened stages (kept between --stage runs)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args()
    res = ROOT / "results" / a.dataset / a.subject
    work = Path(a.work or tempfile.mkdtemp(prefix="stage_memory_"))
    common = ["--record", str(res / "frames.h5"), "--body", a.body, "--threads", str(a.threads)]
    given = json.loads(a.train_settings)
    fixed = {"resolution", "stage1.iterations", "stage2.iterations"}  # not the scene's to decide here
    short = {"resolution": a.resolution, "user_set": sorted({*given.get("user_set", []), *fixed})}
    for k in ("stage1", "stage2"):
        short[k] = {**given.get(k, {}), "iterations": a.steps}
    settings = json.dumps({**given, "preset": given.get("preset", a.preset), **short})
    scene = ["--scene", a.scene] if a.scene else []
    if a.stage == "1":
        cmd = ["delta", "train", "--stage", "1", "--start", str(res / "init/params.npz"), "--out", str(work / "stage1")]
        cmd += ["--settings", settings, *scene, *common]
    elif a.stage == "2":
        cmd = [
            "delta",
            "train",
            "--stage",
            "2",
            "--start",
            str(work / "stage1/model.pt"),
            "--out",
            str(work / "stage2"),
        ]
        cmd += ["--settings", settings, *scene, "--perceptual", str(ROOT / "resources/models/stlpips"), *common]
    else:
        ev = {"max_frames": a.frames, "refine_steps": 30, "splits": ["test_view"], "supersample": 2}
        ev.update(json.loads(a.eval_settings))
        cmd = ["delta", "evaluate", "--model", str(work / "stage2/model.pt"), "--subject", a.subject,
               "--out", str(work / "metrics.csv"), "--settings", json.dumps(ev), *common]  # fmt: skip
    seconds, peak = run(cmd)
    row = {"subject": a.subject, "preset": a.preset, "train_resolution": a.resolution, "stage": a.stage,
           "steps": a.steps if a.stage != "eval" else 0, "frames": a.frames if a.stage == "eval" else 0,
           "seconds": round(seconds, 1), "max_rss_mb": round(peak, 1), "threads": a.threads}  # fmt: skip
    print(row, flush=True)
    save_table(pd.DataFrame([row]), a.out, a.append)


if __name__ == "__main__":
    main()
