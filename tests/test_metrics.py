"""Image metrics against hand-computed values and scikit-image's reference implementation."""

import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from delta import metrics as M


def const(value, h=16, w=16):
    return torch.full((h, w, 3), float(value), dtype=torch.float64)


def test_psnr_of_a_constant_offset_is_hand_computed():
    # MSE = 0.1² = 0.01 -> 10 log10(1 / 0.01) = 20 dB
    assert M.psnr(const(0.5), const(0.6)) == pytest.approx(20.0, abs=1e-9)
    # half the pixels off by 0.2: MSE = 0.02 -> 16.9897 dB
    b = const(0.5)
    b[:, :8] += 0.2
    assert M.psnr(const(0.5), b) == pytest.approx(-10 * math.log10(0.02), abs=1e-9)


def test_identical_images_give_the_ideal_values():
    a = torch.rand(20, 24, 3, generator=torch.Generator().manual_seed(0))
    assert M.psnr(a, a) == math.inf
    assert M.ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    assert M.l1(a, a) == 0.0


def test_masked_scores_see_only_the_mask():
    a, b = const(0.5), const(0.5)
    b[:, 8:] = 0.9  # differs only outside the mask
    mask = torch.zeros(16, 16, dtype=torch.bool)
    mask[:, :4] = True
    assert M.psnr(a, b, mask) == math.inf
    assert M.l1(a, b, mask) == 0.0
    assert M.l1(a, b) == pytest.approx(0.2, abs=1e-12)
    assert math.isnan(M.psnr(a, b, torch.zeros(16, 16, dtype=torch.bool)))


def test_ssim_of_constant_images_is_the_luminance_term():
    # σ = 0 everywhere: SSIM = (2 μa μb + C1) / (μa² + μb² + C1) with C1 = 0.01²
    c1 = 0.01**2
    expected = (2 * 0.2 * 0.4 + c1) / (0.2**2 + 0.4**2 + c1)
    assert M.ssim(const(0.2), const(0.4)) == pytest.approx(expected, abs=1e-12)
    assert M.ssim(const(0.2), const(0.4), torch.ones(16, 16, dtype=torch.bool)) == pytest.approx(expected, abs=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ssim_equals_scikit_image(seed):
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(33, 47, 3, generator=g, dtype=torch.float64)
    b = (a + 0.2 * torch.randn(33, 47, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    kw = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1)
    ref, full = structural_similarity(a.numpy(), b.numpy(), full=True, **kw)
    assert M.ssim(a, b) == pytest.approx(ref, abs=1e-12)
    np.testing.assert_allclose(M.ssim_map(a, b).numpy(), full.mean(-1), atol=1e-12)


def test_ssim_drops_with_noise_and_blur():
    g = torch.Generator().manual_seed(3)
    a = torch.rand(32, 32, 3, generator=g, dtype=torch.float64)
    s = [
        M.ssim(a, (a + k * torch.randn(a.shape, generator=g, dtype=torch.float64)).clamp(0, 1))
        for k in (0.02, 0.1, 0.3)
    ]
    assert 1 > s[0] > s[1] > s[2] > 0


def test_bad_shapes_are_named():
    with pytest.raises(ValueError, match="same shape"):
        M.psnr(const(0.1, 8, 8), const(0.1, 8, 9))
    with pytest.raises(ValueError, match="at least 11"):
        M.ssim(const(0.1, 8, 8), const(0.1, 8, 8))
    with pytest.raises(ValueError, match="mask"):
        M.l1(const(0.1), const(0.1), torch.ones(3, 3, dtype=torch.bool))


def test_iou():
    a = torch.zeros(4, 4, dtype=torch.bool)
    b = torch.zeros(4, 4, dtype=torch.bool)
    a[:2] = True  # 8 pixels
    b[1:3] = True  # 8 pixels, 4 shared
    assert M.iou(a, b) == pytest.approx(4 / 12)
    assert math.isnan(M.iou(a & False, b & False))


def test_outline_band_is_the_pixels_near_the_outline_by_distance():
    """The band against a distance computed pixel by pixel: a pixel is in it when a pixel of the other
    side lies within ``width`` (Chebyshev) of it."""
    rng = np.random.default_rng(3)
    mask = np.zeros((40, 50), bool)
    mask[8:30, 10:38] = True
    mask[15:20, 20:26] = False  # a hole has an outline too
    mask |= rng.random(mask.shape) < 0.01  # and stray pixels
    for width in (1, 2, 4):
        band = M.outline_band(torch.from_numpy(mask), width).numpy()
        expect = np.zeros_like(mask)
        for y, x in np.ndindex(mask.shape):
            ys, xs = slice(max(0, y - width), y + width + 1), slice(max(0, x - width), x + width + 1)
            expect[y, x] = (mask[ys, xs] != mask[y, x]).any()
        np.testing.assert_array_equal(band, expect)
    assert not M.outline_band(torch.ones(6, 6, dtype=torch.bool), 2).any()  # the image border is no outline
    with pytest.raises(ValueError, match="width 0"):
        M.outline_band(torch.from_numpy(mask), 0)


def test_error_share_splits_the_squared_error():
    a = torch.zeros(4, 5, 3)
    b = torch.zeros(4, 5, 3)
    b[0, 0] = 0.5  # squared error 0.75
    b[3, 4, 1] = 0.5  # squared error 0.25
    inside = torch.zeros(4, 5, dtype=torch.bool)
    inside[0, 0] = True
    assert M.error_share(a, b, inside) == pytest.approx(0.75)
    assert M.error_share(a, b, ~inside) == pytest.approx(0.25)
    assert np.isnan(M.error_share(a, a, inside))
