"""Entry point of ``delta reenact``: a trained head avatar re-rendered with another clip's face.

The driver is another trained avatar of a tracked face (its refined per-frame expressions and poses;
the same body model, so the same expression space and skeleton). Each driver frame gives the target's
anchor frame:

- the driver's expression activations, as they are (facial actions mean the same on every face);
- the driver's head motion: for each joint of the neck, head, jaw and eyes
  (:data:`delta.body.face_motion.FACE_JOINTS`), the
  driver's rotation relative to its own reference frame, put on top of the target's rotation in the
  anchor frame (``R = R_d(f) R_d(ref)ᵀ R_t(anchor)``), so the target keeps its own carriage of the head
  and turns, nods and looks as the driver does;

and everything else of the anchor frame: body, place, camera. Each frame renders as a pose the capture
never held (stage 2's F_e gets no time code) at the capture's whole-frame size, written as
``reenactment.mp4`` with ``reenactment.json`` saying what drove what.

Where both subjects are synthetic, the generator renders the truth (the avatar's subject at its anchor
frame driven by the driver subject's true expressions and head motion, composed the same way) and
:func:`score_reenactment` scores the avatar driven three ways against it: not at all, by the driver
avatar's tracked motion, and by the driver's true motion.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import torch

from delta import DeltaError
from delta import metrics as M
from delta.applications.truth import mean_scores, truth_frames, write_scores
from delta.body.face_motion import driven_poses, face_joints
from delta.data import SPLITS
from delta.data.frames import load_full_frames
from delta.eval.evaluate import Perceptual, score_image
from delta.eval.settings import EvalSettings
from delta.export.run import report_frames
from delta.export.video import posed_as, to_bgr, write_video
from delta.io import require_files, save_json
from delta.models.avatar import HybridAvatar
from delta.models.image import full_view, render_image
from delta.progress import Progress
from delta.training.run import load_trained

log = logging.getLogger(__name__)


def check_driver(target: HybridAvatar, driver: HybridAvatar, what: str = "the driver") -> None:
    """Both avatars must model a tracked face in one expression space and share the skeleton."""
    for name, m in (("the avatar", target), (what, driver)):
        if m.expression is None:
            raise DeltaError(f"{name} was trained without expressions (a still face): reenactment needs the "
                             "avatars of tracked talking faces (framing: head)")  # fmt: skip
    if target.expression.shape[1] != driver.expression.shape[1]:
        raise DeltaError(f"{what} has {driver.expression.shape[1]} expression coefficients, the avatar "
                         f"{target.expression.shape[1]}: they need the same body model")  # fmt: skip
    if list(target.body.joint_names) != list(driver.body.joint_names):
        raise DeltaError(f"{what} has another skeleton than the avatar: they need the same body model")


@contextlib.contextmanager
def expression_as(model: HybridAvatar, frame: int, expression: torch.Tensor) -> Iterator[None]:
    """Temporarily give ``frame`` another expression (E,) (restored on exit)."""
    old = model.expression.data[frame].clone()
    try:
        model.expression.data[frame] = expression.to(model.expression)
        yield
    finally:
        model.expression.data[frame] = old


@dataclasses.dataclass
class Drive:
    """A face's motion: per-frame poses (F, J, 3) and expression activations (F, E), and the pose (J, 3) of its
    reference frame (whose head means "no turn")."""

    poses: torch.Tensor
    expressions: torch.Tensor
    reference: torch.Tensor

    def __len__(self) -> int:
        return len(self.poses)


def avatar_drive(driver: HybridAvatar, frames: Sequence[int], reference: int) -> Drive:
    """The motion of a trained avatar's ``frames`` (its refined poses and expressions)."""
    frames = list(frames)
    return Drive(driver.poses.data[frames].clone(), driver.expression.data[frames].clone(),
                 driver.poses.data[reference].clone())  # fmt: skip


def still_drive(target: HybridAvatar, anchor: int, count: int) -> Drive:
    """No motion: the anchor's own pose and expression ``count`` times (the avatar as trained, its frame
    rendered as the driven ones are, without a time code)."""
    pose = target.poses.data[anchor]
    return Drive(pose[None].repeat(count, 1, 1), target.expression.data[anchor][None].repeat(count, 1), pose.clone())


