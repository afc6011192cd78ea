"""The tiny workflow on the one-node SLURM that run_slurm_test.sh starts.

1. The .test configuration end to end through ``--executor slurm`` and locally: every output equal.
2. A stage-1 training job scancel'ed after its first checkpoints: the profile's retry resubmits it, it
   resumes from the checkpoint, and its model and losses equal those of a run never killed.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import torch
from delta.io import load_state
import yaml

SLURM = [
    "--executor", "slurm", "--profile", "workflow/profiles/slurm",
    # no accounting database on this cluster: squeue answers (slurm.conf's MinJobAge keeps finished jobs listed)
    "--slurm-status-command", "squeue", "--slurm-init-seconds-before-status-checks", "5",
]  # fmt: skip
#: Training on one thread in both runs. With 2 OpenMP threads two runs of the same training job on the same
#: machine differ in the last bits of a few parameters and Adam moments (run to run, SLURM or not; MKL_CBWR
#: does not change it: ATen's threaded CPU kernels); on 1 thread they are bitwise equal, so the comparison
#: can be exact. The other rules' outputs compared bitwise equal on 2 threads.
THREADS = ["--set-threads", "train=1"]
#: Compared file trees, and what they may differ in: wall-clock figures.
TREES = ("data", "resources/body", "results")
SKIPPED = ("results/benchmarks/",)
TIMING_KEY = re.compile(r"seconds|time|elapsed")
#: A stage-1 job long enough to be killed mid-run, checkpointed every few steps, on one thread (bitwise reproducible).
KILL_STAGE1 = {"iterations": 60, "checkpoint_every": 5, "preview_every": 0}
KILL_DATASET, KILL_SUBJECT = "synthetic", "loose"


def workflow_copy(src_root: Path, dst: Path) -> Path:
    """The workflow's files in a fresh directory, as a user's clone has them."""
    shutil.rmtree(dst, ignore_errors=True)
    dst.mkdir(parents=True)
    for name in ("Snakefile", "rules", "workflow", "config", ".test"):
        src = src_root / name
        (shutil.copytree if src.is_dir() else shutil.copy)(src, dst / name)
    return dst


def tiny_config(repo: Path, work: Path, stage1: dict | None = None) -> str:
    """The .test configuration, reusing the repository's Anny build, converted models and perceptual weights."""
    cfg = yaml.safe_load((work / ".test/config/config.yaml").read_text())
    cfg["body_model"]["anny"]["cache_dir"] = str(repo / "resources/anny_cache")
    cfg["preprocess"]["models_dir"] = str(repo / "resources/models")
    cfg["training"]["perceptual_dir"] = str(repo / "resources/models/stlpips")
    if stage1:
        cfg["training"]["overrides"]["stage1"].update(stage1)
    (work / "cluster-test.yaml").write_text(yaml.safe_dump(cfg))
    return "cluster-test.yaml"


def snakemake(work: Path, *args: str, log: str) -> float:
    """Run snakemake in ``work`` (output to ``work/log``); the wall time in seconds."""
    t0 = time.time()
    with open(work / log, "w") as out:
        res = subprocess.run([sys.executable, "-m", "snakemake", *args], cwd=work, stdout=out, stderr=subprocess.STDOUT)
    if res.returncode != 0:
        sys.exit(f"snakemake failed in {work}, see {work / log}:\n" + (work / log).read_text()[-3000:])
    return time.time() - t0


# ------------------------------------------------------------ comparisons
def differences(a, b, path: str = "") -> list[str]:
    """Where ``a`` and ``b`` differ, with by how much; [] when equal.

    Tensors and arrays bitwise (NaN equal to NaN in the same place, dtype and shape included), dict keys
    naming wall-clock figures (TIMING_KEY) left out, anything else with ``==``.
    """
    if isinstance(a, (torch.Tensor, np.ndarray)):
        kind = torch.Tensor if isinstance(a, torch.Tensor) else np.ndarray
        if not isinstance(b, kind) or a.dtype != b.dtype or tuple(a.shape) != tuple(b.shape):
            return [
                f"{path}: {a.dtype}{tuple(a.shape)} vs {getattr(b, 'dtype', type(b).__name__)}{tuple(getattr(b, 'shape', ()))}"
            ]
        x, y = (a.detach().cpu().numpy(), b.detach().cpu().numpy()) if kind is torch.Tensor else (a, b)
        if x.dtype.kind not in "fc":
            same = x == y
        else:
            same = (x == y) | (np.isnan(x) & np.isnan(y))
        if np.all(same):
            return []
        if x.dtype.kind in "fc":
            d = np.abs(x.astype(np.float64) - y.astype(np.float64))[~same]
            rel = d / np.maximum(np.abs(x.astype(np.float64))[~same], 1e-300)
            return [
                f"{path}: {int((~same).sum())}/{x.size} values differ, max abs {np.nanmax(d):.3g}, max rel {np.nanmax(rel):.3g}"
            ]
        return [f"{path}: {int((~np.asarray(same)).sum())}/{x.size} values differ"]
    if isinstance(a, dict):
        if not isinstance(b, dict):
            return [f"{path}: dict vs {type(b).__name__}"]
        keep = lambda d: {k for k in d if not (isinstance(k, str) and TIMING_KEY.search(k))}  # noqa: E731
        ka, kb = keep(a), keep(b)
        out = [f"{path}/{k}: only in one" for k in sorted(map(str, ka ^ kb))]
        return out + [p for k in ka & kb for p in differences(a[k], b[k], f"{path}/{k}")]
    if isinstance(a, (list, tuple)):
        if type(a) is not type(b) or len(a) != len(b):
            return [
                f"{path}: {type(a).__name__} of {len(a)} vs {type(b).__name__} of {len(b) if hasattr(b, '__len__') else '?'}"
            ]
        return [p for i, (x, y) in enumerate(zip(a, b)) for p in differences(x, y, f"{path}[{i}]")]
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return []
    return [] if a == b else [f"{path}: {a!r:.80} vs {b!r:.80}"]


