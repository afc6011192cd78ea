"""Training length from convergence: the plateau test and the learning-rate schedule around it."""

import math

import numpy as np
import pytest

from delta.training.presets import StageSettings, find_plateau


def stage(**kw) -> StageSettings:
    base = dict(iterations=1000, rays=1, patch=0, checkpoint_every=1, preview_every=0, log_every=1, lr={}, lr_final=0.1)
    return StageSettings(**{**base, **kw})


def test_the_plateau_is_the_first_window_that_gains_too_little():
    # rises 0.1 dB a step for 300 steps, then flat: windows of 50 gain 5 dB until the flat part
    psnr = np.minimum(np.arange(1, 601) * 0.1, 30.0)
    assert find_plateau(psnr, 50, gain=0.05) == 400  # [350, 400) against [300, 350): both flat
    assert find_plateau(psnr[:399], 50, gain=0.05) is None  # not yet: the window is not complete
    assert find_plateau(psnr, 50, gain=0.05, first=120) == 400  # counted from step 120: checks at 250, 300, ...
    assert find_plateau(psnr, 0, gain=0.05) is None  # off
    # noise of 0.3 dB a step on a slope of 0.01 dB a step: windows of 100 still see the slope (1 dB a window)
    rng = np.random.default_rng(0)
    noisy = 20 + 0.01 * np.arange(2000) + rng.normal(0, 0.3, 2000)
    assert find_plateau(noisy, 100, gain=0.5) is None


def test_the_schedule_anneals_from_where_it_stood_to_lr_final():
    cfg = stage(anneal=0.1)
    assert cfg.end() == 1000 and cfg.end(400) == 500 and cfg.end(950) == 1000  # never past iterations
    # no plateau: exponential decay to lr_final at the last step
    assert cfg.lr_factor(0) == 1.0 and cfg.lr_factor(999) == pytest.approx(0.1)
    # a plateau at 400: unchanged before it, continuous at it, lr_final at the new last step (499)
    assert cfg.lr_factor(399, 400) == cfg.lr_factor(399)
    assert cfg.lr_factor(400, 400) == pytest.approx(cfg.lr_factor(400))
    assert cfg.lr_factor(499, 400) == pytest.approx(0.1)
    steps = [cfg.lr_factor(s, 400) for s in range(400, 500)]
    assert all(a > b for a, b in zip(steps, steps[1:]))  # decays monotonically
    ratios = np.diff(np.log(steps))
    assert np.allclose(ratios, ratios[0])  # exponentially
    assert math.isclose(cfg.lr_factor(450, 400), math.sqrt(cfg.lr_factor(400) * cfg.lr_factor(499, 400)), rel_tol=0.02)
