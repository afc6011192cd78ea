"""What choosing each limb's side along the view buys the held-out frames (``evaluation.refine_sides``).

A single view does not tell an upper arm or a thigh swung toward the camera from the same one swung away:
both put the keypoints on the same pixels, and the init fit of a free pose can end on the wrong side,
which the refinement's small steps cannot cross. With ``refine_sides`` the refinement first tries each
limb's other sides (``delta.body.sides.other_sides``) against the frame. This scores one trained model by
the workflow's evaluation (whole frames at the capture's size, refined rows) without and with it, each
from the same start, one row per frame: PSNR, body error, the limbs swung and, with ``--truth`` (a
synthetic subject's gt folder), each limb bone's angle from the truth's in the root's frame (the mean over
the eight bones and the largest), before and after the refinement.

    PYTHONPATH=$PWD python3 benchmarks/limb_sides.py --model results/synthetic/tight/stage2/model.pt \\
        --record results/synthetic/tight/frames.h5 --body resources/body/anny_sub1.npz --subject tight \\
        --truth data/synthetic/tight/gt --splits test_pose --max-frames 10 --csv benchmarks/limb_sides.csv
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from delta.body.lbs import batch_rodrigues, rigid_transforms, shaped_joints
from delta.body.sides import limbs
from delta.eval.evaluate import evaluate
from delta.eval.settings import SPLITS, EvalSettings
from delta.training.run import load_trained

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table import device_name, save_table, trained_model_arguments  # noqa: E402


def bone_errors_deg(body, betas: torch.Tensor, fitted: torch.Tensor, truth: torch.Tensor) -> np.ndarray:
    """(F, 2L) the angle between each limb bone (upper, lower of every limb) of (F, J, 3) fitted and true
    poses, each bone taken in its own pose's root frame (the heading's error left out)."""
    joints = shaped_joints(body, betas[None].to(body.joints_template.dtype))[0].double()

    def bones(poses: torch.Tensor) -> torch.Tensor:
        rot = batch_rodrigues(poses.double())
        posed, _ = rigid_transforms(rot, joints.expand(len(rot), -1, -1), body.parents)
        vec = torch.stack([posed[:, c[k + 1]] - posed[:, c[k]] for _, c in limbs(body) for k in (0, 1)], 1)
        vec = torch.einsum("fji,fbj->fbi", rot[:, 0], vec)  # R_rootᵀ v
        return vec / vec.norm(dim=-1, keepdim=True)

    cos = (bones(fitted) * bones(truth)).sum(-1).clamp(-1, 1)
    return torch.rad2deg(torch.arccos(cos)).numpy()


def main(argv=None) -> None:
    ap = trained_model_arguments(argparse.ArgumentParser(description=__doc__.split("\n\n")[0]))
    ap.add_argument("--truth", default=None, help="the subject's gt folder (params.npz, meshes.h5)")
    ap.add_argument("--csv", required=True)
    ap.add_argument("--append", action="store_true")
    ap.add_argument("--frames", type=int, nargs="+", help="score these held-out frame ids (all of them, in --splits)")
    ap.add_argument("--passes", nargs="+", choices=["off", "on"], default=["off", "on"],
                    help="score without (off) and with (on) the side choice")  # fmt: skip
    a = ap.parse_args(argv)
    torch.set_num_threads(2)
    truth = np.load(Path(a.truth) / "params.npz") if a.truth else None
    tables = []
    for sides in [p == "on" for p in a.passes]:
        trained = load_trained(a.model, a.record, a.body, device=a.device)  # fresh: refinement moves the poses
        model, data = trained.model, trained.data
        if a.frames:  # the other held-out frames leave the scored splits
            split, ids = np.asarray(data.split), np.asarray(data.frame_ids)
            leave = np.isin(split, [SPLITS[s] for s in a.splits]) & ~np.isin(ids, a.frames)
            data.split = np.where(leave, max(SPLITS.values()) + 1, split)
        st = EvalSettings(splits=tuple(a.splits), max_frames=0 if a.frames else a.max_frames, refine_sides=sides,
                          report_unrefined=False,
                          supersample=a.supersample, worst=0, perceptual_dir=a.perceptual_dir or None)  # fmt: skip
        given = model.poses.detach().clone()
        t0 = time.perf_counter()
        gt_meshes = Path(a.truth) / "meshes.h5" if a.truth else None
        df = evaluate(trained, a.record, st, gt_meshes=gt_meshes, subject=a.subject)
        df = df.assign(sides=sides, eval_wall_s=round(time.perf_counter() - t0, 1),
                       device=device_name(a.device, torch.get_num_threads()))  # fmt: skip
        if truth is not None:
            frames = df["frame"].to_numpy().copy()
            ids = np.asarray(data.frame_ids)[frames]
            true = torch.tensor(truth["poses"][ids])
            for when, poses in (("given", given[frames]), ("refined", model.poses.detach()[frames].cpu())):
                err = bone_errors_deg(model.body.to(device="cpu"), model.betas.detach().cpu(), poses.cpu(), true)
                df[f"bone_err_{when}_mean_deg"], df[f"bone_err_{when}_max_deg"] = err.mean(1), err.max(1)
        tables.append(df)
        keep = [c for c in ("frame_id", "split", "psnr", "body_err_mm", "refine_sides", "bone_err_given_mean_deg",
                            "bone_err_refined_mean_deg", "bone_err_refined_max_deg") if c in df]  # fmt: skip
        print(df[keep].round(2).to_string(), flush=True)
    table = pd.concat(tables, ignore_index=True)
    save_table(table, a.csv, a.append)
    cols = [c for c in ("psnr", "ssim", "stlpips_alex", "body_err_mm", "bone_err_refined_mean_deg") if c in table]
    print(table.groupby(["split", "sides"])[cols].mean().round(3).to_string())


if __name__ == "__main__":
    main()
