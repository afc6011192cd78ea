"""What the occupancy grid saves: samples evaluated, step time and PSNR at equal steps, with and without.
from delta.host_memory import hold_freed_memory

Stage 1 of the `fast` preset on one synthetic subject, run in-process twice back to back (grid off, then
on) with the same seed, rays and steps; only ``render.occupancy.enabled`` differs. Samples per step are
deterministic and the primary figure; times are noisy on a shared machine. Also times the two halves
of a sample's cost on the final model (backward kNN skinning vs the NeRF query) and renders a few
training frames in full for an image PSNR. Needs results/synthetic/{subject}/frames.h5 and init/params.npz.

    python benchmarks/culling.py --steps 150 --rays 2048 --warmup 50
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from delta.host_memory import hold_freed_memory

ROOT = Path(__file__).resolve().parents[1]


def image_psnr(model, data, frames) -> float:
    from delta.models.image import render_image

    vals = []
    for k in frames:
        img = render_image(model, int(k))["rgb"]
        mse = float(((img - data.images[int(k)]) ** 2).mean())
        vals.append(10 * np.log10(1 / max(mse, 1e-10)))
    return float(np.mean(vals))


@torch.no_grad()
def per_sample_cost(model, data, n: int = 20000) -> dict:
    """ms per 10k samples of backward skinning (kNN + blend) and of the NeRF query, on points near the body."""
    from delta.deformers import knn as deformer

    frame = int(data.train[0])
    mesh = model.posed_mesh(frame)[0]
    gen = torch.Generator().manual_seed(0)
    v = mesh.skinning.posed
    pts = v[torch.randint(len(v), (n,), generator=gen)] + 0.05 * torch.randn(n, 3, generator=gen)
    rs = model.spec.render
    out = {}
    for name, fn in (("knn", lambda: deformer.deform(mesh.skinning, pts, rs.k, rs.sigma, rs.max_dist)),
                     ("nerf", lambda: model.nerf(pts))):  # fmt: skip
        fn()
        t = time.perf_counter()
        for _ in range(3):
            fn()
        out[f"{name}_ms_per_10k"] = round(1e4 * (time.perf_counter() - t) / 3 / n * 1e3, 2)
    return out


def one(subject: str, occupancy: bool, a, work: Path) -> dict:
    from delta.body.model import load_body_model
    from delta.training.presets import resolve
    from delta.training.run import build_avatar, load_init, stage_frames
    from delta.training.trainer import train_stage

    over = {"render": {"occupancy": {"enabled": occupancy, "warmup": a.warmup, "update_every": a.update_every}},
            "stage1": {"iterations": a.steps, "rays": a.rays, "checkpoint_every": 10**9, "preview_every": 0,
                       "log_every": 50}}  # fmt: skip
    st = resolve("fast", over)
    data = stage_frames(ROOT / f"results/synthetic/{subject}/frames.h5", st)
    body = load_body_model(ROOT / "resources/body/anny_sub1.npz")
    init = load_init(ROOT / f"results/synthetic/{subject}/init/params.npz", data)
    model = build_avatar(body, st, init, data, 1, torch.device("cpu"))
    out = work / f"{subject}_{'occ' if occupancy else 'plain'}"
    (out / "checkpoint.pt").unlink(missing_ok=True)
    t = time.time()
    res = train_stage(1, model, data, st, out)
    wall = time.time() - t
    L = res.losses
    after = L[L["step"] > a.warmup]
    row = {"subject": subject, "occupancy": occupancy, "steps": a.steps, "rays": a.rays, "warmup": a.warmup,
           "update_every": a.update_every, "seconds": round(wall, 1),
           "samples_per_step": round(float(L["samples"].mean())),
           "samples_per_step_after_warmup": round(float(after["samples"].mean())),
           "s_per_step_after_warmup": round(float(after["seconds"].diff().mean()), 3) if "seconds" in L else None,
           "train_psnr_last20": round(float(L["psnr"].tail(20).mean()), 2),
           "exterior_last20": round(float(L["exterior"].tail(20).mean()), 4),
           "occupied_cells": round(model.occupancy.fraction(), 3) if model.occupancy is not None else 1.0}  # fmt: skip
    row["image_psnr"] = round(image_psnr(model, data, data.train[:: max(1, len(data.train) // 3)][:3]), 2)
    row.update(per_sample_cost(model, data))
    return row


def main() -> None:
    hold_freed_memory()  # the host allocator as every delta command has it, so the clocks are the workflow's
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--subject", default="tight")
    p.add_argument("--steps", type=int, default=150)
    p.add_argument("--rays", type=int, default=2048)
    p.add_argument("--warmup", type=int, default=50)
    p.add_argument("--update-every", type=int, default=16)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--work", default=str(ROOT / "results/benchmarks/culling"))
    p.add_argument("--out", default=str(ROOT / "benchmarks/culling.csv"))
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    rows = [one(a.subject, occ, a, Path(a.work)) for occ in (False, True)]
    for r in rows:
        print(json.dumps(r))
    pd.DataFrame(rows).to_csv(a.out, index=False)


if __name__ == "__main__":
    main()
