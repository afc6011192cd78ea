"""Speed of the synthetic capture generator: a 100-frame 512² subject on this machine.

Generates each configured synthetic subject with 100 turn frames at 512² (no
novel-pose segment) and records wall time, frames/s and peak memory in CSV.

    snakemake --cores 2 resources/body/anny_sub1.npz resources/body/anny_pca.npz
    python benchmarks/synthetic_speed.py --out benchmarks/synthetic_speed.csv
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time

import pandas as pd
import torch
import yaml

from delta.synthetic.generate import generate
from delta.synthetic.spec import parse_subject


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--config", default="config/config.yaml")
    parser.add_argument("--body", default="resources/body/anny_sub1.npz")
    parser.add_argument("--shape-space", default="resources/body/anny_pca.npz")
    parser.add_argument("--anny-cache", default="resources/anny_cache")
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--resolution", type=int, default=512)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", default="benchmarks/synthetic_speed.csv")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    subjects = yaml.safe_load(open(args.config))["datasets"]["synthetic"]["subjects"]
    rows = []
    for name, raw in subjects.items():
        raw = dict(raw, turn_frames=args.frames, novel_frames=0, resolution=args.resolution)
        spec = parse_subject(name, raw)
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            generate(spec, args.body, tmp, args.shape_space, args.anny_cache)
            seconds = time.perf_counter() - t0
        rows.append(dict(subject=name, frames=args.frames, resolution=args.resolution, camera=spec.camera,
                         seconds=round(seconds, 1), frames_per_s=round(args.frames / seconds, 2),
                         peak_rss_mb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
                         threads=args.threads))  # fmt: skip
        print(rows[-1], flush=True)
    pd.DataFrame(rows).to_csv(args.out, index=False)


if __name__ == "__main__":
    main()
