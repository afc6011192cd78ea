"""Mesh-integrated volume rendering: the worked example, mesh stop, stability, gradients, sampling, slab test."""

from __future__ import annotations

import math
from unittest import mock

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from delta.render import volume
from delta.render.volume import composite, nerf_weights, ray_box, sample_deltas, stratified_samples

D = torch.float64


# ----------------------------------------------------------------- the worked example
def test_docstring_worked_example():
    t = torch.tensor([[0.0, 0.5, 1.0]], dtype=D)
    sigma = torch.tensor([[1.0, 2.0]], dtype=D)
    c0, c1, c_end = [0.2, 0.4, 0.6], [1.0, 0.5, 0.0], [0.0, 0.0, 1.0]
    nerf_rgb = torch.tensor([[c0, c1]], dtype=D)
    end_rgb = torch.tensor([c_end], dtype=D)
    out = composite(t, sigma, nerf_rgb, end_rgb)

    w = torch.tensor([0.393469, 0.383400, 0.223130], dtype=D)
    torch.testing.assert_close(out.weights[0], w, rtol=0, atol=5e-7)
    torch.testing.assert_close(out.nerf_mask, torch.tensor([0.776870], dtype=D), rtol=0, atol=5e-7)
    # exact closed forms
    e = math.exp
    exact = [1 - e(-0.5), e(-0.5) * (1 - e(-1.0)), e(-1.5)]
    torch.testing.assert_close(out.weights[0], torch.tensor(exact, dtype=D), rtol=0, atol=1e-14)
    # hand-composited colour: 0.393469 c0 + 0.383400 c1 + 0.223130 c_end
    rgb = [exact[0] * a + exact[1] * b + exact[2] * c for a, b, c in zip(c0, c1, c_end)]
    # = (0.078694 + 0.383400, 0.157388 + 0.191700, 0.236082 + 0.223130)
    torch.testing.assert_close(out.rgb[0], torch.tensor(rgb, dtype=D), rtol=0, atol=1e-14)
    torch.testing.assert_close(out.rgb[0], torch.tensor([0.462094, 0.349088, 0.459212], dtype=D), rtol=0, atol=2e-6)
    # depth: 0 w0 + 0.5 w1 + 1.0 w2
    torch.testing.assert_close(out.depth[0], torch.tensor(0.5 * exact[1] + exact[2], dtype=D), rtol=0, atol=1e-14)
    # optical depth: 1 * 0.5 + 2 * 0.5, and the NeRF mask is 1 - e^-τ
    torch.testing.assert_close(out.optical_depth, torch.tensor([1.5], dtype=D), rtol=0, atol=1e-15)
    torch.testing.assert_close(out.nerf_mask, 1 - torch.exp(-out.optical_depth), rtol=0, atol=1e-15)


def test_sample_deltas_and_clamp():
    t = torch.tensor([[0.0, 0.5, 0.25, 1.0]], dtype=D)
    torch.testing.assert_close(sample_deltas(t), torch.tensor([[0.5, 0.0, 0.75]], dtype=D), rtol=0, atol=0)


# ----------------------------------------------------------------- mesh stop, miss
def test_mesh_stop_samples_never_pass_the_hit():
    gen = torch.Generator().manual_seed(0)
    R, S = 64, 16
    t_near = torch.rand(R, dtype=D, generator=gen)
    d = t_near + 0.1 + 2 * torch.rand(R, dtype=D, generator=gen)  # mesh hit distance
    t = stratified_samples(t_near, d, S, generator=gen)
    assert torch.equal(t[:, -1], d)
    assert bool((t <= d[:, None]).all())

    mesh_rgb = torch.rand(R, 3, dtype=D, generator=gen)
    # a field that is empty up to the mesh and extremely dense (and bright) beyond it
    beyond_sigma = torch.tensor(1e6, dtype=D, requires_grad=True)
    beyond_rgb = torch.tensor([1.0, 1.0, 1.0], dtype=D, requires_grad=True)
    nerf_t = t[:, :-1]
    past = (nerf_t > d[:, None]).to(D)
    sigma = past * beyond_sigma
    nerf_rgb = past[..., None] * beyond_rgb
    out = composite(t, sigma, nerf_rgb, mesh_rgb)

    assert torch.equal(out.rgb, mesh_rgb)  # w_last = 1 exactly, every NeRF weight 0
    assert torch.equal(out.weights[:, -1], torch.ones(R, dtype=D))
    assert torch.equal(out.nerf_mask, torch.zeros(R, dtype=D))
    torch.testing.assert_close(out.depth, d, rtol=0, atol=0)
    out.rgb.sum().backward()
    assert beyond_sigma.grad == 0 and bool((beyond_rgb.grad == 0).all())


