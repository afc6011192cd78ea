"""A limb swung toward the camera and the same limb swung away from it: the two poses one view confuses.

The child joint of a bone (the elbow of an upper arm, the knee of a thigh) lies on one camera ray, at
the bone's length from its joint. That ray meets the sphere of that radius twice: the bone as posed, and
the bone swung to the other side of the joint along the viewing axis, whose keypoint lands on the same
pixel. A limb of two bones (upper arm and forearm, thigh and shin) has four such poses.
:func:`other_sides` gives the three a pose does not take (the parts below the limb carried along
rigidly), so that a caller holding something that can tell them apart (a trained avatar's render against
the photograph) can choose.

Shapes: J joints; rotations (J, 3, 3) local, in world-aligned joint axes, as :func:`delta.body.lbs.lbs`
takes them.
"""

from __future__ import annotations

import itertools

import torch

from delta.body.lbs import rigid_transforms
from delta.body.model import BodyModel
from delta.body.upright import rotation_between

#: (upper bone's joint, middle joint, end joint) of the limbs whose bones a view leaves ambiguous: the arms
#: (shoulder, elbow, wrist) and the legs (hip, knee, ankle).
LIMBS = {
    "anny": (("upperarm01.L", "lowerarm01.L", "wrist.L"), ("upperarm01.R", "lowerarm01.R", "wrist.R"),
             ("upperleg01.L", "lowerleg01.L", "foot.L"), ("upperleg01.R", "lowerleg01.R", "foot.R")),
    "smplx": (("left_shoulder", "left_elbow", "left_wrist"), ("right_shoulder", "right_elbow", "right_wrist"),
              ("left_hip", "left_knee", "left_ankle"), ("right_hip", "right_knee", "right_ankle")),
}  # fmt: skip

MIN_SWING = 0.05
"""Radians: a bone this close to square to the viewing ray has no other side worth trying."""


def limbs(model: BodyModel) -> list[tuple[str, tuple[int, ...]]]:
    """(upper joint's name, chain of joint indices) of ``model``'s :data:`LIMBS` (none for another model)."""
    names = model.joint_names
    found = LIMBS.get(model.name.split("_sub")[0], ())
    return [(chain[0], tuple(names.index(n) for n in chain)) for chain in found if all(n in names for n in chain)]


def other_sides(rotmats: torch.Tensor, joints: torch.Tensor, parents: torch.Tensor, transl: torch.Tensor,
                camera, chain: tuple[int, ...]) -> list[tuple[tuple[int, ...], dict[int, torch.Tensor]]]:  # fmt: skip
    """Every other way a limb's ``chain`` (joint indices, each the parent of the next: shoulder, elbow, wrist)
    can reach the pixels its joints are posed on: each bone either keeps its side along the camera's ray
    through its end or swings to the other, the bone's length kept. Returns (pattern, {joint: (3, 3) local
    rotation}) for each pattern but the pose as given (pattern 1: that bone on its other side). A bone within
    :data:`MIN_SWING` of square to its ray has no other side. Where the bones above moved a bone's start
    beyond its reach of its ray (a pinhole's perspective), the bone points at the ray's nearest point, its
    end as near its pixel as the bone's length allows, and has no other side.

    ``rotmats`` (J, 3, 3) local rotations, ``joints`` (J, 3) rest joints of the shape, ``transl`` (3,),
    ``camera`` an :mod:`delta.cameras.models` camera of the frame.
    """
    posed, A = rigid_transforms(rotmats[None], joints[None], parents)
    posed, G = posed[0] + transl, A[0, :, :3, :3]
    rays = []
    for end in chain[1:]:
        origin, d = camera.rays(camera.project(posed[end][None])[0])
        rays.append((origin[0].to(posed.dtype), d[0].to(posed.dtype) / d[0].norm()))
    cos_min = torch.cos(torch.tensor(MIN_SWING, dtype=posed.dtype))
    out = []
    for pattern in itertools.product((0, 1), repeat=len(rays)):
        if not any(pattern):
            continue
        start, turn, local, ok = posed[chain[0]], torch.eye(3, dtype=posed.dtype), {}, True
        for k, (flip, (origin, d)) in enumerate(zip(pattern, rays)):
            joint, end = chain[k], chain[k + 1]
            bone = posed[end] - posed[joint]
            along = torch.dot(bone, d)
            if flip and along.abs() < bone.norm() * torch.sqrt(1 - cos_min**2):
                ok = False  # square to its ray: no other side
                break
            mid = torch.dot(start - origin, d)
            disc = mid**2 - (start - origin).square().sum() + bone.square().sum()
            if disc >= -1e-9 * bone.square().sum():
                sign = torch.sign(along) * (-1 if flip else 1)
                target = origin + (mid + sign * disc.clamp_min(0).sqrt()) * d
            elif flip:
                ok = False  # the ray passes beyond the bone's reach: it has one nearest way, not two sides
                break
            else:  # the bone toward the ray's nearest point, its end as near the pixel as its length allows
                nearest = origin + mid * d - start
                target = start + nearest / nearest.norm() * bone.norm()
            step = rotation_between(turn @ bone, target - start)
            new_turn = step @ turn  # the world rotation this joint's subtree takes
            local[joint] = G[int(parents[joint])].T @ turn.T @ new_turn @ G[joint]
            start, turn = target, new_turn
        if ok:
            out.append((pattern, local))
    return out
