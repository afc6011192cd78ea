"""What the fields' boxes around the framed vertices buy a capture that frames part of the body.

Each run is ``LABEL=MODEL,SUMMARY,BENCH``: a stage-2 ``model.pt``, the evaluation's ``summary.json`` of
it, and the folder of the workflow's training benchmarks (``results/benchmarks/train``, whose
``{dataset}_{subject}_stage{1,2}.tsv`` hold each stage's seconds). For each run the CSV has the
vertices the boxes hold, the albedo grid's and the exterior colour grid's finest cells (mm), both
stages' steps and seconds, and per scored split (as tracked and refined) PSNR on the whole image and
by region, SSIM, ST-LPIPS and the hair layer's IoU: the means over the scored frames, at the
resolution the evaluation states.

    python benchmarks/framed_boxes.py --record results/synthetic/talker/frames.h5 \\
        --body resources/body/anny_sub1_face.npz --dataset synthetic --subject talker \\
        --run whole=/tmp/old/stage2/model.pt,/tmp/old/summary.json,/tmp/old/bench \\
        --run framed=results/synthetic/talker/stage2/model.pt,/tmp/new/summary.json,results/benchmarks/train \\
        --out benchmarks/framed_boxes.csv
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pandas as pd

SCORES = ("psnr", "psnr_face", "psnr_head", "psnr_hair", "psnr_clothing", "ssim", "stlpips_alex", "hair_layer_iou")


def model_columns(model: str, record: str, body: str) -> dict:
    from delta.training.run import load_trained

    m = load_trained(model, record, body).model
    nerf = m.nerf
    return {
        "framed_vertices": int(m.framed.sum()),
        "modelled_vertices": int(m.modelled.sum()),
        "albedo_cell_mm": round(1000 * m.albedo_field.encoding.finest_cell(), 2),
        "exterior_color_cell_mm": round(1000 * nerf.color_cell(), 2) if nerf is not None else float("nan"),
    }


def stage_seconds(bench: Path, dataset: str, subject: str, stage: int) -> float:
    path = bench / f"{dataset}_{subject}_stage{stage}.tsv"
    return float(pd.read_csv(path, sep="\t")["s"].iloc[0]) if path.exists() else float("nan")


def run_rows(label: str, spec: str, args) -> list[dict]:
    model, summary, bench = spec.split(",")
    base = {"run": label, **model_columns(model, args.record, args.body)}
    import torch

    def steps(path: Path):
        return torch.load(path, map_location="cpu", weights_only=True).get("steps") if path.exists() else None

    stage1 = Path(model).parent.parent / "stage1" / "model.pt"
    base.update(stage1_steps=steps(stage1), stage2_steps=steps(Path(model)), stage1_s=stage_seconds(Path(bench), args.dataset, args.subject, 1),
                stage2_s=stage_seconds(Path(bench), args.dataset, args.subject, 2))  # fmt: skip
    s = json.loads(Path(summary).read_text())
    rows = []
    for split, kinds in s["scores"].items():
        for kind, scores in kinds.items():
            row = dict(base, split=split, refined=kind == "refined", frames=scores.get("frames"),
                       resolution=s["convention"]["resolution"])  # fmt: skip
            row.update({k: scores.get(k) for k in SCORES})
            rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--record", required=True)
    ap.add_argument("--body", required=True)
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--subject", required=True)
    ap.add_argument("--run", action="append", required=True, help="LABEL=MODEL,SUMMARY,BENCH")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    rows = []
    for item in args.run:
        label, spec = item.split("=", 1)
        rows += run_rows(label, spec, args)
    table = pd.DataFrame(rows)
    table.to_csv(args.out, index=False, float_format="%.4g")
    print(table.to_string(index=False))


if __name__ == "__main__":
    main()
