"""Parts of the body by its skeleton: the lower body (the hips or thighs and every joint below them).

The avatar leaves it out of an ``upper`` capture; training's scope detects such a capture from it.
"""

from __future__ import annotations

import torch

from delta.body.model import BodyModel

#: The joints at the tops of the arms (the shoulders) in Anny and SMPL-X.
SHOULDER_JOINTS = ("upperarm01.L", "upperarm01.R", "left_shoulder", "right_shoulder")

#: Joints that start the lower body (with all their descendants): hips/thighs in Anny and SMPL-X.
LOWER_BODY_ROOTS = ("upperleg01", "left_hip", "right_hip")


def lower_body_joints(body: BodyModel) -> list[int]:
    """The hips/legs and every joint below them."""
    names = body.joint_names
    lower = set()
    for j in range(body.num_joints):
        p = int(body.parents[j])
        if any(names[j].startswith(r) for r in LOWER_BODY_ROOTS) or (p >= 0 and p in lower):
            lower.add(j)
    return sorted(lower)


def lower_body_vertices(body: BodyModel) -> torch.Tensor:
    """(V,) bool: vertices skinned mostly (> 1/2) to lower-body joints."""
    ids = lower_body_joints(body)
    if not ids:
        return torch.zeros(body.num_vertices, dtype=torch.bool, device=body.weights.device)
    return body.weights[:, ids].sum(1) > 0.5


def head_vertices(body: BodyModel) -> torch.Tensor:
    """(V,) bool: vertices skinned mostly (> 1/2) to the head and the joints it carries (jaw, eyes,
    tongue), not the neck; none for a body model without a ``head`` joint."""
    head = body.subtree("head").to(body.weights.device)
    return body.weights[:, head].sum(1) > 0.5


def hair_span(body: BodyModel, joints: torch.Tensor) -> tuple[float, float] | None:
    """(low, high): the heights (y) of the shoulders' joints (their mean) and of the head's joint among
    ``joints`` (J, 3), the body's canonical joints: long hair hangs from the head above ``high`` and comes
    to rest on the trunk at ``low``. None for a body model without a ``head`` joint or shoulders."""
    names = body.joint_names
    shoulders = [names.index(n) for n in SHOULDER_JOINTS if n in names]
    if "head" not in names or not shoulders:
        return None
    low, high = float(joints[shoulders, 1].mean()), float(joints[names.index("head"), 1])
    return (low, high) if high > low else None
