"""Soft silhouette: analytic values, finite differences, degenerate and stacked triangles."""

from __future__ import annotations

import torch

from delta.render.silhouette import nearest_faces, point_triangle_distance_2d, soft_silhouette

D = torch.float64
BIG = torch.tensor([[0.0, 0.0], [100.0, 0.0], [0.0, 100.0]], dtype=D)
ONE = torch.tensor([[0, 1, 2]])


def test_point_triangle_distance_2d():
    a, b, c = BIG
    p = torch.tensor([[20.0, 30.0], [-3.0, 50.0], [60.0, 60.0], [-3.0, -4.0], [50.0, 0.0]], dtype=D)
    dist_sq, inside = point_triangle_distance_2d(p, a, b, c)
    torch.testing.assert_close(dist_sq, torch.tensor([400.0, 9.0, 200.0, 25.0, 0.0], dtype=D))
    assert inside.tolist() == [True, False, False, False, True]
    # orientation does not matter
    _, inside_cw = point_triangle_distance_2d(p, a, c, b)
    assert inside_cw.tolist() == inside.tolist()


def test_inside_outside_and_edge_values():
    pixels = torch.tensor([[20.0, 20.0], [200.0, 200.0], [50.0, 0.0], [50.0, 50.0]], dtype=D)
    cover = soft_silhouette(BIG, ONE, pixels, sigma=1.0, k=4)
    torch.testing.assert_close(cover, torch.tensor([1.0, 0.0, 0.5, 0.5], dtype=D), rtol=0, atol=1e-12)
    # at distance d: sigmoid(+-d^2 / sigma)
    near = torch.tensor([[50.0, 1.0], [50.0, -1.0]], dtype=D)
    got = soft_silhouette(BIG, ONE, near, sigma=2.0)
    torch.testing.assert_close(got, torch.sigmoid(torch.tensor([0.5, -0.5], dtype=D)))


def test_face_mask_drops_faces():
    uv = torch.cat([BIG, BIG + 200])
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    pixels = torch.tensor([[20.0, 20.0], [220.0, 220.0]], dtype=D)
    torch.testing.assert_close(soft_silhouette(uv, faces, pixels), torch.ones(2, dtype=D))
    masked = soft_silhouette(uv, faces, pixels, face_mask=torch.tensor([False, True]))
    torch.testing.assert_close(masked, torch.tensor([0.0, 1.0], dtype=D))
    none = soft_silhouette(uv, faces, pixels, face_mask=torch.tensor([False, False]))
    assert none.shape == (2,) and (none == 0).all()


def test_moving_edge_matches_finite_difference():
    # pixels on y = 10 crossing the hypotenuse x + y = 100; all nearest to the hypotenuse
    pixels = torch.stack([torch.arange(30, dtype=D) + 78.5, torch.full((30,), 10.0, dtype=D)], 1)

    def total(dx):
        shift = torch.stack([dx, torch.zeros_like(dx)])
        return soft_silhouette(BIG + shift, ONE, pixels, sigma=4.0, k=1).sum()

    dx = torch.zeros((), dtype=D, requires_grad=True)
    (grad,) = torch.autograd.grad(total(dx), dx)
    h = torch.tensor(1e-5, dtype=D)
    fd = (total(h) - total(-h)) / (2 * h)
    assert grad.abs() > 0.5  # the edge sweeps pixels: a real signal
    torch.testing.assert_close(grad, fd, rtol=1e-4, atol=0)


def test_gradcheck_uv_tiny():
    uv = torch.tensor([[0.0, 0.0], [4.0, 0.3], [0.5, 3.5], [5.0, 4.0]], dtype=D, requires_grad=True)
    faces = torch.tensor([[0, 1, 2], [1, 3, 2]])
    pixels = torch.tensor([[1.0, 1.2], [3.1, 2.9], [-0.7, 2.0], [5.5, 1.0], [2.2, 4.4]], dtype=D)
    assert torch.autograd.gradcheck(lambda x: soft_silhouette(x, faces, pixels, sigma=2.0, k=2), (uv,))