def test_mesh_stop_with_density_before_the_hit():
    """Density in front of the mesh only mixes colours of samples in front of it."""
    t_near, d = torch.tensor([1.0], dtype=D), torch.tensor([3.0], dtype=D)
    t = stratified_samples(t_near, d, 5, perturb=False)  # 1, 1.5, 2, 2.5, 3
    torch.testing.assert_close(t, torch.tensor([[1.0, 1.5, 2.0, 2.5, 3.0]], dtype=D), rtol=0, atol=0)
    sigma = torch.tensor([[0.0, 2.0, 0.0, 0.0]], dtype=D)  # a slab on [1.5, 2)
    red, mesh = torch.tensor([1.0, 0, 0], dtype=D), torch.tensor([[0.0, 0, 1]], dtype=D)
    out = composite(t, sigma, red.expand(1, 4, 3), mesh)
    a = 1 - math.exp(-1.0)
    torch.testing.assert_close(out.rgb, torch.tensor([[a, 0.0, 1 - a]], dtype=D), rtol=0, atol=1e-15)


def test_miss_ends_on_background():
    gen = torch.Generator().manual_seed(1)
    R, S = 8, 6
    t = stratified_samples(torch.zeros(R, dtype=D), torch.full((R,), 4.0, dtype=D), S, generator=gen)
    background = torch.tensor([0.3, 0.7, 0.9], dtype=D).expand(R, 3)
    out = composite(t, torch.zeros(R, S - 1, dtype=D), torch.rand(R, S - 1, 3, dtype=D, generator=gen), background)
    assert torch.equal(out.rgb, background)
    assert torch.equal(out.nerf_mask, torch.zeros(R, dtype=D))


# ----------------------------------------------------------------- weights: partition of unity
@settings(max_examples=150, deadline=None)
@given(
    rows=st.integers(1, 12).flatmap(
        lambda s: st.lists(
            st.lists(st.tuples(st.floats(0.0, 1e6), st.floats(0.0, 1.0)), min_size=s, max_size=s),
            min_size=1,
            max_size=4,
        )
    )
)
def test_weight_rows_sum_to_one(rows):
    sigma = torch.tensor([[s for s, _ in r] for r in rows], dtype=D)
    delta = torch.tensor([[d for _, d in r] for r in rows], dtype=D)
    w = nerf_weights(sigma, delta)
    assert w.shape == (len(rows), sigma.shape[1] + 1)
    assert bool(torch.isfinite(w).all()) and bool((w >= 0).all()) and bool((w <= 1).all())
    torch.testing.assert_close(w.sum(-1), torch.ones(len(rows), dtype=D), rtol=0, atol=1e-6)
    # the same through composite, with t built from the spacings
    t = torch.cat([torch.zeros(len(rows), 1, dtype=D), delta.cumsum(-1)], -1)
    out = composite(t, sigma, torch.zeros(*sigma.shape, 3, dtype=D), torch.ones(len(rows), 3, dtype=D))
    torch.testing.assert_close(out.weights.sum(-1), torch.ones(len(rows), dtype=D), rtol=0, atol=1e-6)
    torch.testing.assert_close(out.nerf_mask + out.weights[:, -1], torch.ones(len(rows), dtype=D), rtol=0, atol=1e-6)


