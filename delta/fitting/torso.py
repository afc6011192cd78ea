"""Where a leaning torso bends: at the root or along the spine.

The fit's first stage turns the root to the torso's keypoints with the limbs at rest, so a body bent
forward at the waist starts with its whole pelvis tipped over and its hips flexed back to put the legs
where they stand. Keypoints cannot tell the two apart (the same neck, shoulders, hips, knees and ankles),
and the fit stays in whichever it started from: on the synthetic deep bend the fitted root is 38–48° off
while a fit started from the truth stays within 3° at a lower cost of the fit's own objective
(docs/fitting.md). So a frame fitted free also starts with part of its root's lean moved into the spine:
the root keeps ``keep`` of its tilt away from the capture's vertical, the rest is spread evenly along the
spine chain, and the root's other children (the hips) turn back by what the root gave up, so that the
legs stay where they were. The fit keeps, a frame, the start whose pose costs least.

Shapes: F frames, J joints; poses are axis-angle in the body model's world-aligned joint axes (y up).
"""

from __future__ import annotations

import torch
from kornia.geometry.conversions import rotation_matrix_to_axis_angle

from delta.body.lbs import batch_rodrigues
from delta.body.model import BodyModel

#: the spine's joints from the root up, per body model (the chain a bend is spread along)
SPINE = {
    "anny": ("spine05", "spine04", "spine03", "spine02", "spine01"),
    "smplx": ("spine1", "spine2", "spine3"),
}


def spine_chain(model: BodyModel) -> tuple[list[int], list[int]]:
    """(the spine's joint indices from the root up, the root's other children); empty for a model without
    a rule or whose spine is not attached to the root."""
    names = SPINE.get(model.name.split("_sub")[0], ())
    ids = [model.joint_names.index(n) for n in names if n in model.joint_names]
    parents = model.parents.tolist()
    if len(ids) != len(names) or not ids or parents[ids[0]] != 0:
        return [], []
    others = [j for j in range(1, model.num_joints) if parents[j] == 0 and j != ids[0]]
    return ids, others


def _rotvec(R: torch.Tensor) -> torch.Tensor:
    return rotation_matrix_to_axis_angle(R.contiguous())


def lean_into_spine(pose: torch.Tensor, vertical: torch.Tensor, keep: float, spine: list[int],
                    others: list[int]) -> torch.Tensor:  # fmt: skip
    """(F, J, 3) ``pose`` with the root keeping ``keep`` (0..1) of its tilt from ``vertical`` (3,) (the
    world's up); the tilt it gives up is spread evenly over the ``spine`` joints (premultiplied: exact where
    they are at rest) and taken back by the root's ``others`` children (exactly), so the spine's top and
    the limbs hanging from ``others`` keep their world orientation."""
    R = batch_rodrigues(pose[:, 0])  # (F, 3, 3) body -> world
    up = R[:, :, 1]  # the body's own up in the world
    v = (vertical / vertical.norm()).to(pose).expand_as(up)
    axis = torch.linalg.cross(v, up, dim=-1)
    sin, cos = axis.norm(dim=-1, keepdim=True), (v * up).sum(-1, keepdim=True)
    angle = torch.atan2(sin, cos)
    axis = axis / sin.clamp_min(1e-12)
    give = batch_rodrigues(axis * angle * (1.0 - keep))  # the part of the tilt the root gives up (world)
    root = give.transpose(1, 2) @ R  # the root turned back by it
    D = R.transpose(1, 2) @ give @ R  # what the children take over, in the root's frame
    out = pose.clone()
    out[:, 0] = _rotvec(root)
    for j in others:
        out[:, j] = _rotvec(D @ batch_rodrigues(pose[:, j]))
    if spine:
        share = batch_rodrigues(_rotvec(D) / len(spine))
        for j in spine:
            out[:, j] = _rotvec(share @ batch_rodrigues(pose[:, j]))
    return out