def autograd_coverage(uv, faces, pixels, sigma, k):
    """The same coverage written with autograd through point_triangle_distance_2d (the distance to the
    nearest of the three segments), the independent oracle of the closed-form gradient."""
    idx = nearest_faces(uv, faces, pixels, k)
    corners = uv[faces[idx]]
    dist_sq, inside = point_triangle_distance_2d(
        pixels[:, None], corners[..., 0, :], corners[..., 1, :], corners[..., 2, :]
    )
    logit = (torch.where(inside, dist_sq, -dist_sq) / sigma).clamp(-1e4, 1e4)
    return -torch.expm1(-torch.nn.functional.softplus(logit).sum(-1))


def test_closed_form_gradient_is_autograds_on_a_crowded_mesh():
    """A jittered grid of 1-pixel triangles (the init fit's coarse mesh on its 64-pixel grid), pixels inside,
    on edges and vertices and outside, and a degenerate triangle: values and uv gradients agree."""
    gen = torch.Generator().manual_seed(3)
    n = 9
    ys, xs = torch.meshgrid(torch.arange(n, dtype=D), torch.arange(n, dtype=D), indexing="ij")
    uv = torch.stack([xs, ys], -1).reshape(-1, 2) + 0.3 * torch.rand(n * n, 2, generator=gen, dtype=D)
    q = (torch.arange(n - 1)[:, None] * n + torch.arange(n - 1)[None]).reshape(-1)
    faces = torch.cat([torch.stack([q, q + 1, q + n], 1), torch.stack([q + 1, q + n + 1, q + n], 1),
                       torch.tensor([[0, 1, 1]])])  # fmt: skip
    pixels = torch.cat([torch.rand(300, 2, generator=gen, dtype=D) * (n + 2) - 1, uv[:20].clone(),
                        (uv[:10] + uv[1:11]) / 2])  # fmt: skip
    weights = torch.rand(len(pixels), generator=gen, dtype=D)
    for sigma in (0.05, 0.3, 2.0):
        a = uv.clone().requires_grad_(True)
        b = uv.clone().requires_grad_(True)
        got, want = soft_silhouette(a, faces, pixels, sigma=sigma, k=8), autograd_coverage(b, faces, pixels, sigma, 8)
        torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
        (got * weights).sum().backward()
        (want * weights).sum().backward()
        assert b.grad.abs().max() > 0.1, "the gradient is a real signal"
        torch.testing.assert_close(a.grad, b.grad, rtol=1e-9, atol=1e-9)


def test_closed_form_gradient_in_float32_is_autograds_in_float64():
    gen = torch.Generator().manual_seed(5)
    uv = torch.rand(40, 2, generator=gen, dtype=D) * 20
    faces = torch.randint(0, 40, (60, 3), generator=gen)
    pixels = torch.rand(500, 2, generator=gen, dtype=D) * 20
    a = uv.float().requires_grad_(True)
    b = uv.clone().requires_grad_(True)
    soft_silhouette(a, faces, pixels.float(), sigma=1.0, k=6).sum().backward()
    autograd_coverage(b, faces, pixels, 1.0, 6).sum().backward()
    torch.testing.assert_close(a.grad.double(), b.grad, rtol=1e-3, atol=1e-3 * float(b.grad.abs().max()))


def test_degenerate_triangles_are_finite():
    uv = torch.tensor(
        [[0.0, 0], [4, 0], [4, 0], [2, 20], [2, 20], [2, 20], [0, 40], [1, 41], [2, 42]],
        dtype=D,
        requires_grad=True,
    )
    faces = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8]])  # a segment, a point, collinear
    pixels = torch.tensor([[2.0, 0], [2, 0.5], [2, 20], [1, 41], [0.5, 40.5], [9, 9], [2.5, 20]], dtype=D)
    cover = soft_silhouette(uv, faces, pixels, sigma=1.0, k=3)
    assert torch.isfinite(cover).all()
    torch.testing.assert_close(cover[[0, 2, 3, 4]], torch.full((4,), 0.5, dtype=D))  # on a segment / the point
    # next to them: sigmoid(-d^2 / sigma), no inside
    torch.testing.assert_close(cover[[1, 6]], torch.sigmoid(torch.tensor([-0.25, -0.25], dtype=D)))
    (grad,) = torch.autograd.grad(cover.sum(), uv)
    assert torch.isfinite(grad).all()