# ----------------------------------------------------------------- stability
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_extreme_densities_and_spacings_are_finite(dtype):
    sig_vals, gaps = [0.0, 1e6, 1e30], [0.0, 1e-12, 0.5]
    rows_sigma, rows_t = [], []
    for s in sig_vals:
        for g in gaps:
            rows_sigma.append([s, s, s])
            rows_t.append([0.0, g, 2 * g, 3 * g])
    rows_sigma.append([1e4, 1e4, 1e4])  # σΔ sums of 1e4: transmittance underflows to 0
    rows_t.append([0.0, 1.0, 2.0, 3.0])
    rows_sigma.append([0.0, 1e4, 1e4])
    rows_t.append([0.0, 1.0, 2.0, 3.0])
    sigma = torch.tensor(rows_sigma, dtype=dtype, requires_grad=True)
    t = torch.tensor(rows_t, dtype=dtype, requires_grad=True)
    R = len(rows_sigma)
    gen = torch.Generator().manual_seed(2)
    nerf_rgb = torch.rand(R, 3, 3, generator=gen).to(dtype).requires_grad_()
    end_rgb = torch.rand(R, 3, generator=gen).to(dtype).requires_grad_()
    out = composite(t, sigma, nerf_rgb, end_rgb)
    for v in (out.rgb, out.weights, out.nerf_mask, out.depth):
        assert bool(torch.isfinite(v).all())
    torch.testing.assert_close(out.weights.sum(-1), torch.ones(R, dtype=dtype), rtol=0, atol=1e-6)
    out.rgb.sum().backward()
    for g in (sigma.grad, t.grad, nerf_rgb.grad, end_rgb.grad):
        assert g is not None and bool(torch.isfinite(g).all())

    w = out.weights.detach()
    # zero density or zero spacing: everything on the end sample
    for i, (s, g) in enumerate((s, g) for s in sig_vals for g in gaps):
        if s == 0.0 or g == 0.0:
            assert torch.equal(w[i], torch.tensor([0.0, 0, 0, 1], dtype=dtype))
    # σ = 1e30 over Δ = 0.5: the first sample is opaque
    assert torch.equal(w[8], torch.tensor([1.0, 0, 0, 0], dtype=dtype))
    # σ = 1e6, Δ = 1e-12: τ = 1e-6 per sample, w_k ≈ τ (expm1 keeps it accurate)
    torch.testing.assert_close(w[4, :3], torch.full((3,), 1e-6, dtype=dtype), rtol=1e-5, atol=0)
    # underflow rows: all weight on the first dense sample, the rest exactly 0
    assert torch.equal(w[-2], torch.tensor([1.0, 0, 0, 0], dtype=dtype))
    assert torch.equal(w[-1], torch.tensor([0.0, 1, 0, 0], dtype=dtype))
    torch.testing.assert_close(out.rgb[-1].detach(), nerf_rgb[-1, 1].detach(), rtol=0, atol=0)


def test_composite_gradcheck():
    gen = torch.Generator().manual_seed(3)
    t = torch.tensor([[0.0, 0.3, 0.7, 1.2], [0.5, 0.9, 1.0, 1.6]], dtype=D, requires_grad=True)
    sigma = (0.2 + 2 * torch.rand(2, 3, dtype=D, generator=gen)).requires_grad_()
    nerf_rgb = torch.rand(2, 3, 3, dtype=D, generator=gen).requires_grad_()
    end_rgb = torch.rand(2, 3, dtype=D, generator=gen).requires_grad_()

    def fn(t, sigma, nerf_rgb, end_rgb):
        out = composite(t, sigma, nerf_rgb, end_rgb)
        return out.rgb, out.nerf_mask, out.weights, out.depth

    assert torch.autograd.gradcheck(fn, (t, sigma, nerf_rgb, end_rgb))


def test_composite_gradient_matches_closed_form():
    """d rgb / d σ_0 for one NeRF sample: rgb = (1 - e^{-σΔ}) c + e^{-σΔ} c_end."""
    t = torch.tensor([[0.0, 0.4]], dtype=D)
    sigma = torch.tensor([[1.5]], dtype=D, requires_grad=True)
    c, c_end = torch.tensor([[[0.9, 0.1, 0.2]]], dtype=D), torch.tensor([[0.1, 0.3, 0.8]], dtype=D)
    out = composite(t, sigma, c, c_end)
    out.rgb[0, 0].backward()
    expected = 0.4 * math.exp(-0.6) * (0.9 - 0.1)
    assert sigma.grad.item() == pytest.approx(expected, rel=1e-12)