@torch.no_grad()
def reenact_frames(target: HybridAvatar, anchor: int, drive: Drive, view, supersample: int = 1) -> Iterator[dict]:
    """Renders (``render_image``'s dicts) of ``target``'s anchor frame driven by each frame of ``drive``."""
    poses = driven_poses(target.poses.data[anchor], drive.poses.to(target.poses), drive.reference.to(target.poses),
                         target.body.joint_names)  # fmt: skip
    for k in range(len(drive)):
        with posed_as(target, anchor, poses[k], target.transl.data[anchor], timeless=True), \
                expression_as(target, anchor, drive.expressions[k]):  # fmt: skip
            yield render_image(target, anchor, supersample=supersample, view=view, soft_silhouette=False)


def truth_drive(params: str | Path, frame_ids: Sequence[int], target: HybridAvatar) -> Drive:
    """The true motion of a reenactment's generated truth (``gt/params.npz``): its poses and expressions of the
    capture frames ``frame_ids``, relative to its frame of the driver's reference (``drive_reference``).
    Its poses hold the driver's face motion on top of the avatar subject's true anchor pose, so relative to
    that frame they are the driver's own true motion; the joints and facial actions are matched by name."""
    with np.load(params, allow_pickle=False) as p:
        if "drive_reference" not in p:
            raise DeltaError(f"{params}: not the generated truth of a reenactment (no 'drive_reference')")
        poses, acts, ref = p["poses"], p["expression"], int(p["drive_reference"])
        joints, actions = [str(n) for n in p["joint_names"]], [str(n) for n in p["expression_names"]]
    body = target.body
    for what, theirs, ours in (
        ("joints", joints, body.joint_names),
        ("facial actions", actions, body.expression_names),
    ):
        missing = sorted(set(ours) - set(theirs))
        if missing:
            raise DeltaError(f"{params}: the truth's body has no {what} {missing[:5]} of the avatar's body model")
    j = [joints.index(n) for n in body.joint_names]
    e = [actions.index(n) for n in body.expression_names]
    ids = list(frame_ids)
    t = lambda a: torch.as_tensor(a, dtype=target.poses.dtype)  # noqa: E731
    return Drive(t(poses[ids][:, j]), t(acts[ids][:, e]), t(poses[ref][j]))


def score_reenactment(tr, drv, anchor: int, reference: int, truth: str | Path, view, count: int,
                      perceptual_dir: str | None = None, supersample: int = 2) -> list[dict]:  # fmt: skip
    """Rows of ``scores.csv``: ``count`` of the driver's held-out frames (evenly spaced) of the reenactment
    (``tr`` driven by ``drv``) scored against its generated truth (the avatar's subject driven by the driver
    subject's true motion, :func:`delta.synthetic.generate.scene_motion`), each rendered three ways from the
    avatar's anchor frame: ``as_trained`` (not driven: the frame as the avatar has it), ``edited`` (driven by
    the driver avatar's tracked motion: the application) and ``true_drive`` (driven by the driver's true
    motion: what the avatar renders of a perfectly tracked driver). Scores: PSNR, SSIM, L1 and ST-LPIPS on
    the whole image and on the head (face, hair and neck: the person less its clothing), the exterior mask's
    IoU with the truth's clothing and hair, and the mean absolute error of the expression activations."""
    truth = Path(truth)
    params = truth / "gt" / "params.npz"
    require_files(truth=params)
    with np.load(params, allow_pickle=False) as p:
        if "drive_anchor" not in p:
            raise DeltaError(f"{params}: not the generated truth of a reenactment (no 'drive_anchor')")
        drove = int(p["drive_anchor"]), int(p["drive_reference"])
    wanted = int(tr.data.frame_ids[anchor]), int(drv.data.frame_ids[reference])
    if drove != wanted:
        raise DeltaError(f"{params}: generated for the avatar's frame {drove[0]} driven relative to the driver's "
                         f"frame {drove[1]}; this reenactment drives frame {wanted[0]} relative to {wanted[1]}")  # fmt: skip
    frames = report_frames(drv.data.split, count)
    ids = [int(drv.data.frame_ids[f]) for f in frames]
    model = tr.model
    images = truth_frames(truth, ids, (view.width, view.height), tr.settings.background)
    perceptual = Perceptual(EvalSettings(perceptual_dir=perceptual_dir), model.background.device)
    true = truth_drive(params, ids, model)
    drives = {"as_trained": still_drive(model, anchor, len(frames)), "edited": avatar_drive(drv.model, frames, reference),
              "true_drive": true}  # fmt: skip
    split = np.asarray(drv.data.split)
    rows = []
    for variant, drive in drives.items():
        for k, img in enumerate(reenact_frames(model, anchor, drive, view, supersample)):
            head = images.head[k]
            row = {"application": "reenact", "variant": variant, "frame": frames[k], "frame_id": ids[k],
                   "split": SPLITS[int(split[frames[k]])],
                   **score_image(img, images.images[k], {"head": head}, perceptual, ("head",), tr.settings.background),
                   "exterior_iou": M.iou(img["nerf_mask"] > 0.5, images.exterior[k]) if model.nerf is not None
                   else float("nan"),
                   "expression_err": float((drive.expressions[k].cpu() - true.expressions[k].cpu()).abs().mean())}  # fmt: skip
            rows.append(row)
            log.info("%s frame %d: %.2f dB (head %.2f dB)", variant, ids[k], row["psnr"], row["psnr_head"])
    return rows


