"""Linear blend skinning as pure functions, one step each (SMPL-X conventions).

Every function is batched over frames (B), and device and dtype follow the
inputs. Shapes: V vertices, J joints, S shape, E expression coefficients.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Optional

import torch

from delta.body.model import BodyModel
from delta.body.rotations import axis_angle_to_matrix


@dataclasses.dataclass
class LBSOutput:
    """Everything a forward pass produces; backward skinning needs the transforms."""

    vertices: torch.Tensor
    """(B, V, 3) posed vertices (translation included)."""
    joints: torch.Tensor
    """(B, J, 3) posed joint positions."""
    rest_vertices: torch.Tensor
    """(B, V, 3) shaped, expression-, offset- and pose-corrected vertices before skinning."""
    rest_joints: torch.Tensor
    """(B, J, 3) shape-dependent rest joint positions J(β)."""
    joint_transforms: torch.Tensor
    """(B, J, 4, 4) rest -> posed transform of each joint (A_j = G_j [I | -J_j], translation included)."""
    vertex_transforms_3x4: torch.Tensor
    """(B, V, 3, 4) top rows of the per-vertex blended transforms: vertices = T_v · [rest_vertices; 1]."""

    @property
    def vertex_transforms(self) -> torch.Tensor:
        """(B, V, 4, 4) per-vertex blended transforms (built on access)."""
        T = self.vertex_transforms_3x4
        bottom = torch.zeros_like(T[..., :1, :])
        bottom[..., 0, 3] = 1.0
        return torch.cat([T, bottom], dim=-2)


def blend_shapes(coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Linear blend shapes: (B, S) coefficients, (N, 3, S) directions -> (B, N, 3)."""
    return torch.einsum("bs,nks->bnk", coeffs, dirs)


def batch_rodrigues(axis_angle: torch.Tensor) -> torch.Tensor:
    """Axis-angle (..., 3) -> rotation matrices (..., 3, 3); finite gradients at 0 and beyond π."""
    return axis_angle_to_matrix(axis_angle)


def pose_features(rotmats: torch.Tensor) -> torch.Tensor:
    """Pose-corrective features (R_j - I) for j >= 1: (B, J, 3, 3) -> (B, 9 (J - 1))."""
    eye = torch.eye(3, dtype=rotmats.dtype, device=rotmats.device)
    return (rotmats[:, 1:] - eye).flatten(1)


@functools.lru_cache(maxsize=32)
def kinematic_levels(parents: tuple[int, ...]) -> tuple[tuple[int, ...], ...]:
    """Joints grouped by depth in the tree: each level's parents lie in earlier levels."""
    depth = [0] * len(parents)
    for j, p in enumerate(parents):
        depth[j] = 0 if p < 0 else depth[p] + 1
    levels: list[list[int]] = [[] for _ in range(max(depth) + 1)]
    for j, d in enumerate(depth):
        levels[d].append(j)
    return tuple(tuple(level) for level in levels)


def _homogeneous(rot: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3), (..., 3) -> (..., 4, 4) rigid transforms."""
    top = torch.cat([rot, trans.unsqueeze(-1)], dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


@functools.lru_cache(maxsize=32)
def _chain_plan(parents: tuple[int, ...], device: str) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
    """Index tensors of forward kinematics by pointer jumping, made once per tree and device: each joint's
    parent (a root its own), which joints are roots (J, 1) (their offset is their position), and per round
    each joint's ancestor 2^r joints up (J, a stand-in identity, above a root), for the rounds that cover
    the tree's depth."""
    J = len(parents)
    up = [p if p >= 0 else J for p in parents] + [J]  # the stand-in's ancestor is itself
    rounds = []
    for _ in range(max(1, len(kinematic_levels(parents)) - 1).bit_length()):
        rounds.append(torch.tensor(up, dtype=torch.int64, device=device))
        up = [up[a] for a in up]
    parent = torch.tensor([p if p >= 0 else j for j, p in enumerate(parents)], dtype=torch.int64, device=device)
    root = torch.tensor([[p < 0] for p in parents], device=device)
    return parent, root, rounds