# ----------------------------------------------------------------- stratified samples
@pytest.mark.parametrize("num", [2, 3, 17])
def test_stratified_samples_properties(num):
    gen = torch.Generator().manual_seed(num)
    R = 500
    near = 3 * torch.rand(R, generator=gen)
    far = near + 5 * torch.rand(R, generator=gen)
    t = stratified_samples(near, far, num, generator=gen)
    assert t.shape == (R, num)
    assert torch.equal(t[:, -1], far)
    assert bool((t[:, 1:] >= t[:, :-1]).all())
    assert bool((t >= near[:, None]).all()) and bool((t <= far[:, None]).all())
    # one sample per bin of width (far - near) / (num - 1)
    width = (far - near) / (num - 1)
    k = torch.arange(num - 1)
    lo = near[:, None] + width[:, None] * k
    assert bool((t[:, :-1] >= lo - 1e-5).all()) and bool((t[:, :-1] <= lo + width[:, None] + 1e-5).all())
    # reproducible with a seeded generator
    again = stratified_samples(near, far, num, generator=torch.Generator().manual_seed(99))
    assert torch.equal(again, stratified_samples(near, far, num, generator=torch.Generator().manual_seed(99)))


def test_stratified_samples_unperturbed_bin_starts():
    near, far = torch.tensor([1.0, -2.0], dtype=D), torch.tensor([2.0, 6.0], dtype=D)
    t = stratified_samples(near, far, 5, perturb=False)
    expected = torch.tensor([[1.0, 1.25, 1.5, 1.75, 2.0], [-2.0, 0.0, 2.0, 4.0, 6.0]], dtype=D)
    torch.testing.assert_close(t, expected, rtol=0, atol=1e-15)


def test_stratified_samples_degenerate_and_invalid():
    near = torch.tensor([0.7, 2.0])
    t = stratified_samples(near, near.clone(), 6, generator=torch.Generator().manual_seed(0))
    assert torch.equal(t, near[:, None].expand(2, 6))
    # far < near: no sample lies beyond far (all collapse onto it, every spacing is 0)
    t = stratified_samples(torch.tensor([2.0]), torch.tensor([1.0]), 3, perturb=False)
    assert torch.equal(t, torch.tensor([[1.0, 1.0, 1.0]]))
    for num in (1, 0, -3):
        with pytest.raises(ValueError):
            stratified_samples(near, near + 1, num)


def test_stratified_samples_worst_case_jitter_stays_below_far():
    def top_of_bin(shape, dtype=None, device=None, generator=None):
        return torch.full(shape, 1.0 - 2.0**-24, dtype=dtype)  # the largest value float32 torch.rand returns

    near, far = torch.tensor([0.1]), torch.tensor([2.4])
    with mock.patch.object(volume.torch, "rand", top_of_bin):
        t = stratified_samples(near, far, 8)
    assert bool((t <= far[:, None]).all()) and bool((t[:, 1:] >= t[:, :-1]).all())


# ----------------------------------------------------------------- ray / box
LO = torch.tensor([-1.0, -1.0, -1.0], dtype=D)
HI = torch.tensor([1.0, 1.0, 1.0], dtype=D)


def _box(origins, dirs, lo=LO, hi=HI):
    return ray_box(torch.tensor(origins, dtype=D), torch.tensor(dirs, dtype=D), lo, hi)


def test_ray_box_axis_aligned():
    t_in, t_out, hit = _box([[-3.0, 0.2, -0.5], [0.3, 5.0, 0.0], [0.0, 0.0, -4.0]],
                            [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 2.0]])  # fmt: skip
    torch.testing.assert_close(t_in, torch.tensor([2.0, 4.0, 1.5], dtype=D), rtol=0, atol=1e-12)
    torch.testing.assert_close(t_out, torch.tensor([4.0, 6.0, 2.5], dtype=D), rtol=0, atol=1e-12)
    assert hit.tolist() == [True, True, True]


def test_ray_box_diagonal():
    s3, s2 = math.sqrt(3.0), math.sqrt(2.0)
    t_in, t_out, hit = _box([[-3.0, -3.0, -3.0], [-2.0, -3.0, 0.0], [2.0, 2.0, 2.0]],
                            [[1 / s3, 1 / s3, 1 / s3], [1 / s2, 1 / s2, 0.0], [-1.0, -1.0, -1.0]])  # fmt: skip
    # corner (-1,-1,-1) to corner (1,1,1); second ray: x-slab [√2, 3√2], y-slab [2√2, 4√2], z parallel inside
    torch.testing.assert_close(t_in, torch.tensor([2 * s3, 2 * s2, 1.0], dtype=D), rtol=0, atol=1e-12)
    torch.testing.assert_close(t_out, torch.tensor([4 * s3, 3 * s2, 3.0], dtype=D), rtol=0, atol=1e-12)
    assert hit.tolist() == [True, True, True]