def test_stacked_triangles_and_tiny_sigma_are_finite():
    uv = BIG.repeat(1000, 1).requires_grad_(True)
    faces = torch.arange(3000).reshape(1000, 3)
    pixels = torch.tensor([[20.0, 20.0], [200.0, 200.0], [50.0, 0.0], [50.0, 0.5], [50.0, -0.5]], dtype=D)
    for sigma in (1.0, 1e-6):
        cover = soft_silhouette(uv, faces, pixels, sigma=sigma, k=1000)
        assert torch.isfinite(cover).all() and (cover >= 0).all() and (cover <= 1).all()
        assert cover[0] == 1 and cover[1] == 0 and cover[2] == 1  # 1 - 0.5^1000 on the edge
        (grad,) = torch.autograd.grad(cover.sum(), uv)
        assert torch.isfinite(grad).all()
    cover = soft_silhouette(uv, faces, pixels, sigma=1e-6, k=1000)
    torch.testing.assert_close(cover[3:], torch.tensor([1.0, 0.0], dtype=D))


def _grid_mesh(n=6, size=10.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    ii, jj = torch.meshgrid(torch.arange(n + 1), torch.arange(n + 1), indexing="ij")
    uv = torch.stack([jj, ii], -1).reshape(-1, 2).to(D) * size
    interior = ((ii > 0) & (ii < n) & (jj > 0) & (jj < n)).reshape(-1)
    uv[interior] += (torch.rand(int(interior.sum()), 2, generator=g, dtype=D) - 0.5) * 0.4 * size
    q = (ii[:-1, :-1] * (n + 1) + jj[:-1, :-1]).reshape(-1)
    faces = torch.cat([torch.stack([q, q + 1, q + n + 2], 1), torch.stack([q, q + n + 2, q + n + 1], 1)])
    return uv, faces


def test_converges_to_all_triangles_as_k_grows():
    uv, faces = _grid_mesh()
    g = torch.Generator().manual_seed(1)
    pixels = torch.rand(200, 2, generator=g, dtype=D) * 80 - 10
    sigma = 10.0  # blurry: ~6 triangles contribute to a pixel near a vertex
    # independent reference over every triangle: 1 - prod(1 - sigmoid)
    a, b, c = (uv[faces[:, i]][None] for i in range(3))
    dist_sq, inside = point_triangle_distance_2d(pixels[:, None], a, b, c)
    ref = 1 - torch.prod(1 - torch.sigmoid(torch.where(inside, dist_sq, -dist_sq) / sigma), dim=1)
    ks = (1, 4, 16, 32, 72)
    errors = [(soft_silhouette(uv, faces, pixels, sigma=sigma, k=k) - ref).abs().max().item() for k in ks]
    assert all(e1 >= e2 - 1e-15 for e1, e2 in zip(errors, errors[1:]))  # nested candidate sets
    assert errors[0] > 0.1 and errors[2] < 1e-3 and errors[3] < 1e-9 and errors[4] < 1e-12
    # sharp sigma: the exact (hard) coverage of the square [0, 60]^2 away from its border
    sharp = soft_silhouette(uv, faces, pixels, sigma=1e-3, k=16)
    inner = ((pixels > 1) & (pixels < 59)).all(1)
    outer = ((pixels < -1) | (pixels > 61)).any(1)
    dist_edges = dist_sq.min(1).values  # pixels within 1 px of an internal edge blend by design
    keep = dist_edges > 1
    assert (sharp[inner & keep] > 1 - 1e-9).all() and (sharp[outer] < 1e-9).all()


def test_nearest_faces_shape_and_dtype_follow_inputs():
    uv, faces = _grid_mesh(n=2)
    idx = nearest_faces(uv, faces, torch.zeros(3, 2, dtype=D), k=100)
    assert idx.shape == (3, len(faces)) and idx.dtype == torch.int64
    idx1 = nearest_faces(uv, faces, torch.zeros(3, 2, dtype=D), k=1)
    assert idx1.shape == (3, 1)
    out = soft_silhouette(uv.float(), faces, torch.tensor([[5.0, 5.0]]), k=2)
    assert out.dtype == torch.float32
