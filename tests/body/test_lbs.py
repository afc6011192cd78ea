"""Linear blend skinning against analytic oracles and finite differences."""

import math

import pytest
import torch

from delta.body.lbs import batch_rodrigues, blend_shapes, kinematic_levels, lbs, rigid_transforms
from tests.conftest import soft_tree_model, tree_model


def rot_z(angle: float, dtype=torch.float64) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=dtype)


def test_rest_pose_returns_template(tree):
    out = lbs(tree, torch.zeros(1, 2, dtype=torch.float64), torch.zeros(1, 4, 3, dtype=torch.float64))
    torch.testing.assert_close(out.vertices[0], tree.v_template, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.joints[0], tree.joints_template, rtol=0, atol=1e-12)
    eye = torch.eye(4, dtype=torch.float64).expand(4, 4, 4)
    torch.testing.assert_close(out.joint_transforms[0], eye, rtol=0, atol=1e-12)


def test_shape_blend_shapes_are_linear(tree):
    betas = torch.tensor([[0.7, -1.3]], dtype=torch.float64)
    out = lbs(tree, betas, torch.zeros(1, 4, 3, dtype=torch.float64))
    expected = tree.v_template + 0.7 * tree.shapedirs[..., 0] - 1.3 * tree.shapedirs[..., 1]
    torch.testing.assert_close(out.vertices[0], expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.rest_joints[0], tree.joints_template + blend_shapes(betas, tree.joints_shapedirs)[0])


@pytest.mark.parametrize("joint,subtree", [(1, [1, 2]), (3, [3]), (2, [2])])
def test_rotating_one_joint_moves_only_its_subtree(joint, subtree):
    model = tree_model()
    model.posedirs = None  # pure rigid skinning for the oracle
    angle = 0.9
    pose = torch.zeros(1, 4, 3, dtype=torch.float64)
    pose[0, joint, 2] = angle
    out = lbs(model, torch.zeros(1, 2, dtype=torch.float64), pose)
    owner = model.weights.argmax(1)
    centre = model.joints_template[joint]
    R = rot_z(angle)
    for v in range(model.num_vertices):
        rest = model.v_template[v]
        expected = R @ (rest - centre) + centre if int(owner[v]) in subtree else rest
        torch.testing.assert_close(out.vertices[0, v], expected, rtol=0, atol=1e-12)
    for j in range(4):
        rest = model.joints_template[j]
        expected = R @ (rest - centre) + centre if j in subtree else rest
        torch.testing.assert_close(out.joints[0, j], expected, rtol=0, atol=1e-12)


def test_chain_composes_rotations():
    """Rotating root and child: the grandchild joint goes where the composed rotations put it."""
    model = tree_model()
    pose = torch.zeros(1, 4, 3, dtype=torch.float64)
    pose[0, 0, 2], pose[0, 1, 2] = 0.3, 0.5
    out = lbs(model, torch.zeros(1, 2, dtype=torch.float64), pose)
    j1 = rot_z(0.3) @ torch.tensor([1.0, 0, 0], dtype=torch.float64)
    j2 = j1 + rot_z(0.8) @ torch.tensor([1.0, 0, 0], dtype=torch.float64)
    torch.testing.assert_close(out.joints[0, 2], j2, rtol=0, atol=1e-12)


def test_transforms_reproduce_vertices_and_invert():
    model = soft_tree_model()
    gen = torch.Generator().manual_seed(3)
    pose = torch.randn(3, 4, 3, generator=gen, dtype=torch.float64)
    transl = torch.randn(3, 3, generator=gen, dtype=torch.float64)
    out = lbs(model, torch.randn(3, 2, generator=gen, dtype=torch.float64), pose, transl=transl)
    T = out.vertex_transforms
    homo = torch.cat([out.rest_vertices, torch.ones_like(out.rest_vertices[..., :1])], -1)
    torch.testing.assert_close((T @ homo.unsqueeze(-1)).squeeze(-1)[..., :3], out.vertices)
    back = torch.linalg.inv(T) @ torch.cat([out.vertices, torch.ones_like(out.vertices[..., :1])], -1).unsqueeze(-1)
    torch.testing.assert_close(back.squeeze(-1)[..., :3], out.rest_vertices)