def h5_content(path: Path) -> dict:
    items = {}
    with h5py.File(path) as f:
        f.visititems(lambda name, obj: items.__setitem__(name, obj[()] if isinstance(obj, h5py.Dataset) else None))
        f.visititems(lambda name, obj: items.update({f"{name}@{k}": v for k, v in obj.attrs.items()}))
        items.update({f"@{k}": v for k, v in f.attrs.items()})
    return {k: np.asarray(v) if v is not None else None for k, v in items.items()}


def csv_content(path: Path) -> list[dict]:
    """A CSV's rows without its wall-clock columns (losses.csv's ``seconds``), values as written."""
    with open(path, newline="") as f:
        return [{k: v for k, v in row.items() if not TIMING_KEY.search(k or "")} for row in csv.DictReader(f)]


def file_differences(a: Path, b: Path) -> list[str]:
    """Where two files' contents differ: arrays and tensors bitwise, JSON and CSV without wall-clock keys
    and columns, anything else byte for byte."""
    ext = a.suffix
    if ext in (".h5", ".hdf5"):
        return differences(h5_content(a), h5_content(b))
    if ext == ".npz":
        with np.load(a) as x, np.load(b) as y:
            return differences(dict(x), dict(y))
    if ext == ".pt":
        return differences(load_state(a), load_state(b))
    if ext == ".json":
        return differences(json.loads(a.read_text()), json.loads(b.read_text()))
    if ext == ".csv":
        return differences(csv_content(a), csv_content(b))
    return [] if a.read_bytes() == b.read_bytes() else ["bytes differ"]


def compare_trees(a: Path, b: Path) -> list[str]:
    """Problems between two runs' outputs; [] when every file exists in both with equal content."""

    def files(root):
        return {str(p.relative_to(root)) for t in TREES for p in (root / t).rglob("*")
                if p.is_file() and not str(p.relative_to(root)).startswith(SKIPPED)}  # fmt: skip

    fa, fb = files(a), files(b)
    problems = [f"only in {a.name}: {p}" for p in sorted(fa - fb)] + [f"only in {b.name}: {p}" for p in sorted(fb - fa)]
    for p in sorted(fa & fb):
        problems += [f"differs: {p}{d}" for d in file_differences(a / p, b / p)[:5]]
    print(f"compared {len(fa & fb)} files of {TREES} (benchmark timings left out)")
    return problems


# ------------------------------------------------------------ the scancel test
def stage1_dir(work: Path) -> Path:
    return work / "results" / KILL_DATASET / KILL_SUBJECT / "stage1"


def copy_without_training(src: Path, dst: Path) -> Path:
    """A finished run's directory with its training outputs (and their checkpoints) removed."""
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(src, dst, symlinks=True)
    for stage in dst.glob("results/*/*/stage[12]"):
        shutil.rmtree(stage)
    return dst


def kill_when_checkpointed(work: Path, proc: subprocess.Popen) -> int:
    """scancel the running training job once it has written a checkpoint; the checkpoint's step."""
    ckpt = stage1_dir(work) / "checkpoint.pt"
    deadline = time.time() + 900
    while not ckpt.exists():
        if proc.poll() is not None or time.time() > deadline:
            sys.exit("the training job never wrote a checkpoint")
        time.sleep(0.2)
    jobs = subprocess.run(["squeue", "-h", "-t", "RUNNING", "-o", "%i"], capture_output=True, text=True, check=True)
    ids = jobs.stdout.split()
    assert len(ids) == 1, f"expected one running job, squeue lists {ids}"
    subprocess.run(["scancel", ids[0]], check=True)
    step = load_state(ckpt)["step"]
    print(f"scancel {ids[0]} with the checkpoint at step {step} of {KILL_STAGE1['iterations']}")
    return step