def reenact_avatar(model_path: str | Path, record: str | Path, body_path: str | Path, driver_model: str | Path,
                   driver_record: str | Path, out_dir: str | Path, anchor: int = 0, reference: int = 0,
                   max_frames: int = 0, fps: int = 25, device: str = "cpu", truth: str | Path | None = None,
                   perceptual_dir: str | None = None, score_frames: int = 4, supersample: int = 2) -> dict:  # fmt: skip
    """Write ``reenactment.mp4``, ``reenactment.json`` and ``scores.csv`` in ``out_dir``: the avatar of
    ``model_path`` driven by every frame of the avatar of ``driver_model`` (at most ``max_frames``, evenly
    spread; 0: all); with ``truth`` (the generated capture of the avatar's subject driven by the driver's),
    ``score_frames`` of the driver's held-out frames scored against it (:func:`score_reenactment`; otherwise
    ``scores.csv`` holds its header alone)."""
    t0 = time.perf_counter()
    require_files(model=model_path, record=record, body_model=body_path, driver_model=driver_model,
                  driver_record=driver_record)  # fmt: skip
    tr = load_trained(model_path, record, body_path, device)
    drv = load_trained(driver_model, driver_record, body_path, device)
    check_driver(tr.model, drv.model, f"the driver {driver_model}")
    n_target, n_driver = len(tr.data.frame_ids), len(drv.data.frame_ids)
    for name, value, count in (("anchor", anchor, n_target), ("reference", reference, n_driver)):
        if not 0 <= value < count:
            raise DeltaError(f"--{name} {value}: the {'avatar' if name == 'anchor' else 'driver'} has {count} frames")
    frames = list(range(n_driver))
    if max_frames and n_driver > max_frames:
        frames = np.linspace(0, n_driver - 1, max_frames).round().astype(int).tolist()
    full = load_full_frames(record, [anchor], tr.settings.background)
    view = full_view(full, tr.model.resolution)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    progress = Progress(f"reenactment ({view.width}x{view.height})", len(frames))
    drive = avatar_drive(drv.model, frames, reference)
    images = (to_bgr(img["rgb"]) for img in reenact_frames(tr.model, anchor, drive, view))
    count = write_video(out / "reenactment.mp4", progress.counted(images, "rendered"), fps)
    rows = []
    if truth is not None and score_frames:
        rows = score_reenactment(tr, drv, anchor, reference, truth, view, score_frames, perceptual_dir, supersample)
    write_scores(out / "scores.csv", rows)
    summary = {"model": str(model_path), "driver": str(driver_model), "anchor": anchor, "reference": reference,
               "driver_frames": frames, "frames": count, "fps": fps, "resolution": "{}x{}".format(*full.size),
               "face_joints": [tr.model.body.joint_names[j] for j in face_joints(tr.model.body.joint_names)],
               "scores": mean_scores(rows), "seconds": round(time.perf_counter() - t0, 2)}  # fmt: skip
    save_json(out / "reenactment.json", summary)
    log.info("%d frames of %s driven by %s in %.1f s", count, model_path, driver_model, summary["seconds"])
    return summary
