"""Entry point of ``delta animate``: a trained avatar driven by another motion.

The motion (:mod:`delta.applications.motion`) is placed where the avatar stood (:func:`place`): its
world is turned so that its up is the capture's up (:mod:`delta.body.upright`: estimated from the fit,
as the motion's own is unless its convention names it, AMASS's z), its first frame starts at the
anchor frame's place facing the anchor frame's way, and the whole motion is lifted onto the capture's
floor (:func:`onto_floor`). A motion recorded in any world (AMASS's z-up, another capture's camera)
thus stands upright on the floor where the avatar stood, seen by that frame's camera. Each frame is
rendered as a pose the capture never held (stage 2's F_e without a time code) at the capture's
whole-frame scoring size, written as ``animation.mp4``, and as ``animation.glb`` (skinned and animated, upright
on y = 0: :mod:`delta.export.animated`); with ``meshes`` set, the posed body and
clothing meshes of every frame too. ``animation.json`` says what was driven by what, and how it was
placed."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from delta import DeltaError
from delta.applications.motion import Motion, read_motion, resample
from delta.applications.settings import AnimateSettings
from delta.body.lbs import batch_rodrigues, posed_joints
from delta.body.rotations import matrix_to_axis_angle
from delta.body.upright import (
    Upright,
    axis_angle_matrix,
    body_axes,
    floor_height,
    heading,
    robust_direction,
    rotation_between,
    signed_angle,
)
from delta.cameras.models import camera_vertical
from delta.data.frames import load_full_frames
from delta.export.meshes import MeshPart, body_mesh, pose_clothing, read_mesh, write_mesh
from delta.export.run import write_avatar_animation
from delta.export.video import baked_trajectory, capture_upright, posed_as, to_bgr, write_video
from delta.io import require_files, save_json
from delta.models.image import full_view, render_image
from delta.progress import Progress
from delta.training.run import load_trained

log = logging.getLogger(__name__)


def place(root: torch.Tensor, transl: torch.Tensor, anchor_root: torch.Tensor, anchor_transl: torch.Tensor,
          up: torch.Tensor, motion_up: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """Root axis-angle (F, 3) and translation (F, 3) of a motion moved rigidly onto the capture: upright on
    the capture's ``up`` (3,), starting where the anchor frame stood and facing where it faced.

    With B the smallest rotation taking ``motion_up`` (the motion world's up) onto ``up`` and H the turn
    about ``up`` that gives the motion's first frame the heading of ``anchor_root`` (3,), A = H B: frame f
    gets the root rotation A R_f and the translation t_anchor + A (t_f − t_0), the motion's whole world
    turned by A and shifted, which is the same motion. A lean or a bow in the motion's first frame stays
    a lean, where aligning that frame with the anchor would tilt the whole motion. (The root joint turns
    about its own rest position, so its position is J0 + t for either body and only differences of t
    matter.)
    """
    R = batch_rodrigues(root.double())
    up, motion_up = up.double(), motion_up.double()
    B = rotation_between(motion_up, up)
    anchor = batch_rodrigues(anchor_root.double()[None])[0]
    A = axis_angle_matrix(up, signed_angle(heading(B @ R[0], up), heading(anchor, up), up)) @ B
    new_root = matrix_to_axis_angle(A @ R)
    new_t = anchor_transl.double() + (transl.double() - transl[0].double()) @ A.T
    return new_root.to(root.dtype), new_t.to(transl.dtype)


def onto_floor(
    transl: torch.Tensor, joints: torch.Tensor, up: torch.Tensor, floor: float
) -> tuple[torch.Tensor, float]:
    """(F, 3) translations lifted along ``up`` so that the motion's floor (from its (F, J, 3) posed joints,
    :func:`~delta.body.upright.floor_height`) is the capture's ``floor``; and the lift (m)."""
    lift = floor - floor_height(joints.double(), up.double())
    return transl + lift * up.to(transl), lift