def scancel_test(repo: Path, finished: Path, scratch: Path) -> dict:
    target = str(stage1_dir(Path("")) / "model.pt")
    one_thread = [*THREADS, "--configfile"]
    whole = copy_without_training(finished, scratch / "never_killed")
    cfg = tiny_config(repo, whole, KILL_STAGE1)
    t_whole = snakemake(whole, target, "--cores", "2", *one_thread, cfg, log="snakemake.log")

    killed = copy_without_training(finished, scratch / "killed")
    cfg = tiny_config(repo, killed, KILL_STAGE1)
    t0 = time.time()
    with open(killed / "snakemake.log", "w") as out:
        cmd = [sys.executable, "-m", "snakemake", target, *SLURM, *one_thread, cfg]
        proc = subprocess.Popen(cmd, cwd=killed, stdout=out, stderr=subprocess.STDOUT)
        killed_at = kill_when_checkpointed(killed, proc)
        rc = proc.wait(timeout=1800)
    log_text = (killed / "snakemake.log").read_text()
    assert rc == 0, f"the run with the killed job failed, see {killed / 'snakemake.log'}:\n{log_text[-3000:]}"
    train_log = (killed / "logs/train" / f"{KILL_DATASET}_{KILL_SUBJECT}_stage1.log").read_text()
    resumed = re.search(r"resuming from .* at step (\d+)", train_log)
    assert resumed, f"the resubmitted job did not resume:\n{train_log[-2000:]}"
    assert len(re.findall(r"submitted with SLURM jobid", log_text)) == 2, "expected one submission and one retry"
    assert 0 < int(resumed.group(1)) < KILL_STAGE1["iterations"]
    problems = [f"differs: {n}{d}" for n in ("model.pt", "losses.csv", "checkpoint.pt")
                for d in file_differences(stage1_dir(whole) / n, stage1_dir(killed) / n)]  # fmt: skip
    assert not problems, problems
    print(
        f"killed at step {killed_at}, resumed at step {resumed.group(1)}: model.pt, losses.csv equal a run never killed"
    )
    return {"never_killed_s": round(t_whole, 1), "killed_and_resumed_s": round(time.time() - t0, 1),
            "killed_at_step": killed_at, "resumed_at_step": int(resumed.group(1))}  # fmt: skip


def src_id(src: Path) -> str:
    """A digest of the code and workflow files a run used."""
    import hashlib

    h = hashlib.sha256((src / "Snakefile").read_bytes())
    for p in sorted(
        q for d in ("delta", "rules", "workflow", "config", ".test") for q in (src / d).rglob("*") if q.is_file()
    ):
        if "__pycache__" not in p.parts:
            h.update(str(p.relative_to(src)).encode() + p.read_bytes())
    return h.hexdigest()[:16]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--src", type=Path, required=True, help="the code and workflow files to run")
    ap.add_argument("--repo", type=Path, required=True, help="whose Anny build, converted models and weights to reuse")
    ap.add_argument("--scratch", type=Path, required=True)
    ap.add_argument("--skip-e2e", action="store_true", help="reuse the slurm run already in the scratch dir")
    ap.add_argument("--retrain", action="store_true",
                    help="reuse both runs of the same code in the scratch dir, rerunning only training (and what "
                         "follows it) in each: after a change to how training runs")  # fmt: skip
    args = ap.parse_args()
    summary = {}
    local, cluster = args.scratch / "local", args.scratch / "slurm"
    run_id = {"src": src_id(args.src), "args": THREADS}
    if not args.skip_e2e:
        done = local / "finished.json"  # a local run of the same code is kept: DELTA_TEST_REV pins it
        previous = json.loads(done.read_text()) if done.is_file() else {}
        if args.retrain:
            assert previous.get("src") == run_id["src"] and (cluster / "results").is_dir(), (
                "no runs of this code to reuse"
            )
            for work in (local, cluster):
                for stage in work.glob("results/*/*/stage[12]"):
                    shutil.rmtree(stage)
            previous = {}
        if {k: previous.get(k) for k in run_id} != run_id:
            if not args.retrain:
                workflow_copy(args.src, local)
            cfg = tiny_config(args.repo, local)
            seconds = snakemake(local, "--cores", "2", *THREADS, "--configfile", cfg, log="snakemake.log")
            done.write_text(json.dumps(run_id | {"seconds": round(seconds, 1), "retrain": args.retrain}))
        summary["local_s"] = json.loads(done.read_text())["seconds"]
        if not args.retrain:
            workflow_copy(args.src, cluster)
        cfg = tiny_config(args.repo, cluster)
        summary["slurm_s"] = round(snakemake(cluster, *SLURM, *THREADS, "--configfile", cfg, log="snakemake.log"), 1)
        summary["retrain_only"] = args.retrain
        submitted = len(re.findall(r"submitted with SLURM jobid", (cluster / "snakemake.log").read_text()))
        assert submitted >= (6 if args.retrain else 10), f"only {submitted} jobs went through SLURM"
        summary["slurm_jobs"] = submitted
        problems = compare_trees(local, cluster)
        assert not problems, "\n".join(problems)
        print(f"the slurm run ({submitted} jobs) and the local run wrote equal outputs")
    summary |= scancel_test(args.repo, cluster, args.scratch)
    (args.scratch / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
