"""Entry point of ``delta reenact``: a trained head avatar re-rendered with another clip's face.

The driver is another trained avatar of a tracked face (its refined per-frame expressions and poses;
the same body model, so the same expression space and skeleton). Each driver frame gives the target's
anchor frame:

- the driver's expression activations, as they are (facial actions mean the same on every face);
- the driver's head motion: for each joint of the neck, head, jaw and eyes (:data:`FACE_JOINTS`), the
  driver's rotation relative to its own reference frame, put on top of the target's rotation in the
  anchor frame (``R = R_d(f) R_d(ref)ᵀ R_t(anchor)``), so the target keeps its own carriage of the head
  and turns, nods and looks as the driver does;

and everything else of the anchor frame: body, place, camera. Each frame renders as a pose the capture
never held (stage 2's F_e gets no time code) at the capture's whole-frame size, written as
``reenactment.mp4`` with ``reenactment.json`` saying what drove what.
"""

from __future__ import annotations

import contextlib
import logging
import time
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import torch

from delta import DeltaError
from delta.body.lbs import batch_rodrigues
from delta.body.rotations import matrix_to_axis_angle
from delta.data.frames import load_full_frames
from delta.export.video import posed_as, to_bgr, write_video
from delta.io import require_files, save_json
from delta.models.avatar import HybridAvatar
from delta.models.image import full_view, render_image
from delta.progress import Progress
from delta.training.run import load_trained

log = logging.getLogger(__name__)

#: name prefixes of the joints whose motion is the face's (Anny: neck01-03, head, eye.L/R; SMPL-X: neck,
#: head, jaw, left_eye_smplhf, right_eye_smplhf)
FACE_JOINTS = ("neck", "head", "jaw", "eye", "left_eye", "right_eye")


def face_joints(joint_names: Sequence[str]) -> list[int]:
    """Indices of the joints that move with the face (names starting with a :data:`FACE_JOINTS` prefix)."""
    return [j for j, n in enumerate(joint_names) if str(n).lower().startswith(FACE_JOINTS)]


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


@torch.no_grad()
def driven_face(
    target_pose: torch.Tensor, driver_poses: torch.Tensor, reference: int, joints: Sequence[int]
) -> torch.Tensor:
    """(F, K, 3) axis-angle of the ``joints`` for each driver frame: ``R_d(f) R_d(reference)ᵀ R_t`` from the
    target's anchor pose (J, 3) and the driver's poses (F, J, 3)."""
    j = list(joints)
    Rd = batch_rodrigues(driver_poses[:, j].reshape(-1, 3)).view(len(driver_poses), len(j), 3, 3)
    Rt = batch_rodrigues(target_pose[j])
    R = Rd @ Rd[reference].transpose(-1, -2) @ Rt
    return matrix_to_axis_angle(R.reshape(-1, 3, 3)).view(len(driver_poses), len(j), 3)


@contextlib.contextmanager
def expression_as(model: HybridAvatar, frame: int, expression: torch.Tensor) -> Iterator[None]:
    """Temporarily give ``frame`` another expression (E,) (restored on exit)."""
    old = model.expression.data[frame].clone()
    try:
        model.expression.data[frame] = expression.to(model.expression)
        yield
    finally:
        model.expression.data[frame] = old


@torch.no_grad()
def reenact_frames(target: HybridAvatar, anchor: int, driver: HybridAvatar, frames: Sequence[int], reference: int,
                   view) -> Iterator[torch.Tensor]:  # fmt: skip
    """Renders (H, W, 3) in [0, 1] of ``target``'s anchor frame driven by ``driver``'s ``frames``."""
    check_driver(target, driver)
    joints = face_joints(target.body.joint_names)
    frames = list(frames)
    rot = driven_face(target.poses.data[anchor], driver.poses.data[frames + [reference]], len(frames), joints)
    for k, f in enumerate(frames):
        pose = target.poses.data[anchor].clone()
        pose[joints] = rot[k].to(pose)
        with posed_as(target, anchor, pose, target.transl.data[anchor], timeless=True), \
                expression_as(target, anchor, driver.expression.data[f]):  # fmt: skip
            yield render_image(target, anchor, view=view, soft_silhouette=False)["rgb"]


def reenact_avatar(model_path: str | Path, record: str | Path, body_path: str | Path, driver_model: str | Path,
                   driver_record: str | Path, out_dir: str | Path, anchor: int = 0, reference: int = 0,
                   max_frames: int = 0, fps: int = 25, device: str = "cpu") -> dict:  # fmt: skip
    """Write ``reenactment.mp4`` and ``reenactment.json`` in ``out_dir``: the avatar of ``model_path`` driven
    by every frame of the avatar of ``driver_model`` (at most ``max_frames``, evenly spread; 0: all)."""
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
    images = (to_bgr(img) for img in reenact_frames(tr.model, anchor, drv.model, frames, reference, view))
    count = write_video(out / "reenactment.mp4", progress.counted(images, "rendered"), fps)
    summary = {"model": str(model_path), "driver": str(driver_model), "anchor": anchor, "reference": reference,
               "driver_frames": frames, "frames": count, "fps": fps, "resolution": "{}x{}".format(*full.size),
               "face_joints": [tr.model.body.joint_names[j] for j in face_joints(tr.model.body.joint_names)],
               "seconds": round(time.perf_counter() - t0, 2)}  # fmt: skip
    save_json(out / "reenactment.json", summary)
    log.info("%d frames of %s driven by %s in %.1f s", count, model_path, driver_model, summary["seconds"])
    return summary