def test_translation_shifts_everything(tree):
    t = torch.tensor([[0.1, -2.0, 3.0]], dtype=torch.float64)
    pose = torch.full((1, 4, 3), 0.2, dtype=torch.float64)
    a = lbs(tree, torch.zeros(1, 2, dtype=torch.float64), pose)
    b = lbs(tree, torch.zeros(1, 2, dtype=torch.float64), pose, transl=t)
    torch.testing.assert_close(b.vertices, a.vertices + t[:, None])
    torch.testing.assert_close(b.joints, a.joints + t[:, None])


def test_rotmat_input_matches_axis_angle():
    model = soft_tree_model()
    pose = torch.randn(2, 4, 3, dtype=torch.float64)
    a = lbs(model, torch.zeros(2, 2, dtype=torch.float64), pose)
    b = lbs(model, torch.zeros(2, 2, dtype=torch.float64), batch_rodrigues(pose), pose_is_rotmat=True)
    torch.testing.assert_close(a.vertices, b.vertices)


def test_kinematic_levels_respect_parents():
    parents = (-1, 0, 1, 0, 3, 4, 1)
    levels = kinematic_levels(parents)
    depth = {j: d for d, level in enumerate(levels) for j in level}
    assert all(depth[j] == depth[p] + 1 for j, p in enumerate(parents) if p >= 0)


def test_rigid_transforms_match_sequential_reference():
    """Level-batched kinematics equals the textbook per-joint loop."""
    gen = torch.Generator().manual_seed(5)
    parents = torch.tensor([-1, 0, 1, 2, 0, 4, 1, 6])
    J = len(parents)
    rot = batch_rodrigues(torch.randn(2, J, 3, generator=gen, dtype=torch.float64))
    joints = torch.randn(2, J, 3, generator=gen, dtype=torch.float64)
    posed, A = rigid_transforms(rot, joints, parents)
    for b in range(2):
        G = []
        for j in range(J):
            local = torch.eye(4, dtype=torch.float64)
            local[:3, :3] = rot[b, j]
            local[:3, 3] = joints[b, j] - (joints[b, parents[j]] if j else 0)
            G.append(local if j == 0 else G[parents[j]] @ local)
        for j in range(J):
            torch.testing.assert_close(posed[b, j], G[j][:3, 3])
            torch.testing.assert_close(A[b, j, :3, :3], G[j][:3, :3])
            torch.testing.assert_close(A[b, j, :3, 3], G[j][:3, 3] - G[j][:3, :3] @ joints[b, j])


