"""Accuracy of the Anny -> BodyModel conversion against Anny's own forward pass.

For each (num_shape, num_samples) the script converts Anny, then poses 32 random
phenotypes (held out from the PCA samples) in random poses with both Anny and
the project's LBS, and writes the vertex error in mm to CSV.

    python benchmarks/anny_conversion.py --out benchmarks/anny_conversion.csv
"""

from __future__ import annotations

import argparse
import time

import pandas as pd
import torch

from delta.body.anny_convert import (
    ANNY_TO_SMPLX,
    anny_pose_deltas,
    anny_rest,
    build_anny,
    convert_anny,
    project_shape,
    sample_phenotypes,
)
from delta.body.lbs import batch_rodrigues, lbs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="benchmarks/anny_conversion.csv")
    parser.add_argument("--num-shape", type=int, nargs="+", default=[8, 16, 24, 32, 64])
    parser.add_argument("--num-samples", type=int, nargs="+", default=[256, 1024])
    parser.add_argument("--cache-dir", default="resources/anny_cache")
    args = parser.parse_args()
    torch.set_num_threads(2)
    anny_model = build_anny(args.cache_dir)
    C = torch.as_tensor(ANNY_TO_SMPLX)
    ph = sample_phenotypes(32, len(anny_model.phenotype_labels), seed=2024)
    rest = anny_rest(anny_model, ph)
    gen = torch.Generator().manual_seed(0)
    pose = 0.5 * torch.randn(32, len(anny_model.bone_labels), 3, generator=gen, dtype=torch.float64)
    rot = C.T @ batch_rodrigues(pose) @ C
    deltas = anny_pose_deltas(rot, torch.zeros(32, 3, dtype=torch.float64), rest["rest_bone_poses"],
                              anny_model.reference_bone_orientations, anny_model.bone_parents)  # fmt: skip
    with torch.no_grad():
        ref = anny_model(pose_parameters=deltas, phenotype_kwargs=ph)["vertices"] @ C.T
    rows = []
    for samples in args.num_samples:
        for k in args.num_shape:
            t0 = time.perf_counter()
            conv = convert_anny(num_shape=k, num_samples=samples, seed=0, anny_model=anny_model)
            seconds = time.perf_counter() - t0
            betas = project_shape(conv, rest["rest_vertices"], rest["rest_bone_heads"])
            err = 1000 * (lbs(conv.model, betas, pose).vertices - ref).norm(dim=-1)
            rows.append(dict(num_shape=k, num_samples=samples, max_mm=err.max().item(),
                             mean_mm=err.mean().item(), p99_mm=err.flatten().quantile(0.99).item(),
                             explained_variance=float(conv.explained_variance.sum()), convert_s=seconds))  # fmt: skip
            print(rows[-1], flush=True)
    pd.DataFrame(rows).to_csv(args.out, index=False)


if __name__ == "__main__":
    main()