def test_ray_box_offset_box():
    lo, hi = torch.tensor([0.0, 1.0, 2.0], dtype=D), torch.tensor([1.0, 3.0, 5.0], dtype=D)
    t_in, t_out, hit = _box([[0.5, 2.0, 10.0]], [[0.0, 0.0, -1.0]], lo, hi)
    assert (t_in.item(), t_out.item(), hit.item()) == (pytest.approx(5.0), pytest.approx(8.0), True)


def test_ray_box_parallel_to_slabs():
    t_in, t_out, hit = _box([[-3.0, 0.5, 0.0], [-3.0, 2.0, 0.0], [-3.0, 0.0, -1.5], [-3.0, -0.0, 0.0]],
                            [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, -0.0], [1.0, -0.0, -0.0]])  # fmt: skip
    assert bool(torch.isfinite(t_in).all()) and bool(torch.isfinite(t_out).all())
    assert hit.tolist() == [True, False, False, True]
    torch.testing.assert_close(t_in[[0, 3]], torch.tensor([2.0, 2.0], dtype=D), rtol=0, atol=1e-12)
    torch.testing.assert_close(t_out[[0, 3]], torch.tensor([4.0, 4.0], dtype=D), rtol=0, atol=1e-12)


def test_ray_box_origin_inside_and_misses():
    t_in, t_out, hit = _box(
        [[0.0, 0.0, 0.0], [0.5, -0.5, 0.25], [-3.0, 3.0, 0.0], [3.0, 0.0, 0.0], [-3.0, 1.5, 0.0]],
        [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.1, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]],
    )
    torch.testing.assert_close(t_in[:2], torch.zeros(2, dtype=D), rtol=0, atol=0)  # clamped at 0
    torch.testing.assert_close(t_out[:2], torch.tensor([1.0, 1.25], dtype=D), rtol=0, atol=1e-12)
    # going away in y, box behind the origin, passing the corner region above the box
    assert hit.tolist() == [True, True, False, False, False]


def test_optical_depth_keeps_its_gradient_where_the_opacity_saturates():
    """On an opaque ray (τ = 40) the opacity's gradient in a density is e^-τ Δ (~1e-18): nothing the
    optimiser can act on. The optical depth's is Δ, whatever τ is (finite differences agree)."""
    t = torch.linspace(0.0, 1.0, 17, dtype=D)[None]
    sigma = torch.full((1, 16), 40.0, dtype=D, requires_grad=True)
    out = composite(t, sigma, torch.zeros(1, 16, 3, dtype=D), torch.ones(1, 3, dtype=D))
    (g_mask,) = torch.autograd.grad(out.nerf_mask.sum(), sigma, retain_graph=True)
    (g_tau,) = torch.autograd.grad(out.optical_depth.sum(), sigma)
    assert float(g_mask.abs().max()) < 1e-16
    torch.testing.assert_close(g_tau, torch.full((1, 16), 1 / 16, dtype=D), rtol=0, atol=1e-15)
    h = 1e-6
    bumped = sigma.detach().clone()
    bumped[0, 5] += h
    fd = (volume.optical_depth(bumped, sample_deltas(t)) - volume.optical_depth(sigma.detach(), sample_deltas(t))) / h
    torch.testing.assert_close(fd, torch.tensor([1 / 16], dtype=D), rtol=0, atol=1e-8)


def test_the_shell_ramp_is_zero_inside_linear_across_the_room_and_one_beyond():
    from delta.render.volume import shell_ramp

    d = torch.tensor([0.0, 0.02, 0.03, 0.065, 0.1, 0.5])
    torch.testing.assert_close(shell_ramp(d, 0.03, 0.1), torch.tensor([0.0, 0.0, 0.0, 0.5, 1.0, 1.0]))
    torch.testing.assert_close(shell_ramp(d, 0.05, 0.05), torch.tensor([0.0, 0.0, 0.0, 1.0, 1.0, 1.0]))  # a step


