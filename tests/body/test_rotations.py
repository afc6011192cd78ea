"""Rotations against kornia (an independent implementation), analytic cases, the extremes (zero angle, π)
and finite differences."""

import math

import pytest
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_quaternion

from delta.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle, matrix_to_quaternion, mean_rotation


def random_axis_angles(n: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=dtype), dim=-1)
    angle = torch.rand(n, 1, generator=g, dtype=dtype) * math.pi
    return axis * angle


def extreme_axis_angles(dtype=torch.float64) -> torch.Tensor:
    """Zero, tiny, around the Taylor switch, just below and at π, about each axis and a diagonal one."""
    axes = torch.tensor([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=dtype)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    angles = torch.tensor([0, 1e-12, 1e-6, 9.99e-4, 1e-3, 1.01e-3, 0.5, math.pi - 1e-4, math.pi], dtype=dtype)
    return (axes[:, None] * angles[None, :, None]).reshape(-1, 3)


def test_matrices_match_kornia_and_are_rotations():
    aa = torch.cat([random_axis_angles(500, 0), extreme_axis_angles()])
    R = axis_angle_to_matrix(aa)
    assert torch.allclose(R, axis_angle_to_rotation_matrix(aa), atol=1e-12)
    eye = torch.eye(3, dtype=aa.dtype).expand_as(R)
    assert torch.allclose(R @ R.transpose(-1, -2), eye, atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(len(R), dtype=aa.dtype), atol=1e-12)


def test_a_quarter_turn_about_z_takes_x_to_y():
    R = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2]))
    assert torch.allclose(R @ torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]), atol=1e-6)
    assert axis_angle_to_matrix(torch.zeros(2, 5, 3)).shape == (2, 5, 3, 3)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_axis_angles_come_back_from_their_matrices_up_to_pi(dtype):
    aa = torch.cat([random_axis_angles(500, 1, dtype), extreme_axis_angles(dtype)])
    aa = aa[aa.norm(dim=-1) < math.pi - 1e-6]  # below π the axis-angle of a rotation is unique
    back = matrix_to_axis_angle(axis_angle_to_matrix(aa))
    tol = 1e-11 if dtype == torch.float64 else 2e-6
    assert torch.allclose(back, aa, atol=tol)


def test_at_pi_either_sign_of_the_axis_is_the_same_rotation():
    aa = extreme_axis_angles()
    aa = aa[aa.norm(dim=-1) > math.pi - 1e-9]  # angle π: v and -v are one rotation
    back = matrix_to_axis_angle(axis_angle_to_matrix(aa))
    assert len(aa) == 4 and torch.allclose(back.norm(dim=-1), torch.full((4,), math.pi, dtype=aa.dtype), atol=1e-7)
    assert torch.allclose(axis_angle_to_matrix(back), axis_angle_to_matrix(aa), atol=1e-12)


def test_quaternions_match_kornia_up_to_sign_and_have_w_nonnegative():
    aa = torch.cat([random_axis_angles(500, 2), extreme_axis_angles()])
    R = axis_angle_to_matrix(aa)
    q = matrix_to_quaternion(R)
    ref = rotation_matrix_to_quaternion(R)
    same = torch.minimum((q - ref).abs().amax(-1), (q + ref).abs().amax(-1))
    assert same.max() < 1e-9
    assert (q[:, 0] >= 0).all() and torch.allclose(q.norm(dim=-1), torch.ones(len(q), dtype=q.dtype))
    # analytic: a half turn about z is (0, 0, 0, 1)
    half = matrix_to_quaternion(axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi], dtype=torch.float64)))
    assert torch.allclose(half.abs(), torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64), atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-8, 5e-4, 2e-3, 1.0, 3.0])
def test_gradients_match_finite_differences_at_every_angle(angle):
    axis = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64), dim=0)
    aa = (axis * angle + torch.tensor([1e-9, 0.0, 0.0], dtype=torch.float64) * (angle == 0.0)).requires_grad_()
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (aa,), eps=1e-7, atol=1e-6)
    assert torch.autograd.gradcheck(lambda v: matrix_to_axis_angle(axis_angle_to_matrix(v)), (aa,), eps=1e-7,
                                    atol=1e-6)  # fmt: skip


def test_gradient_at_the_rest_pose_is_the_cross_product_matrix():
    """d R / d v at v = 0 is skew(e_i) for each component: finite, exact, no NaN from dividing by the angle."""
    aa = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    jac = torch.autograd.functional.jacobian(axis_angle_to_matrix, aa)  # (3, 3, 3)
    e = torch.eye(3, dtype=torch.float64)
    skew = torch.stack([torch.linalg.cross(e[i].expand(3, 3), e, dim=-1).T for i in range(3)])  # skew(e_i)
    assert torch.allclose(jac.permute(2, 0, 1), skew, atol=1e-15)
    back = torch.autograd.functional.jacobian(matrix_to_axis_angle, torch.eye(3, dtype=torch.float64))
    assert torch.isfinite(back).all()


def test_the_mean_rotation_is_scipys_chordal_mean():
    """SciPy's ``Rotation.mean`` (the quaternion eigenvector mean, which minimises the same chordal distance)
    as the oracle, on rotations spread up to 90° about a common one; a rotation alone is its own mean, and
    two turns by ±a about one axis average to no turn."""
    from scipy.spatial.transform import Rotation

    gen = torch.Generator().manual_seed(3)
    base = axis_angle_to_matrix(torch.tensor([0.3, -1.1, 0.4], dtype=torch.float64))
    spread = axis_angle_to_matrix(0.8 * torch.randn(40, 3, generator=gen, dtype=torch.float64))
    R = base @ spread
    expected = Rotation.from_matrix(R.numpy()).mean().as_matrix()
    torch.testing.assert_close(mean_rotation(R), torch.from_numpy(expected), atol=1e-10, rtol=0)
    torch.testing.assert_close(mean_rotation(R[:1]), R[0], atol=1e-12, rtol=0)
    pair = axis_angle_to_matrix(torch.tensor([[0.0, 0.7, 0.0], [0.0, -0.7, 0.0]], dtype=torch.float64))
    torch.testing.assert_close(mean_rotation(pair), torch.eye(3, dtype=torch.float64), atol=1e-12, rtol=0)
