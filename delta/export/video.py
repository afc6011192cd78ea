"""Videos and images of the avatar: a turntable, the novel (test) poses, reference | render | error."""

from __future__ import annotations

import contextlib
import math
import os
from typing import Iterable, Iterator

import cv2
import numpy as np
import torch

from delta.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from delta.body.upright import Upright, axis_angle_matrix, estimate_upright, level_rotation
from delta.cameras.models import camera_vertical
from delta.io import atomic_path
from delta.models.avatar import HybridAvatar
from delta.models.image import View, render_image

#: Absolute error (mean over RGB) shown at the top of the heat map's colour scale.
ERROR_SCALE = 0.25


def moved_params(root_pose: torch.Tensor, transl: torch.Tensor, root_joint: torch.Tensor, centre: torch.Tensor,
                 rotation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """Root axis-angle (3,) and translation (3,) that rotate the posed body by the (3, 3) ``rotation``
    about ``centre``.

    The root's rest -> posed map is x -> R0 (x - J0) + J0 + t; the moved body is A (that - c) + c,
    so R0' = A R0 and t' = A (J0 + t - c) + c - J0 (J0: the shaped rest root joint).
    """
    A = rotation.to(root_pose)
    R0 = axis_angle_to_matrix(root_pose[None])[0]
    new_root = matrix_to_axis_angle((A @ R0)[None])[0]
    return new_root, A @ (root_joint + transl - centre) + centre - root_joint


def view_directions(model: HybridAvatar, frame: int, centre: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(3,) world direction from the frame's camera to ``centre`` and (3,) the camera's image-up direction
    in the world."""
    cam = model.camera(frame)
    view = centre - cam.center.to(centre) if model.pinhole else centre.new_tensor([0.0, 0.0, -1.0])
    return view, camera_vertical(cam).to(centre)


def capture_upright(model: HybridAvatar) -> Upright:
    """The capture's up direction and floor, estimated from every frame's fitted body (see
    :mod:`delta.body.upright`)."""
    with torch.no_grad():
        rot, joints = model.skeletons()
        level = camera_vertical(model.camera(0))
    return estimate_upright(rot.double().cpu(), joints.double().cpu(), level)


@contextlib.contextmanager
def posed_as(model: HybridAvatar, frame: int, pose: torch.Tensor, transl: torch.Tensor,
             timeless: bool = False) -> Iterator[None]:  # fmt: skip
    """Temporarily give ``frame`` another pose (J, 3) and translation (3,) (restored on exit);
    ``timeless``: the frame also leaves the training sequence, so stage 2's F_e gets no time code
    (a pose the capture never held)."""
    old = model.poses.data[frame].clone(), model.transl.data[frame].clone(), model.frame_time[frame].clone()
    try:
        model.poses.data[frame] = pose
        model.transl.data[frame] = transl
        if timeless:
            model.frame_time[frame] = float("nan")
        yield
    finally:
        model.poses.data[frame], model.transl.data[frame], model.frame_time[frame] = old


@contextlib.contextmanager
def baked_trajectory(model: HybridAvatar, frame: int) -> Iterator[None]:
    """Fold the trajectory's correction of ``frame`` into its own root pose, translation and camera, and
    switch the trajectory off (restored on exit): the frame renders the same, and a change of its
    root pose (a turntable) acts on the corrected body."""
    traj = model.trajectory
    if traj is None:
        yield
        return
    per_frame = [p.data[frame].clone() for p in model.per_frame_parameters()]
    try:
        with torch.no_grad():
            turn, shift = traj(frame)
            R = axis_angle_to_matrix(turn[None])[0] @ axis_angle_to_matrix(model.poses[frame, :1])[0]
            model.poses.data[frame, 0] = matrix_to_axis_angle(R[None])[0]
            if model.pinhole:
                model.transl.data[frame] += shift
            else:
                model.ortho_scale.data[frame] *= shift[0].exp()
                model.ortho_trans.data[frame] += shift[1:]
        model.trajectory = None
        yield
    finally:
        model.trajectory = traj
        for p, old in zip(model.per_frame_parameters(), per_frame):
            p.data[frame] = old


def to_bgr(rgb: torch.Tensor | np.ndarray) -> np.ndarray:
    """(H, W, 3) float RGB in [0, 1] -> uint8 BGR."""
    a = rgb.detach().cpu().numpy() if isinstance(rgb, torch.Tensor) else np.asarray(rgb)
    return cv2.cvtColor((np.clip(a, 0, 1) * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR)


def write_video(path: str | os.PathLike, frames: Iterable[np.ndarray], fps: int) -> int:
    """Write uint8 BGR frames (H, W, 3) as an mp4 (MPEG-4 part 2), atomically; returns the frame count."""
    count, writer = 0, None
    with atomic_path(path) as tmp:
        try:
            for img in frames:
                if writer is None:
                    h, w = img.shape[:2]
                    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
                    if not writer.isOpened():
                        raise RuntimeError(f"{path}: OpenCV cannot write mp4v video")
                writer.write(img)
                count += 1
        finally:
            if writer is not None:
                writer.release()
        if count == 0:
            raise ValueError(f"{path}: no frames to write")
    return count


@torch.no_grad()
def turntable(model: HybridAvatar, frame: int, count: int, view: View | None = None,
              upright: Upright | None = None) -> Iterator[np.ndarray]:  # fmt: skip
    """``count`` renders of ``frame`` turned through one full revolution about the capture's up axis
    (``upright``: estimated from the fit when not given), the view rolled so that axis looks vertical
    (the model's crop, or ``view``: the capture's whole frame)."""
    upright = capture_upright(model) if upright is None else upright
    with baked_trajectory(model, frame):
        yield from _turntable(model, frame, count, view, upright.up)


def turntable_rotations(up: torch.Tensor, level: torch.Tensor, count: int) -> list[torch.Tensor]:
    """The (3, 3) rotation of each turntable frame: a turn by 2πk/count about ``up``, then ``level``."""
    return [level @ axis_angle_matrix(up, 2 * math.pi * k / count) for k in range(count)]


def turn_centre(model: HybridAvatar, vertices: torch.Tensor) -> torch.Tensor:
    """(3,) the point a turntable turns about: the mean of the posed ``vertices`` (V, 3) the capture frames of
    what it models (a head-and-shoulders capture turns about its head and shoulders, not about a body
    below the picture; a box's centre would depend on the world's axes)."""
    framed = model.framed.to(vertices.device)
    return vertices[framed].mean(0) if bool(framed.any()) else vertices.mean(0)


def turntable_poses(model: HybridAvatar, frame: int, count: int, up: torch.Tensor) -> list[tuple[torch.Tensor, ...]]:
    """The (J, 3) pose and (3,) translation of ``frame`` in each of ``count`` turntable views: the body turned
    about ``up`` through :func:`turn_centre`, then levelled for the frame's camera."""
    out = model.pose_body(frame)
    centre = turn_centre(model, out.vertices[0])
    root = int((model.body.parents == -1).nonzero()[0])
    root_joint = out.rest_joints[0, root]
    pose, transl = model.poses[frame, root], model.transl[frame]
    up = up.to(centre)
    level = level_rotation(up, *view_directions(model, frame, centre))
    posed = []
    for rotation in turntable_rotations(up, level, count):
        new_pose, new_t = moved_params(pose, transl, root_joint, centre, rotation)
        posed.append((torch.cat([new_pose[None], model.poses[frame, 1:]]), new_t))
    return posed


def _turntable(model: HybridAvatar, frame: int, count: int, view: View | None, up: torch.Tensor):
    for pose, transl in turntable_poses(model, frame, count, up):
        with posed_as(model, frame, pose, transl):
            yield to_bgr(render_image(model, frame, view=view, soft_silhouette=False)["rgb"])


def render_frames(model: HybridAvatar, frames: Iterable[int], view: View | None = None) -> Iterator[np.ndarray]:
    for f in frames:
        yield to_bgr(render_image(model, int(f), view=view, soft_silhouette=False)["rgb"])


def error_map(reference: torch.Tensor, render: torch.Tensor) -> np.ndarray:
    """(H, W, 3) uint8 BGR heat map of the mean absolute RGB error, ``ERROR_SCALE`` at the top."""
    err = (reference - render).abs().mean(-1).cpu().numpy() / ERROR_SCALE
    return cv2.applyColorMap((np.clip(err, 0, 1) * 255).round().astype(np.uint8), cv2.COLORMAP_INFERNO)


def side_by_side(reference: torch.Tensor, render: torch.Tensor) -> np.ndarray:
    """[reference | render | error] as one uint8 BGR image."""
    return np.concatenate([to_bgr(reference), to_bgr(render), error_map(reference, render)], axis=1)
