"""The person's fringe claimed by its parts: a part label says what a pixel's centre sees, the person's
alpha also covers the outline pixels whose centre missed the person; those go to the nearest part, so
the exterior's and the body's targets together hold all of the person's alpha."""

import numpy as np
import pytest

from delta.data.frames import FRINGE_REACH, claim_fringe


def exact_distance(mask: np.ndarray) -> np.ndarray:
    """Euclidean distance of every pixel to the mask's nearest pixel, by brute force."""
    ys, xs = np.nonzero(mask)
    yy, xx = np.mgrid[: mask.shape[0], : mask.shape[1]]
    if len(ys) == 0:
        return np.full(mask.shape, np.inf)
    return np.sqrt((yy[..., None] - ys) ** 2 + (xx[..., None] - xs) ** 2).min(-1)


def test_unlabelled_pixels_go_to_the_nearest_part_within_reach():
    rng = np.random.default_rng(7)
    for trial in range(6):
        h, w = 24, 30
        labels = rng.integers(0, 3, (h, w)) * (rng.random((h, w)) < 0.08)  # sparse seeds of parts 1 and 2
        parts = {"clothing": labels == 1, "skin": labels == 2}
        alpha = (rng.random((h, w)) < 0.7).astype(np.uint8) * rng.integers(1, 256, (h, w)).astype(np.uint8)
        out = claim_fringe(alpha, parts)
        d = {k: exact_distance(m) for k, m in parts.items()}
        free = (alpha > 0) & ~parts["clothing"] & ~parts["skin"]
        for name, m in parts.items():
            assert (out[name] & m).sum() == m.sum()  # a part keeps its own pixels
            other = "skin" if name == "clothing" else "clothing"
            gained = out[name] & ~m
            assert not (gained & ~free).any()  # only the person's unlabelled pixels are claimed
            # the nearest part (cv2's 5x5 distance: within 2 % of the exact one), within reach
            assert (d[name][gained] <= d[other][gained] * 1.03 + 1e-9).all()
            assert (d[name][gained] <= FRINGE_REACH * 1.03).all()
        claimed = out["clothing"] | out["skin"]
        assert not (out["clothing"] & out["skin"]).any()
        nearest = np.minimum(d["clothing"], d["skin"])
        outside = exact_distance(alpha == 0)  # the fringe: near where the person is not
        fringe = free & (outside <= FRINGE_REACH * 0.97)
        # a fringe pixel clearly within reach of a part is claimed; one clearly beyond, or inside the person, is not
        assert claimed[fringe & (nearest <= FRINGE_REACH * 0.97)].all()
        assert not claimed[free & (nearest > FRINGE_REACH * 1.03)].any()
        assert not claimed[free & (outside > FRINGE_REACH * 1.03)].any()


def disc(n: int, radius: float, sub: int = 8):
    """A disc's alpha by 8x8 samples a pixel (0-255) and the part label of each pixel's centre."""
    c = n / 2
    off = (np.arange(sub) + 0.5) / sub
    yy, xx = np.mgrid[:n, :n]
    ys = yy[..., None, None] + off[:, None]
    xs = xx[..., None, None] + off[None, :]
    cover = (((ys - c) ** 2 + (xs - c) ** 2) <= radius**2).mean((-1, -2))
    centre = ((yy + 0.5 - c) ** 2 + (xx + 0.5 - c) ** 2) <= radius**2
    return np.rint(cover * 255).astype(np.uint8), centre


def test_a_disc_s_exterior_target_holds_all_of_its_alpha():
    alpha, centre = disc(64, 20.3)
    a = alpha.astype(np.float64) / 255
    before = np.minimum(centre, a).sum()
    after = np.minimum(claim_fringe(alpha, {"clothing": centre})["clothing"], a).sum()
    outline = 2 * np.pi * 20.3
    # the centre label leaves out the edge pixels less than half covered: where an edge crosses a pixel
    # at a uniform offset, E[a; a < 1/2] = 1/8 of a pixel all round
    assert (a.sum() - before) / outline == pytest.approx(0.125, abs=0.025)
    assert after == pytest.approx(a.sum(), abs=1e-9)


def test_nothing_to_claim_leaves_the_parts_as_they_are():
    alpha, centre = disc(32, 10.0)
    alpha[~centre] = 0
    parts = {"clothing": centre, "hair": np.zeros_like(centre)}
    out = claim_fringe(alpha, parts)
    assert all(np.array_equal(out[k], parts[k]) for k in parts)
    far = np.zeros((32, 32), np.uint8)
    far[0, 0] = 200  # unlabelled and far from every part: nobody's
    assert not claim_fringe(far, {"clothing": centre})["clothing"][0, 0]


def test_an_unlabelled_patch_inside_the_person_stays_unlabelled():
    """A parser that labels clothing and not skin leaves the arms unlabelled: only their fringe at the
    outline is claimed, not the skin beside a sleeve inside the person."""
    alpha = np.zeros((40, 40), np.uint8)
    alpha[5:35, 5:35] = 255  # the person, its outline 5 px in from the image's
    sleeve = np.zeros((40, 40), bool)
    sleeve[5:35, 5:20] = True  # clothing on the left half; the right half unlabelled skin
    alpha[4, 5:35] = alpha[35, 5:35] = 80  # a fringe row above and below
    out = claim_fringe(alpha, {"clothing": sleeve})["clothing"]
    assert out[4, 5:20].all() and out[35, 5:20].all()  # the fringe beside the sleeve: the sleeve's
    assert not out[4, 24:35].any()  # the fringe beyond reach of the sleeve: nobody's
    assert not out[15:25, 20:23].any()  # skin beside the sleeve deep inside the person: not claimed
