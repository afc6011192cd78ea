"""Whether a capture's subject keeps one pose: the evidence for holding the fitted pose near its mean.

``FitConfig.static_weight`` holds every joint but the root near the sequence's mean, which is right for
a subject who turns in place in one pose (People Snapshot, the synthetic turns: there the fitted limbs
wander with the heading and the hold removes it) and wrong for one who moves (a dancer's raised arms
pulled down to her mean pose). The keypoints tell the two apart without a fit: the extent of a limb
along the torso's axis (shoulder to wrist, shoulder to elbow, hip to ankle), in torso lengths, does
not change as a body turns about its vertical, and changes by a large part of a torso length when an
arm is raised or a leg lifted. Its spread over the frames (the standard deviation; the largest over
the limbs) is the evidence: 0.04 on the synthetic loose turn, 0.06 on tight, 0.48 on the real dancer
(`benchmarks/static_hold.csv`).

Shapes: F frames, 18 OpenPose keypoints (u, v, confidence).
"""

from __future__ import annotations

import numpy as np

#: (from, to) OpenPose-18 indices of the limbs measured
LIMBS = ((2, 4), (5, 7), (2, 3), (5, 6), (8, 10), (11, 13))
_NECK, _HIPS = 1, (8, 11)
MIN_FRAMES = 3


def limb_spreads(keypoints: np.ndarray, conf: float = 0.5) -> dict[tuple[int, int], float]:
    """Each limb's standard deviation across frames of its extent along the torso (neck to mid-hip), in
    torso lengths, for the limbs seen with the torso in at least ``MIN_FRAMES`` frames."""
    kp = np.asarray(keypoints, dtype=np.float64)
    xy, c = kp[..., :2], kp[..., 2]
    axis = (xy[:, _HIPS[0]] + xy[:, _HIPS[1]]) / 2 - xy[:, _NECK]
    length = np.linalg.norm(axis, axis=1)
    torso = (c[:, _NECK] >= conf) & (c[:, _HIPS[0]] >= conf) & (c[:, _HIPS[1]] >= conf) & (length > 1e-6)
    spreads = {}
    for a, b in LIMBS:
        seen = torso & (c[:, a] >= conf) & (c[:, b] >= conf)
        if seen.sum() >= MIN_FRAMES:
            along = ((xy[seen, b] - xy[seen, a]) * axis[seen]).sum(1) / length[seen] ** 2
            spreads[(a, b)] = float(along.std())
    return spreads


def limb_spread(keypoints: np.ndarray, conf: float = 0.5) -> float | None:
    """The largest of :func:`limb_spreads`; None where no limb is seen with the torso often enough (a
    head-and-shoulders capture)."""
    return max(limb_spreads(keypoints, conf).values(), default=None)


def hold_decision(keypoints: np.ndarray, held: np.ndarray, threshold: float, weight: float, conf: float = 0.5) -> dict:
    """Whether the fit holds the pose of the ``held`` (F,) frames (``weight`` > 0 and their limbs'
    spread at most ``threshold``; a capture whose limbs are not seen is held as configured), with the
    evidence: ``{"hold": bool, "limb_spread": float | None, "threshold": float, "why": str}``."""
    spread = limb_spread(np.asarray(keypoints)[np.asarray(held, bool)], conf)
    if weight <= 0:
        hold, why = False, "static_weight is 0"
    elif spread is None:
        hold, why = True, "no limb is seen with the torso in enough frames: held as configured"
    elif spread <= threshold:
        hold, why = True, f"the limbs keep one pose (spread {spread:.3f} <= {threshold:g} torso lengths)"
    else:
        hold, why = False, f"the limbs move (spread {spread:.3f} > {threshold:g} torso lengths): not held"
    return {"hold": hold, "limb_spread": None if spread is None else round(spread, 4), "threshold": threshold,
            "why": why}  # fmt: skip