def motion_up(motion: Motion) -> tuple[torch.Tensor, str]:
    """(3,) the motion world's up and where it came from: the file's (its ``up``, or its convention), or
    estimated from its root rotations as a capture's is."""
    if motion.up is not None:
        return torch.from_numpy(motion.up).double(), f"{motion.source} file"
    R = batch_rodrigues(torch.from_numpy(motion.poses[:, 0]).double())
    return robust_direction(body_axes(R)), "estimated from the motion"


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
    upright = capture_upright(model)
    placed = {"upright": upright.describe(camera_vertical(model.camera(0)))}
    with baked_trajectory(model, anchor):
        poses, transl, how = placed_motion(model, anchor, motion, upright)
        placed.update(how)
        frames = render_motion(model, anchor, poses, transl, view, out / "meshes" if settings.meshes else None,
                               surface)  # fmt: skip
        count = write_video(out / "animation.mp4", frames, max(int(round(motion.fps)), 1))
        glb = write_avatar_animation(model, batch_rodrigues(poses), transl, np.arange(motion.num_frames) / motion.fps,
                                     out / "animation.glb", surface, upright)  # fmt: skip
    summary = {"placement": placed, "glb": glb, "model": str(model_path), "motion": str(motion_path), "motion_kind": motion.source,
               "frames": count, "fps": motion.fps, "anchor": anchor, "anchor_frame_id": int(tr.data.frame_ids[anchor]),
               "resolution": "{}x{}".format(*full.size), "meshes": bool(settings.meshes),
               "clothing_mesh": surface is not None and not surface.empty, "settings": vars(settings).copy(),
               "seconds": round(time.perf_counter() - t_start, 2)}  # fmt: skip
    save_json(out / "animation.json", summary)
    log.info("%d frames of %s (%s) driven at %s in %.1f s", count, motion_path, motion.source, summary["resolution"],
             summary["seconds"])  # fmt: skip
    return summary


@torch.no_grad()
def placed_motion(model, anchor: int, motion: Motion, upright: Upright) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """(F, J, 3) poses and (F, 3) translations of ``motion`` placed upright on the capture's floor from the
    ``anchor`` frame's place and heading (:func:`place`, :func:`onto_floor`), and how it was placed."""
    ref = model.poses.data
    up = upright.up.to(ref)
    m_up, m_up_from = motion_up(motion)
    poses = torch.from_numpy(motion.poses).to(ref)
    root, transl = place(poses[:, 0], torch.from_numpy(motion.transl).to(ref), ref[anchor, 0], model.transl.data[anchor],
                         up, m_up.to(ref))  # fmt: skip
    poses[:, 0] = root
    joints = posed_joints(model.body, model.betas.detach(), batch_rodrigues(poses), transl)
    transl, lift = onto_floor(transl, joints, up, upright.floor)
    return poses, transl, {"motion_up": [round(float(c), 5) for c in m_up], "motion_up_from": m_up_from,
                           "lift_m": round(lift, 4)}  # fmt: skip


def drive(model, anchor: int, motion: Motion, view, mesh_dir: Path | None, clothing: MeshPart | None,
          upright: Upright | None = None):  # fmt: skip
    """Rendered frames (uint8 BGR) of ``model`` posed by ``motion``, placed upright on the capture's floor
    (``upright``: estimated from the model when not given) from the ``anchor`` frame's place and camera
    (:func:`placed_motion`, :func:`render_motion`)."""
    upright = capture_upright(model) if upright is None else upright
    poses, transl, _ = placed_motion(model, anchor, motion, upright)
    return render_motion(model, anchor, poses, transl, view, mesh_dir, clothing)


@torch.no_grad()
def render_motion(model, anchor: int, poses: torch.Tensor, transl: torch.Tensor, view, mesh_dir: Path | None,
                  clothing: MeshPart | None):  # fmt: skip
    """Rendered frames (uint8 BGR) of ``model`` given the (F, J, 3) ``poses`` and (F, 3) ``transl`` in the
    ``anchor`` frame's slot, seen by its camera; with ``mesh_dir``, each frame's posed meshes are written
    there."""
    progress = Progress(f"animation ({view.width}x{view.height})", len(poses))
    for f in range(len(poses)):
        with posed_as(model, anchor, poses[f], transl[f], timeless=True):
            if mesh_dir is not None:
                body, out = body_mesh(model, anchor)
                write_mesh(mesh_dir / f"body_{f:05d}.ply", body)
                if clothing is not None and not clothing.empty:
                    write_mesh(mesh_dir / f"clothing_{f:05d}.ply", pose_clothing(model, clothing, out))
            image = to_bgr(render_image(model, anchor, view=view, soft_silhouette=False)["rgb"])
        progress.tick("rendered")
        yield image
