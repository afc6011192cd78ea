"""Entry point of ``delta animate``: a trained avatar driven by another motion.

The motion (:mod:`delta.applications.motion`) is placed where the avatar stood: its first frame takes
the anchor frame's root rotation and translation, and every later frame moves relative to that one
(:func:`place`), so a motion recorded in any world (AMASS's z-up, another capture's camera) starts
where and as the avatar stood in its capture, seen by that frame's camera. Each frame is rendered as
a pose the capture never held (stage 2's F_e without a time code) at the capture's whole-frame
scoring size, written as ``animation.mp4``; with ``meshes`` set, the posed body and clothing meshes of
every frame too. ``animation.json`` says what was driven by what.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch
from kornia.geometry.conversions import rotation_matrix_to_axis_angle

from delta import DeltaError
from delta.applications.motion import Motion, read_motion, resample
from delta.applications.settings import AnimateSettings
from delta.body.lbs import batch_rodrigues
from delta.data.frames import load_full_frames
from delta.export.meshes import MeshPart, body_mesh, pose_clothing, read_mesh, write_mesh
from delta.export.video import baked_trajectory, posed_as, to_bgr, write_video
from delta.io import require_files, save_json
from delta.models.image import full_view, render_image
from delta.progress import Progress
from delta.training.run import load_trained

log = logging.getLogger(__name__)


def place(root: torch.Tensor, transl: torch.Tensor, anchor_root: torch.Tensor,
          anchor_transl: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """Root axis-angle (F, 3) and translation (F, 3) of a motion moved rigidly so that its first frame
    has ``anchor_root`` (3,) and ``anchor_transl`` (3,).

    With A = R_anchor R_0ᵀ (R_0: the motion's first root rotation), frame f gets the root rotation
    A R_f and the translation t_anchor + A (t_f − t_0): the motion's whole world turned by A and
    shifted, which is the same motion. (The root joint turns about its own rest position, so its
    position is J0 + t for either body and only differences of t matter.)
    """
    R = batch_rodrigues(root.double())
    A = batch_rodrigues(anchor_root.double()[None])[0] @ R[0].T
    new_root = rotation_matrix_to_axis_angle(A @ R)
    new_t = anchor_transl.double() + (transl.double() - transl[0].double()) @ A.T
    return new_root.to(root.dtype), new_t.to(transl.dtype)


def check_anchor(anchor: int, frames: int, train: np.ndarray) -> int:
    """The anchor frame: ``anchor`` when it is a frame of the capture, the first training frame for -1."""
    if anchor == -1:
        return int(train[0])
    if not 0 <= anchor < frames:
        raise DeltaError(f"anchor: frame {anchor} is not a frame of the capture (0..{frames - 1})")
    return anchor


def _clothing(path: str | Path | None) -> MeshPart | None:
    """The export's clothing surface in the NeRF's space (clothing_nerf_space.ply), when there is one."""
    return read_mesh(path) if path is not None and Path(path).is_file() else None


def animate_avatar(model_path: str | Path, record: str | Path, body_path: str | Path, motion_path: str | Path,
                   out_dir: str | Path, settings: AnimateSettings, clothing: str | Path | None = None,
                   device: str = "cpu") -> dict:  # fmt: skip
    """Render ``animation.mp4`` (and the per-frame meshes) of a trained avatar driven by a motion file;
    returns the summary written as ``animation.json``."""
    t_start = time.perf_counter()
    require_files(model=model_path, record=record, body_model=body_path)
    tr = load_trained(model_path, record, body_path, device)
    model, body = tr.model, tr.model.body
    motion = read_motion(motion_path, body.joint_names, body.parents.cpu().numpy(),
                         body.joints_template.cpu().double().numpy())  # fmt: skip
    motion = resample(motion, settings.fps, settings.max_frames)
    anchor = check_anchor(settings.anchor, len(tr.data.frame_ids), tr.data.train)
    full = load_full_frames(record, [anchor], tr.settings.background)
    view = full_view(full, model.resolution)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    surface = _clothing(clothing) if model.nerf is not None else None
    if settings.meshes:
        (out / "meshes").mkdir(exist_ok=True)
    with baked_trajectory(model, anchor):
        frames = drive(model, anchor, motion, view, out / "meshes" if settings.meshes else None, surface)
        count = write_video(out / "animation.mp4", frames, max(int(round(motion.fps)), 1))
    summary = {"model": str(model_path), "motion": str(motion_path), "motion_kind": motion.source,
               "frames": count, "fps": motion.fps, "anchor": anchor, "anchor_frame_id": int(tr.data.frame_ids[anchor]),
               "resolution": "{}x{}".format(*full.size), "meshes": bool(settings.meshes),
               "clothing_mesh": surface is not None and not surface.empty, "settings": vars(settings).copy(),
               "seconds": round(time.perf_counter() - t_start, 2)}  # fmt: skip
    save_json(out / "animation.json", summary)
    log.info("%d frames of %s (%s) driven at %s in %.1f s", count, motion_path, motion.source, summary["resolution"],
             summary["seconds"])  # fmt: skip
    return summary


@torch.no_grad()
def drive(model, anchor: int, motion: Motion, view, mesh_dir: Path | None, clothing: MeshPart | None):
    """Rendered frames (uint8 BGR) of ``model`` posed by ``motion`` from the ``anchor`` frame's place and
    camera; with ``mesh_dir``, each frame's posed meshes are written there."""
    ref = model.poses.data
    poses = torch.from_numpy(motion.poses).to(ref)
    root, transl = place(
        poses[:, 0], torch.from_numpy(motion.transl).to(ref), ref[anchor, 0], model.transl.data[anchor]
    )
    poses[:, 0] = root
    progress = Progress(f"animation ({view.width}x{view.height})", motion.num_frames)
    for f in range(motion.num_frames):
        with posed_as(model, anchor, poses[f], transl[f], timeless=True):
            if mesh_dir is not None:
                body, out = body_mesh(model, anchor)
                write_mesh(mesh_dir / f"body_{f:05d}.ply", body)
                if clothing is not None and not clothing.empty:
                    write_mesh(mesh_dir / f"clothing_{f:05d}.ply", pose_clothing(model, clothing, out))
            image = to_bgr(render_image(model, anchor, view=view, soft_silhouette=False)["rgb"])
        progress.tick("rendered")
        yield image
