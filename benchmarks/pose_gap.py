"""Where a synthetic avatar's held-out poses lose to its held-out views: the pose fit or the avatar.

A held-out pose is scored with the init fit's pose of that frame, refined with the model frozen
(``delta/eval/heldout.py``). Its gap to the held-out views has two causes that the workflow's
score mixes: the fit's pose is wrong (the novel segment is fitted free: no hold, unusual poses), and
the avatar itself renders a pose it never saw worse (its exterior carried by the body into a new
configuration). This scores the same frames of one trained avatar twice by the workflow's evaluation:
with the fitted poses, and with the generator's true poses put in their place (every joint, the root
and the translation: the truth's, shifted by the mean difference between the avatar's and the truth's
translation over the training frames, which carries the fitted shape's root joint; an orthographic
capture keeps its fitted per-frame camera, which the refinement moves), refined the same way.
The difference is what the pose fit costs; what remains against the views is the avatar's own.
``--poses`` also takes another init fit's ``params.npz`` of the same record (a fit with other settings):
its poses and translations (and orthographic cameras) of the scored frames, scored on the same avatar,
tell whether a change to the fit would show in the renders. ``true:arms``, ``true:legs`` and ``true:torso``
keep the fitted poses but for that group's joints, whose local rotations become the truth's (an Anny body:
clavicles to wrists; hips to feet; spine, neck and head): which part of the body the fit costs the render.
``--frames`` scores chosen held-out frames.

Rows: one per (frame, poses, refined): PSNR overall and in the regions the evaluation scores, body
vertex error, and the fitted pose's error against the truth (root and joints, degrees; the largest
joint named).

    PYTHONPATH=$PWD python3 benchmarks/pose_gap.py --model results/synthetic/tight/stage2/model.pt \\
        --record results/synthetic/tight/frames.h5 --body resources/body/anny_sub1.npz --subject tight \\
        --truth data/synthetic/tight/gt --perceptual-dir "" --csv benchmarks/pose_gap.csv
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from delta.body.lbs import batch_rodrigues
from delta.eval.evaluate import evaluate
from delta.eval.settings import SPLITS, EvalSettings
from delta.training.run import load_trained

sys.path.insert(0, str(Path(__file__).resolve().parent))
from edge_profile import set_body  # noqa: E402
from table import device_name, save_table, trained_model_arguments  # noqa: E402

SCORES = ("psnr", "psnr_body", "psnr_face", "psnr_clothing", "psnr_hair", "psnr_outline", "outline_error_share",
          "nerf_iou", "mesh_iou", "body_err_mm", "body_err_pa_mm", "refine_kept_step")  # fmt: skip


#: Anny joints by name (before the side's ``.L``/``.R``) of the groups a ``true:GROUP`` pass takes from the truth
GROUPS = {
    "arms": ("clavicle", "shoulder01", "upperarm01", "upperarm02", "lowerarm01", "lowerarm02", "wrist"),
    "legs": ("pelvis", "upperleg01", "upperleg02", "lowerleg01", "lowerleg02", "foot"),
    "torso": ("spine05", "spine04", "spine03", "spine02", "spine01", "neck01", "neck02", "neck03", "head"),
}


def group_joints(names, group: str) -> list[int]:
    """Indices of ``names`` (the body's joints) in ``GROUPS[group]``."""
    if group not in GROUPS:
        raise SystemExit(f"true:{group}: not a joint group (known: {', '.join(GROUPS)})")
    return [j for j, n in enumerate(names) if str(n).split(".")[0] in GROUPS[group]]


@torch.no_grad()
def put_true_group(model, frames: np.ndarray, frame_ids: np.ndarray, truth, group: str) -> None:
    """In place: ``frames``' local rotations of the joints of ``group`` become the generator's."""
    idx = group_joints(model.body.joint_names, group)
    for f in frames:
        model.poses[f, idx] = torch.as_tensor(truth["poses"][frame_ids[f]][idx], dtype=model.poses.dtype)


def angles_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis-angle pairs -> (...) the angle of the rotation between them, in degrees."""
    ra, rb = batch_rodrigues(a.reshape(-1, 3)), batch_rodrigues(b.reshape(-1, 3))
    cos = ((ra.transpose(1, 2) @ rb).diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2
    return torch.rad2deg(torch.arccos(cos.clamp(-1.0, 1.0))).reshape(a.shape[:-1])


def pose_errors(fitted: torch.Tensor, truth: torch.Tensor, names) -> list[dict]:
    """Per frame of (F, J, 3) fitted and true poses: the root's error, the joints' mean and largest (named)."""
    err = angles_deg(fitted.double(), truth.double())
    rows = []
    for e in err:
        worst = int(e[1:].argmax()) + 1
        rows.append({"root_err_deg": float(e[0]), "joint_err_mean_deg": float(e[1:].mean()),
                     "joint_err_max_deg": float(e[worst]), "joint_err_max_name": str(names[worst])})  # fmt: skip
    return rows


@torch.no_grad()
def put_true_poses(model, frames: np.ndarray, frame_ids: np.ndarray, train: np.ndarray, truth) -> None:
    """In place: ``frames``' pose and translation become the generator's; the translation is shifted by the
    mean (avatar - truth) over the ``train`` frames (the fitted shape puts its root joint elsewhere)."""
    shift = (model.transl[train].cpu().numpy() - truth["transl"][frame_ids[train]]).mean(0)
    for f in frames:
        set_body(model, f, None, truth["poses"][frame_ids[f]], truth["transl"][frame_ids[f]] + shift)


@torch.no_grad()
def put_fitted_poses(model, frames: np.ndarray, frame_ids: np.ndarray, path: str) -> None:
    """In place: ``frames``' pose, translation (and orthographic camera) become those another init fit's
    ``params.npz`` at ``path`` gives the same frame ids; the avatar keeps its shape."""
    fit = np.load(path)
    row = {int(i): r for r, i in enumerate(fit["frame_ids"])}
    missing = [int(frame_ids[f]) for f in frames if int(frame_ids[f]) not in row]
    if missing or fit["poses"].shape[1:] != tuple(model.poses.shape[1:]):
        raise SystemExit(f"{path}: not a fit of this avatar's record (frames {missing[:5]} missing, or poses "
                         f"{fit['poses'].shape[1:]} against {tuple(model.poses.shape[1:])})")  # fmt: skip
    for f in frames:
        r = row[int(frame_ids[f])]
        camera = (fit["ortho_scale"][r], fit["ortho_trans"][r]) if "ortho_scale" in fit else None
        set_body(model, f, None, fit["poses"][r], fit["transl"][r], camera)


def main(argv=None) -> None:
    ap = trained_model_arguments(argparse.ArgumentParser(description=__doc__.split("\n\n")[0]))
    ap.add_argument("--truth", required=True, help="the subject's gt folder (params.npz, meshes.h5)")
    ap.add_argument("--refine-steps", type=int, default=EvalSettings.refine_steps)
    ap.add_argument("--csv", required=True)
    ap.add_argument("--append", action="store_true")
    ap.add_argument("--poses", nargs="+", default=["fitted", "true"],
                    help="passes: 'fitted' (the avatar's own), 'true' (the generator's), 'true:GROUP' (the "
                    "generator's rotations of one joint group: arms, legs, torso), or another init fit's params.npz "
                    "(labelled by its folder's name)")  # fmt: skip
    ap.add_argument("--frames", type=int, nargs="+", help="score these held-out frame ids (all of them, in --splits)")
    a = ap.parse_args(argv)
    torch.set_num_threads(2)
    truth = np.load(Path(a.truth) / "params.npz")
    st = EvalSettings(splits=tuple(a.splits), max_frames=0 if a.frames else a.max_frames, refine_steps=a.refine_steps,
                      supersample=a.supersample, worst=0, perceptual_dir=a.perceptual_dir or None)  # fmt: skip
    tables = []
    for poses in a.poses:
        trained = load_trained(a.model, a.record, a.body, device=a.device)  # fresh: refinement moves the poses
        model, data = trained.model, trained.data
        ids, split = np.asarray(data.frame_ids), np.asarray(data.split)
        if a.frames:  # the other held-out frames leave the scored splits (for a label that is none)
            leave = np.isin(split, [SPLITS[s] for s in a.splits]) & ~np.isin(ids, a.frames)
            data.split = split = np.where(leave, max(SPLITS.values()) + 1, split)
        scored = np.flatnonzero(np.isin(split, [SPLITS[s] for s in a.splits]))
        if poses not in ("fitted", "true") and not poses.startswith("true:"):
            put_fitted_poses(model, scored, ids, poses)
            poses = Path(poses).parent.name
        # the errors of the poses the avatar was given by a fit (a 'true' pass carries the workflow fit's)
        errors = pose_errors(model.poses.detach()[scored].cpu(), torch.as_tensor(truth["poses"][ids[scored]]),
                             truth["joint_names"])  # fmt: skip
        if poses == "true":
            put_true_poses(model, scored, ids, np.flatnonzero(split == SPLITS["train"]), truth)
        elif poses.startswith("true:"):
            put_true_group(model, scored, ids, truth, poses.split(":", 1)[1])
        t0 = time.perf_counter()
        df = evaluate(trained, a.record, st, gt_meshes=Path(a.truth) / "meshes.h5", subject=a.subject)
        err = pd.DataFrame(errors, index=scored)
        df = df[["subject", "frame", "frame_id", "split", "refined", *[c for c in SCORES if c in df]]]
        df = df.join(err, on="frame").assign(poses=poses, eval_wall_s=round(time.perf_counter() - t0, 1),
                                             device=device_name(a.device, torch.get_num_threads()))  # fmt: skip
        tables.append(df)
        print(df.drop(columns=["subject", "device"]).round(2).to_string(), flush=True)
    table = pd.concat(tables, ignore_index=True)
    save_table(table, a.csv, a.append)
    means = table.groupby(["split", "poses", "refined"])[["psnr", "psnr_outline", "psnr_clothing", "body_err_mm"]]
    print(means.mean().round(2).to_string())


if __name__ == "__main__":
    main()