def rigid_transforms(
    rotmats: torch.Tensor, joints: torch.Tensor, parents: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward kinematics.

    Args:
        rotmats: (B, J, 3, 3) local rotations in world-aligned axes.
        joints: (B, J, 3) rest joint positions.
        parents: (J,) parent indices, -1 for the root.
    Returns:
        posed_joints (B, J, 3) and relative transforms A (B, J, 4, 4) with
        A_j = G_j · [I | -J_j], which carry rest points to posed points.

    The chain G_j = L_root ··· L_parent · L_j is composed by pointer jumping: after round r each joint
    holds the product of its 2^r nearest links, so ceil(log2 depth) rounds of one gather and one batched
    product reach every root (Anny's 17 levels: 5 rounds). On a GPU each operation is a launch, forward
    and backward, and their number does not grow with the joints'.
    """
    parent, root, rounds = _chain_plan(tuple(parents.tolist()), str(joints.device))
    rel = torch.where(root, joints, joints - joints[:, parent])
    local = _homogeneous(rotmats, rel)  # 1. each joint's transform relative to its parent
    eye = torch.eye(4, dtype=local.dtype, device=local.device).expand(local.shape[0], 1, 4, 4)
    G = torch.cat([local, eye], dim=1)  # (B, J + 1, 4, 4): the stand-in identity above the roots
    for up in rounds:  # 2. G_j <- G_up(j) · G_j: the product of twice as many links
        G = G[:, up] @ G
    G = G[:, :-1]
    posed_joints = G[..., :3, 3]
    # 3. remove the rest joint position: A_j = G_j - [0 | G_j[:3,:3] J_j]
    shift = torch.einsum("bjik,bjk->bji", G[..., :3, :3], joints)
    A = torch.cat([G[..., :3, :3], (G[..., :3, 3] - shift).unsqueeze(-1)], dim=-1)
    return posed_joints, torch.cat([A, G[..., 3:, :]], dim=-2)


def skin(
    rest_vertices: torch.Tensor, weights: torch.Tensor, joint_transforms: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Blend joint transforms per vertex and apply them.

    Args:
        rest_vertices: (B, V, 3).
        weights: (V, J) or (B, V, J) skinning weights.
        joint_transforms: (B, J, 4, 4).
    Returns:
        posed vertices (B, V, 3) and per-vertex transforms (B, V, 3, 4) (top rows).
    """
    B, J = joint_transforms.shape[:2]
    A = joint_transforms[..., :3, :].reshape(B, J, 12)
    homo = torch.cat([rest_vertices, torch.ones_like(rest_vertices[..., :1])], dim=-1)
    if weights.ndim == 2:
        # one GEMM over the batch, (V, J) @ (J, B * 12), then work in that contiguous (V, B)
        # layout: memory traffic, not arithmetic, bounds this on a CPU
        T = (weights @ A.permute(1, 0, 2).reshape(J, B * 12)).reshape(-1, B, 3, 4)
        posed = torch.einsum("vbij,vbj->vbi", T, homo.transpose(0, 1)).transpose(0, 1)
        return posed, T.transpose(0, 1)
    T = torch.bmm(weights, A).reshape(B, -1, 3, 4)
    return torch.einsum("bvij,bvj->bvi", T, homo), T


def shaped_joints(model: BodyModel, betas: torch.Tensor) -> torch.Tensor:
    """(B, J, 3) rest joints of (B, S') shape coefficients (S' <= S)."""
    return model.joints_template + blend_shapes(betas, model.joints_shapedirs[..., : betas.shape[1]])


def posed_joints(model: BodyModel, betas: torch.Tensor, rotmats: torch.Tensor,
                 transl: Optional[torch.Tensor] = None) -> torch.Tensor:  # fmt: skip
    """(B, J, 3) the joints of :func:`lbs` alone, without skinning a vertex: (B, S') ``betas`` (or (S',),
    shared), (B, J, 3, 3) rotations, optional (B, 3) translation."""
    betas = betas.expand(rotmats.shape[0], -1) if betas.ndim == 1 else betas
    joints = shaped_joints(model, betas)
    posed, _ = rigid_transforms(rotmats, joints.expand(rotmats.shape[0], -1, -1), model.parents)
    return posed if transl is None else posed + transl[:, None]


def lbs(
    model: BodyModel,
    betas: torch.Tensor,
    pose: torch.Tensor,
    expression: Optional[torch.Tensor] = None,
    offsets: Optional[torch.Tensor] = None,
    transl: Optional[torch.Tensor] = None,
    pose_is_rotmat: bool = False,
) -> LBSOutput:
    """Pose a body model.

    Args:
        model: the body model (its tensors on the inputs' device and dtype).
        betas: (B, S') shape coefficients, S' <= S (the rest are zero).
        pose: (B, J, 3) axis-angle, or (B, J, 3, 3) rotations with ``pose_is_rotmat``.
        expression: (B, E') expression coefficients, optional.
        offsets: (B, V, 3) or (V, 3) canonical per-vertex offsets (DELTA's F_d), optional.
        transl: (B, 3) global translation, optional.
    """
    B = betas.shape[0]
    S = betas.shape[1]
    # 1. identity (and expression) blend shapes, shape-dependent joints
    v_shaped = model.v_template + blend_shapes(betas, model.shapedirs[..., :S])
    joints = shaped_joints(model, betas)
    if expression is not None and model.exprdirs is not None:
        E = expression.shape[1]
        v_shaped = v_shaped + blend_shapes(expression, model.exprdirs[..., :E])
        if model.joints_exprdirs is not None:
            joints = joints + blend_shapes(expression, model.joints_exprdirs[..., :E])
    # 2. rotations and pose correctives
    rotmats = pose if pose_is_rotmat else batch_rodrigues(pose)
    rest = v_shaped
    if model.posedirs is not None:
        rest = rest + blend_shapes(pose_features(rotmats), model.posedirs)
    if offsets is not None:
        rest = rest + offsets
    rest = rest.expand(B, -1, -1)
    # 3. forward kinematics and skinning
    posed_joints, A = rigid_transforms(rotmats, joints.expand(B, -1, -1), model.parents)
    if transl is not None:
        A = A.clone()
        A[..., :3, 3] = A[..., :3, 3] + transl[:, None]
        posed_joints = posed_joints + transl[:, None]
    vertices, T = skin(rest, model.weights, A)
    return LBSOutput(
        vertices=vertices,
        joints=posed_joints,
        rest_vertices=rest,
        rest_joints=joints.expand(B, -1, -1),
        joint_transforms=A,
        vertex_transforms_3x4=T,
    )
