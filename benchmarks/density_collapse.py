"""Does the NeRF's raw density run away downwards in the first training steps? (#8's reference)

Trains stage 1 of a saved configuration (a sweep's ``settings.json``) for a few steps, once per
``--variant`` (a JSON override on top of it), and writes the quantiles of the NeRF's raw density
(before the activation) at uniform points of its box after each listed step. A raw density far
below zero everywhere means σ = 0 everywhere: no NeRF, and with either activation no gradient back.
(The cure: SCARF's NeRF-only start, ``stage1.nerf_warmup`` with its precrop, and the
hybrid at a NeRF rate of 1e-4 — the ``paper`` preset's; a variant ``'{"stage1": {"nerf_warmup": 0}}'``
shows the collapse again.)

    python benchmarks/density_collapse.py --settings results/synthetic/loose/tradeoff/reference/stage1/settings.json \\
        --record results/synthetic/loose/frames.h5 --body resources/body/anny_sub1.npz \\
        --init results/synthetic/loose/init/params.npz --out benchmarks/density_collapse.csv \\
        --variant paper='{}' --variant exp='{"nerf": {"density_activation": "exp", "density_noise": 0}}' \\
        --variant lr_5e-5='{"stage1": {"lr": {"nerf": 5e-5}}}' --variant no_pixel='{"weights": {"pixel": 0}}'

A variant named ``scarf_losses...`` trains with SCARF's loss shapes in place of the paper's: the NeRF
alpha loss a Huber penalty (δ = the settings' ``huber_delta``) instead of L1, and the rgb loss masked by
the person (rays outside the person teach nothing); it patches the two functions for that variant only.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import tempfile
import time
from pathlib import Path

import pandas as pd
import torch

import delta.training.trainer as T
from delta import losses as L
from delta.body.model import load_body_model
from delta.training.presets import deep_merge, resolve
from delta.training.run import build_avatar, load_init, stage_frames
from delta.training.trainer import train_stage

QUANTILES = (0.01, 0.1, 0.5, 0.9, 0.99)


@contextlib.contextmanager
def scarf_losses(on: bool):
    """SCARF's loss shapes while the block runs (``on``): Huber NeRF alpha loss, person-masked rgb loss."""
    if not on:
        yield
        return
    loss_terms = T.loss_terms

    def masked(model, batch, st, *rest, **kw):
        terms, r = loss_terms(model, batch, st, *rest, **kw)
        terms["pixel"] = L.huber((r.rgb - batch.rgb) * batch.person[:, None], st.weights.huber_delta)
        terms["exterior"] = L.huber(r.nerf_mask - batch.exterior, st.weights.huber_delta)
        return terms, r

    T.loss_terms = masked
    try:
        yield
    finally:
        T.loss_terms = loss_terms


def run(args: argparse.Namespace, name: str, override: dict) -> list[dict]:
    saved = json.loads(Path(args.settings).read_text())
    raw = deep_merge(saved["settings"], override)
    last = max(args.steps)
    raw["stage1"] = {**raw["stage1"], "iterations": last, "checkpoint_every": last + 1, "preview_every": 0,
                     "log_every": last + 1}  # fmt: skip
    st = resolve(saved["preset"], raw)
    data = stage_frames(args.record, st)
    model = build_avatar(load_body_model(args.body), st, load_init(args.init, data), data, 1, torch.device("cpu"))
    lo, hi = model.nerf.encoding.lo, model.nerf.encoding.hi
    points = lo + torch.rand(args.points, 3, generator=torch.Generator().manual_seed(0)) * (hi - lo)
    rows, t0 = [], time.time()
    with tempfile.TemporaryDirectory() as tmp, scarf_losses(name.startswith("scarf_losses")):
        for step in sorted({0, *args.steps}):
            if step:
                train_stage(1, model, data, st, Path(tmp), max_steps=step)  # resumes from its own checkpoint
            with torch.no_grad():
                r = model.nerf.raw_density(points)
            q = torch.quantile(r, torch.tensor(QUANTILES))
            rows.append({"variant": name, "override": json.dumps(override), "step": step,
                         **{f"raw_q{int(100 * k):02d}": round(float(v), 3) for k, v in zip(QUANTILES, q)},
                         "share_positive": float((r > 0).float().mean()), "seconds": round(time.time() - t0, 1)})  # fmt: skip
            print(rows[-1], flush=True)
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--settings", required=True, help="a stage1/settings.json written by training")
    p.add_argument("--record", required=True)
    p.add_argument("--body", required=True)
    p.add_argument("--init", required=True)
    p.add_argument("--variant", action="append", required=True, help="NAME=JSON override")
    p.add_argument("--steps", type=int, nargs="+", default=[4, 8, 16, 24, 50])
    p.add_argument("--points", type=int, default=100_000)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", required=True)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for spec in args.variant:
        name, override = spec.split("=", 1)
        rows += run(args, name, json.loads(override))
    pd.DataFrame(rows).to_csv(args.out, index=False)


if __name__ == "__main__":
    main()
