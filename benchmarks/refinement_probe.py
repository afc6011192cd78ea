"""What the refinement's check sees: its probe's loss at each check against larger, independent measures.

The evaluation's refinement (``delta/eval/heldout.py``) keeps the pose of the lowest loss on one fixed probe of
4096 rays (pixel Huber + 0.1 × silhouette), checked every ``--check`` steps. This runs that refinement on each
frame of the given splits, keeps every check's pose, and measures each pose again: on the refinement's probe
(its loss and its squared error), on two independent draws of ``--large`` rays each (squared error: what PSNR
scores), and, for the pose as given, the pose kept, the last pose and the poses the large draws and the
probe's squared error would keep, the whole frame at the capture's size as the evaluation scores it (PSNR,
2×2 rays a pixel). One row per (frame, check); ``full_psnr`` is empty where the frame was not rendered. The
refinement's path is not bit-exact from one process to the next (the threads' sums), so a frame run twice may
keep another check's pose.

    PYTHONPATH=$PWD python3 benchmarks/refinement_probe.py --model results/synthetic/loose/stage2/model.pt \\
        --record results/synthetic/loose/frames.h5 --body resources/body/anny_sub1.npz --subject loose \\
        --frames 74 29 4 107 --csv benchmarks/refinement_probe.csv
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch

import delta.eval.heldout as heldout
from delta.data.frames import load_full_frames, sample_rays
from delta.eval.settings import SPLITS, EvalSettings
from delta.models.image import full_view, render_image
from delta.training.run import load_trained

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import model_arguments  # noqa: E402

SPLIT_NAMES = {v: k for k, v in SPLITS.items()}


@torch.no_grad()
def measures(model, frame: int, batch, seed: int) -> dict[str, float]:
    """The refinement's loss on ``batch`` (rendered with the sample jitter of ``seed``) and its squared error."""
    r = model.render(frame, batch.pixels.to(model.background.device), torch.Generator().manual_seed(seed))
    return {
        "loss": float(heldout.loss_of(r, batch)),
        "mse": float((r.rgb - batch.rgb.to(r.rgb.device)).square().mean()),
    }


def main(argv=None) -> None:
    ap = model_arguments(argparse.ArgumentParser(description=__doc__.split("\n\n")[0]))
    ap.add_argument("--frames", nargs="+", type=int, required=True, help="the record's frame indices")
    ap.add_argument("--steps", type=int, default=EvalSettings().refine_steps)
    ap.add_argument("--check", type=int, default=EvalSettings().refine_check)
    ap.add_argument("--large", type=int, default=65536, help="rays of each independent large draw")
    ap.add_argument("--csv", required=True)
    ap.add_argument("--append", action="store_true")
    a = ap.parse_args(argv)
    torch.set_num_threads(2)
    st = EvalSettings()
    trained = load_trained(a.model, a.record, a.body)
    model, data = trained.model, trained.data
    params = model.per_frame_parameters()
    poses: dict[int, list[torch.Tensor]] = {}
    better = heldout._better

    def kept_poses(model_, frame, probe, seed, params_, step, best):  # every check's pose, for measuring again
        poses[step] = [p.detach()[frame].clone() for p in params_]
        return better(model_, frame, probe, seed, params_, step, best)

    heldout._better = kept_poses
    rows, before = [], pd.read_csv(a.csv) if a.append and Path(a.csv).is_file() else None
    for f in a.frames:
        given = [p.detach()[f].clone() for p in params]
        poses.clear()
        poses[0] = given
        fit = heldout.refine_frame(model, data, f, a.steps, rays=st.refine_rays, lr=st.refine_lr, seed=f,
                                   lr_end=st.refine_lr_end, check=a.check)  # fmt: skip
        probe = sample_rays(data, f, max(st.refine_rays, heldout.PROBE_RAYS), torch.Generator().manual_seed(f + 1))
        large = [sample_rays(data, f, a.large, torch.Generator().manual_seed(f + 1000 * k)) for k in (1, 2)]
        full = load_full_frames(a.record, [f], trained.settings.background)
        view = full_view(full, model.resolution)
        frame_rows = {}
        for step, pose in sorted(poses.items()):
            heldout.put_pose(params, f, pose)
            on_probe = measures(model, f, probe, f + 2)  # the refinement's own probe and jitter
            frame_rows[step] = {"subject": a.subject, "split": SPLIT_NAMES.get(int(data.split[f]), "train"),
                                "frame": f, "step": step, "kept": step == fit.kept, "probe_loss": on_probe["loss"],
                                "probe_mse": on_probe["mse"], "large_mse_a": measures(model, f, large[0], 7)["mse"],
                                "large_mse_b": measures(model, f, large[1], 8)["mse"], "full_psnr": np.nan}  # fmt: skip
        by = lambda key: min(frame_rows, key=lambda s: frame_rows[s][key])  # noqa: E731
        for step in sorted({0, fit.kept, max(poses), by("large_mse_a"), by("probe_mse")}):
            heldout.put_pose(params, f, poses[step])
            with torch.no_grad():
                img = render_image(model, f, supersample=st.supersample, view=view, soft_silhouette=False)
            mse = float((img["rgb"].clamp(0, 1) - full.images[0].to(img["rgb"].device)).square().mean())
            frame_rows[step]["full_psnr"] = -10 * math.log10(mse)
        heldout.put_pose(params, f, given)
        rows += frame_rows.values()
        print(pd.DataFrame(frame_rows.values()).drop(columns="subject").to_string(), flush=True)
        # written after every frame: a run cut short keeps what it measured
        pd.concat([before, pd.DataFrame(rows)], ignore_index=True).to_csv(a.csv, index=False)


if __name__ == "__main__":
    main()
