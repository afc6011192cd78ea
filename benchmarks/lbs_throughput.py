"""LBS forward + backward throughput (frames/s) of the upsampled body mesh.

Gradients flow to shape, pose, translation and per-vertex offsets, as in
training. Writes one CSV row per (device, dtype, batch).

    snakemake --cores 2                      # builds resources/body/anny_sub1.npz
    python benchmarks/lbs_throughput.py --out benchmarks/lbs_throughput.csv
"""

from __future__ import annotations

import argparse
import platform
import time

import pandas as pd
import torch

from delta.body.lbs import lbs
from delta.body.model import load_body_model


def run(model, batch: int, device: str, dtype: torch.dtype, repeats: int) -> dict:
    m = model.to(device=device, dtype=dtype)
    gen = torch.Generator().manual_seed(0)
    betas = torch.randn(batch, m.num_shape, generator=gen).to(device, dtype).requires_grad_()
    pose = (0.3 * torch.randn(batch, m.num_joints, 3, generator=gen)).to(device, dtype).requires_grad_()
    transl = torch.zeros(batch, 3, device=device, dtype=dtype, requires_grad=True)
    offsets = torch.zeros(m.num_vertices, 3, device=device, dtype=dtype, requires_grad=True)

    def step():
        out = lbs(m, betas, pose, offsets=offsets, transl=transl)
        out.vertices.square().mean().backward()

    step()  # warm-up
    if device == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(repeats):
        step()
    if device == "cuda":
        torch.cuda.synchronize()
    seconds = (time.perf_counter() - t0) / repeats
    return dict(device=device, dtype=str(dtype).replace("torch.", ""), batch=batch, vertices=m.num_vertices,
                joints=m.num_joints, ms_per_step=1000 * seconds, frames_per_s=batch / seconds,
                threads=torch.get_num_threads(), cpu=platform.processor() or platform.machine())  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--model", default="resources/body/anny_sub1.npz")
    parser.add_argument("--out", default="benchmarks/lbs_throughput.csv")
    parser.add_argument("--batch", type=int, nargs="+", default=[1, 16, 64])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--devices", nargs="+", default=["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model = load_body_model(args.model)
    rows = [run(model, b, d, torch.float32, args.repeats) for d in args.devices for b in args.batch]
    for row in rows:
        print(row, flush=True)
    pd.DataFrame(rows).to_csv(args.out, index=False)


if __name__ == "__main__":
    main()
