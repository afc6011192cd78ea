"""The applications scored against the truth the generator renders for them, on avatars the workflow trained.

Each avatar is a trained workflow run's subject, given as ``NAME=WORK:DATASET:SUBJECT`` (WORK: the
folder the workflow ran in; the subject's synthetic spec is read from WORK's config, the People
Snapshot stand-in's included). For every ``--dress B:A`` pair, B's avatar wears A's exterior and is
scored against the generated capture of B's body wearing A's garments and hair; for every
``--reshape B:label=value`` the same against B with its phenotype edited. Both are scored on B's test
frames at B's scoring size, as trained and edited (no test-time refinement), with the gain of the edit.

    PYTHONPATH=. python3 benchmarks/applications.py \\
        --avatar standin=/tmp/dt-work:peoplesnapshot:standin-male-3-casual \\
        --avatar loose=/tmp/bench-work:synthetic:loose \\
        --avatar gen0=/tmp/gen-work:synthetic:gen0 \\
        --dress standin:loose --dress loose:standin --dress standin:gen0 \\
        --reshape standin:weight=0.85 --reshape loose:weight=0.8 \\
        --reshape standin:weight=+0.35 --reshape loose:weight=+0.35 \\
        --work /tmp/appbench --out benchmarks/applications.csv

Writes the CSV (one row per job and variant: as_trained, edited, gain) with each job's seconds.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from delta.applications.dress import dress_avatar
from delta.applications.reshape import reshape_avatar
from delta.applications.settings import ShowSettings
from delta.applications.truth import summarize_scores
from delta.config import load_config
from delta.synthetic.generate import generate
from delta.synthetic.spec import dressed_raw, parse_subject, reshaped_raw, truth_name


def avatar(text: str) -> tuple[str, dict]:
    name, _, rest = text.partition("=")
    work, dataset, subject = rest.split(":")
    work = Path(work)
    config = load_config(work / "config" / "config.yaml", device=False)
    raw = (config["datasets"].get("synthetic", {}).get("subjects", {}) | config["standins"]).get(subject)
    if raw is None:
        raise SystemExit(f"{subject}: not a synthetic subject of {work}/config/config.yaml")
    out = work / "results" / dataset / subject
    return name, {"model": out / "stage2" / "model.pt", "record": out / "frames.h5", "raw": raw, "work": work,
                  "subject": subject, "clothing": out / "export" / "clothing_nerf_space.ply"}  # fmt: skip


def truth(work: Path, name: str, raw: dict, body: Path, shape_space: Path, cache: Path) -> Path:
    out = work / "truth" / name
    if not (out / "gt" / "splits.json").is_file():
        generate(parse_subject(name, raw), body, out, shape_space, cache)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--avatar", action="append", required=True, help="NAME=WORK:DATASET:SUBJECT")
    ap.add_argument("--dress", action="append", default=[], help="B:A (B wears A's exterior)")
    ap.add_argument(
        "--reshape", action="append", default=[], help="B:label=value[,label=value] (a signed value: a change)"
    )
    ap.add_argument("--work", type=Path, required=True, help="folder for the generated truths and the outputs")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=5, help="test frames scored per job")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    avatars = dict(avatar(a) for a in args.avatar)
    first = next(iter(avatars.values()))["work"]
    body, shape_space = first / "resources/body/anny_sub1.npz", first / "resources/body/anny_pca.npz"
    cache = load_config(first / "config" / "config.yaml", device=False)["body_model"]["anny"]["cache_dir"]
    cache = Path(cache) if Path(cache).is_absolute() else first / cache
    perceptual = str(first / "resources/models/stlpips")
    settings = ShowSettings(turntable_frames=2, score_frames=args.frames, supersample=2)
    scores, seconds = [], {}
    for pair in args.dress:
        b, a = pair.split(":")
        B, A = avatars[b], avatars[a]
        t = time.perf_counter()
        gt = truth(
            args.work, truth_name("dress", B["subject"], a), dressed_raw(B["raw"], A["raw"]), body, shape_space, cache
        )
        out = args.work / "results" / B["subject"] / "dress" / a
        dress_avatar(B["model"], B["record"], A["model"], A["record"], body, out, settings, gt, perceptual,
                     B["clothing"], A["clothing"])  # fmt: skip
        scores.append(out / "scores.csv")
        seconds[(B["subject"], "dress", a)] = time.perf_counter() - t
    for job in args.reshape:
        b, _, edit_text = job.partition(":")
        edit = {k: v if v[:1] in "+-" else float(v) for k, v in (kv.split("=") for kv in edit_text.split(","))}
        B = avatars[b]
        name = "-".join(f"{k}{v}" for k, v in edit.items())
        t = time.perf_counter()
        gt = truth(
            args.work, truth_name("reshape", B["subject"], name), reshaped_raw(B["raw"], edit), body, shape_space, cache
        )
        out = args.work / "results" / B["subject"] / "reshape" / name
        reshape_avatar(B["model"], B["record"], body, edit, out, shape_space, cache, settings, gt, perceptual,
                       B["clothing"])  # fmt: skip
        scores.append(out / "scores.csv")
        seconds[(B["subject"], "reshape", name)] = time.perf_counter() - t
    table = summarize_scores(scores)
    table["seconds"] = [round(seconds[(r.subject, r.application, r.name)]) for r in table.itertuples()]
    table["threads"] = args.threads
    args.out.parent.mkdir(parents=True, exist_ok=True)
    table.to_csv(args.out, index=False)
    print(table.to_string())


if __name__ == "__main__":
    main()