def _distortion_by_pairs(t: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Mip-NeRF 360's distortion written out over every pair of intervals (the O(S²) definition)."""
    mid = 0.5 * (t[..., 1:] + t[..., :-1])
    deltas = t[..., 1:] - t[..., :-1]
    wn = w[..., :-1]
    pairs = (wn[..., :, None] * wn[..., None, :] * (mid[..., :, None] - mid[..., None, :]).abs()).sum((-1, -2))
    return pairs + (wn * wn * deltas).sum(-1) / 3


def test_distortion_worked_example_and_its_limits():
    """The docstring's example; no weight costs nothing; one opaque interval costs Δ/3 wherever it lies; an
    opacity of one spread evenly over a depth D costs D/3 (the pairs' mean distance) as the intervals shrink;
    the mesh's share (the last column) is not the exterior's."""
    from delta.render.volume import distortion

    D = torch.float64
    t = torch.tensor([[0.0, 1.0, 3.0, 4.0]], dtype=D)
    torch.testing.assert_close(
        distortion(t, torch.tensor([[0.5, 0.25, 0.0, 0.25]], dtype=D)), torch.tensor([0.5], dtype=D)
    )
    torch.testing.assert_close(distortion(t, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=D)), torch.zeros(1, dtype=D))
    for k, length in ((0, 1.0), (1, 2.0)):
        w = torch.zeros(1, 4, dtype=D)
        w[0, k] = 1.0
        torch.testing.assert_close(distortion(t, w), torch.tensor([length / 3], dtype=D))
    n, depth = 400, 0.05
    t = torch.linspace(0.3, 0.3 + depth, n + 1, dtype=D)[None]
    w = torch.cat([torch.full((1, n), 1.0 / n, dtype=D), torch.zeros(1, 1, dtype=D)], -1)
    torch.testing.assert_close(distortion(t, w), torch.tensor([depth / 3], dtype=D), rtol=0, atol=1e-12)


def test_distortion_is_the_pairs_sum_and_its_gradient_agrees():
    """The prefix-sum form equals the pairs' sum on random sorted rays (jittered samples, zero-width
    intervals, weights from random densities), and its gradient in the densities passes gradcheck."""
    from delta.render.volume import distortion

    g = torch.Generator().manual_seed(3)
    D = torch.float64
    t = torch.sort(torch.rand(64, 17, generator=g, dtype=D) * 0.2, -1).values
    t[:5, 4] = t[:5, 3]  # zero-width intervals
    sigma = (
        torch.rand(64, 16, generator=g, dtype=D) * torch.tensor([0.0, 50.0, 500.0, 5e4], dtype=D).repeat(16)[:, None]
    )
    w = nerf_weights(sigma, sample_deltas(t))
    torch.testing.assert_close(distortion(t, w), _distortion_by_pairs(t, w), rtol=1e-12, atol=1e-15)
    s = (torch.rand(4, 8, generator=g, dtype=D) * 20).requires_grad_(True)
    ts = torch.sort(torch.rand(4, 9, generator=g, dtype=D), -1).values
    assert torch.autograd.gradcheck(lambda x: distortion(ts, nerf_weights(x, sample_deltas(ts))), (s,))


def test_distortion_prefers_one_sheet_to_a_slab_of_the_same_opacity():
    """Two rays of the same opacity (0.9): drawn within one 1-cm interval it costs 0.81 × 1 cm / 3, spread
    over the ray's ten intervals (its weight falling with the transmittance) over five times that."""
    from delta.render.volume import distortion

    D = torch.float64
    t = torch.linspace(0.0, 0.1, 11, dtype=D)[None].expand(2, 11)
    sheet = torch.zeros(10, dtype=D)
    sheet[5] = -math.log(0.1) / 0.01
    slab = torch.full((10,), -math.log(0.1) / 0.1, dtype=D)
    w = nerf_weights(torch.stack([sheet, slab]), sample_deltas(t))
    torch.testing.assert_close(w[:, :-1].sum(-1), torch.full((2,), 0.9, dtype=D))
    cost = distortion(t, w)
    torch.testing.assert_close(cost[0], torch.tensor(0.81 * 0.01 / 3, dtype=D))
    assert float(cost[1]) > 5 * float(cost[0])