def _dispatched(fn) -> int:
    """Tensor operations (not views) that fn() dispatches, forward and backward."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Count(TorchDispatchMode):
        n = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            Count.n += func.overloadpacket.__name__ not in ("view", "select", "slice", "expand", "detach", "t")
            return func(*args, **(kwargs or {}))

    with Count():
        fn()
    return Count.n


def test_kinematics_cost_a_few_operations_a_round_not_a_joint():
    """On a GPU each operation is a launch: two trees of the same depth, one with four times the joints,
    dispatch the same operations forward and backward (pointer jumping: ceil(log2 depth) rounds), and the
    gradients check against finite differences."""
    narrow = [-1, *range(8)]  # a chain: 9 levels, one joint each
    wide = [-1] + [0 if d == 0 else 1 + 4 * (d - 1) for d in range(8) for _ in range(4)]  # 4 joints a level
    counts = []
    for parents in (narrow, wide):
        J = len(parents)
        rot = batch_rodrigues(torch.randn(1, J, 3, generator=torch.Generator().manual_seed(J), dtype=torch.float64))
        rot.requires_grad_()
        joints = torch.randn(1, J, 3, dtype=torch.float64, requires_grad=True)
        par = torch.tensor(parents)
        depth = len(kinematic_levels(tuple(parents)))
        counts.append((depth, _dispatched(lambda: sum(x.sum() for x in rigid_transforms(rot, joints, par)).backward())))
    assert counts[0][0] == counts[1][0] == 9 and counts[0][1] == counts[1][1]
    torch.autograd.gradcheck(lambda r, j: rigid_transforms(r, j, torch.tensor(narrow))[1],
                             (torch.randn(1, 9, 3, 3, dtype=torch.float64, requires_grad=True),
                              torch.randn(1, 9, 3, dtype=torch.float64, requires_grad=True)))  # fmt: skip


# ------------------------------------------------------------------ gradients
def _vertices(model, **kw):
    def f(betas, pose, offsets):
        return lbs(model, betas, pose, offsets=offsets, **kw).vertices

    return f


@pytest.mark.parametrize("pose_scale", [0.0, 0.7, 3.0])
def test_gradcheck_shape_pose_offsets(pose_scale):
    model = soft_tree_model()
    gen = torch.Generator().manual_seed(11)
    betas = torch.randn(2, 2, generator=gen, dtype=torch.float64, requires_grad=True)
    pose = (pose_scale * torch.randn(2, 4, 3, generator=gen, dtype=torch.float64)).requires_grad_()
    offsets = (0.01 * torch.randn(2, 20, 3, generator=gen, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(_vertices(model), (betas, pose, offsets))


def test_gradcheck_translation_and_joints():
    model = soft_tree_model()
    betas = torch.randn(1, 2, dtype=torch.float64, requires_grad=True)
    pose = torch.randn(1, 4, 3, dtype=torch.float64, requires_grad=True)
    transl = torch.randn(1, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda b, p, t: lbs(model, b, p, transl=t).joints, (betas, pose, transl))


# ------------------------------------------------------------------ extremes
@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-6, math.pi - 1e-6, math.pi, math.pi + 1e-6, 2 * math.pi, 7.5, -13.0])
def test_extreme_angles_finite_values_and_gradients(angle):
    model = soft_tree_model()
    for axis in ([1.0, 0, 0], [0.3, -0.5, 0.8]):
        direction = torch.tensor(axis, dtype=torch.float64)
        direction = direction / direction.norm()
        pose = (angle * direction).expand(1, 4, 3).clone().requires_grad_()
        betas = torch.zeros(1, 2, dtype=torch.float64, requires_grad=True)
        out = lbs(model, betas, pose)
        assert torch.isfinite(out.vertices).all()
        out.vertices.square().sum().backward()
        assert torch.isfinite(pose.grad).all() and torch.isfinite(betas.grad).all()
        # rotations stay orthonormal
        R = batch_rodrigues(pose.detach())
        torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand_as(R))


def test_rotation_by_2pi_is_identity(tree):
    pose = torch.zeros(1, 4, 3, dtype=torch.float64)
    pose[0, 1] = torch.tensor([0.0, 2 * math.pi, 0.0], dtype=torch.float64)
    out = lbs(tree, torch.zeros(1, 2, dtype=torch.float64), pose)
    tree.posedirs = None
    ref = lbs(tree, torch.zeros(1, 2, dtype=torch.float64), torch.zeros(1, 4, 3, dtype=torch.float64))
    assert torch.allclose(out.joints, ref.joints, atol=1e-12)


@pytest.mark.parametrize("batch", [1, 256])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_extreme_shapes_and_batches(batch, dtype):
    model = soft_tree_model().to(dtype=dtype)
    gen = torch.Generator().manual_seed(batch)
    betas = (5.0 * torch.sign(torch.randn(batch, 2, generator=gen))).to(dtype).requires_grad_()
    pose = (4.0 * torch.randn(batch, 4, 3, generator=gen)).to(dtype).requires_grad_()
    out = lbs(model, betas, pose)
    assert out.vertices.shape == (batch, 20, 3) and out.vertices.dtype == dtype
    assert torch.isfinite(out.vertices).all()
    out.vertices.sum().backward()
    assert torch.isfinite(betas.grad).all() and torch.isfinite(pose.grad).all()


def test_float32_agrees_with_float64():
    m64 = soft_tree_model()
    m32 = m64.to(dtype=torch.float32)
    pose = torch.randn(4, 4, 3, dtype=torch.float64)
    betas = torch.randn(4, 2, dtype=torch.float64)
    a = lbs(m64, betas, pose).vertices
    b = lbs(m32, betas.float(), pose.float()).vertices
    torch.testing.assert_close(b.double(), a, rtol=0, atol=1e-5)
