"""One face's motion put on another: the joints that move with a face, and a driver's head motion relative to
its own reference frame composed onto a target's pose (reenactment, and its generated truth)."""

from __future__ import annotations

from typing import Sequence

import torch

from delta.body.lbs import batch_rodrigues
from delta.body.rotations import matrix_to_axis_angle

#: name prefixes of the joints whose motion is the face's (Anny: neck01-03, head, eye.L/R; SMPL-X: neck,
#: head, jaw, left_eye_smplhf, right_eye_smplhf)
FACE_JOINTS = ("neck", "head", "jaw", "eye", "left_eye", "right_eye")


def face_joints(joint_names: Sequence[str]) -> list[int]:
    """Indices of the joints that move with the face (names starting with a :data:`FACE_JOINTS` prefix)."""
    return [j for j, n in enumerate(joint_names) if str(n).lower().startswith(FACE_JOINTS)]


@torch.no_grad()
def driven_face(
    target_pose: torch.Tensor, driver_poses: torch.Tensor, reference: torch.Tensor, joints: Sequence[int]
) -> torch.Tensor:
    """(F, K, 3) axis-angle of the ``joints`` for each driver frame: ``R_d(f) R_d(ref)ᵀ R_t`` from the target's
    anchor pose (J, 3), the driver's poses (F, J, 3) and the driver's reference pose (J, 3)."""
    j = list(joints)
    Rd = batch_rodrigues(driver_poses[:, j].reshape(-1, 3)).view(len(driver_poses), len(j), 3, 3)
    Rref = batch_rodrigues(reference[j].to(driver_poses))
    Rt = batch_rodrigues(target_pose[j].to(driver_poses))
    R = Rd @ Rref.transpose(-1, -2) @ Rt
    return matrix_to_axis_angle(R.reshape(-1, 3, 3)).view(len(driver_poses), len(j), 3)


def driven_poses(target_pose: torch.Tensor, driver_poses: torch.Tensor, driver_reference: torch.Tensor,
                 joint_names: Sequence[str]) -> torch.Tensor:  # fmt: skip
    """(F, J, 3): the target's pose (J, 3) in every frame, its face joints driven by the driver's poses (F, J, 3)
    relative to the driver's reference pose (J, 3) (:func:`driven_face`)."""
    joints = face_joints(joint_names)
    out = target_pose[None].repeat(len(driver_poses), 1, 1)
    out[:, joints] = driven_face(target_pose, driver_poses, driver_reference, joints).to(out)
    return out
