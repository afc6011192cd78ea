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

A close-up of a talking head is the other case: its head turns and nods on shoulders that keep still,
and the face points the fit follows say where the head points, not which joint turned it. Holding the
limbs' mean there holds the neck and head, so the fit turns the whole body with the head (the synthetic
short-haired talker: the root turned 12.4° about its mean on average, where the truth's torso never
moves; ``benchmarks/torso_hold.csv``) and a shirt drawn on that torso smears across frames. For a tracked
face whose neck and shoulder keypoints keep still (:func:`torso_spread`, in shoulder widths: 0.001 on the
synthetic talkers, 0.49 on the turning full bodies) the hold keeps the torso instead
(``FitConfig.still_torso`` > 0): one turn and place of the root and one pose of every joint below the
neck, shared by every frame (tied, not pulled toward a mean: hundreds of face points outweigh any pull
and lift a pulled torso off its shoulders' keypoints), with the neck and head free; the face tracking
then corrects the body's place once for every frame and turns the head on its neck (docs/fitting.md).

Shapes: F frames, 18 OpenPose keypoints (u, v, confidence).
"""

from __future__ import annotations

import numpy as np

#: (from, to) OpenPose-18 indices of the limbs measured
LIMBS = ((2, 4), (5, 7), (2, 3), (5, 6), (8, 10), (11, 13))
_NECK, _HIPS = 1, (8, 11)
_SHOULDERS = (2, 5)
#: the joints a held torso leaves free: the neck's chain and everything it carries (Anny's, SMPL-X's)
HEAD_CHAIN = ("neck01", "neck")
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


def torso_spread(keypoints: np.ndarray, conf: float = 0.5) -> float | None:
    """How far the neck and shoulder keypoints move over the frames: the largest standard deviation of
    their image coordinates, in shoulder widths (the median distance between the shoulders), over the
    frames that see all three; None for fewer than ``MIN_FRAMES`` such frames."""
    kp = np.asarray(keypoints, dtype=np.float64)
    ids = [_NECK, *_SHOULDERS]
    seen = (kp[:, ids, 2] >= conf).all(1)
    if seen.sum() < MIN_FRAMES:
        return None
    xy = kp[seen][:, ids, :2]
    width = float(np.median(np.linalg.norm(xy[:, 1] - xy[:, 2], axis=-1)))
    return float(xy.std(0).max() / width) if width > 1e-6 else None


def hold_decision(keypoints: np.ndarray, held: np.ndarray, threshold: float, weight: float, conf: float = 0.5,
                  face: bool = False, still: float = 0.0) -> dict:  # fmt: skip
    """Whether the fit holds the pose of the ``held`` (F,) frames (``weight`` > 0 and their limbs'
    spread at most ``threshold``; a capture whose limbs are not seen is held as configured), and what it
    holds, with the evidence: ``{"hold": bool, "holds": "limbs" | "torso", "limb_spread": float | None,
    "torso_spread": float | None, "threshold": float, "why": str}``. ``holds`` is ``"torso"`` for a tracked
    ``face`` whose neck and shoulders move by at most ``still`` shoulder widths over every frame
    (:func:`torso_spread`), or are not seen often enough to tell (a close-up: held as configured): the
    root's turn and place and the joints below the neck over every frame, the neck and head free; else
    ``"limbs"``: every joint but the root over the ``held`` frames. ``still`` 0: never the torso."""
    torso = torso_spread(keypoints, conf) if face else None
    evidence = {"torso_spread": None if torso is None else round(torso, 4)}
    if weight > 0 and face and still > 0 and (torso is None or torso <= still):
        why = ("the shoulders are not seen in enough frames: a tracked face's torso held as configured"
               if torso is None else f"a face on a still torso (neck and shoulders spread {torso:.3f} <= {still:g} "
               "shoulder widths)")  # fmt: skip
        return {"hold": True, "holds": "torso", "limb_spread": None, **evidence, "threshold": still,
                "why": f"{why}: the torso held, the neck and head free"}  # fmt: skip
    return _limbs_decision(keypoints, held, threshold, weight, conf) | evidence


def _limbs_decision(keypoints: np.ndarray, held: np.ndarray, threshold: float, weight: float, conf: float) -> dict:
    spread = limb_spread(np.asarray(keypoints)[np.asarray(held, bool)], conf)
    if weight <= 0:
        hold, why = False, "static_weight is 0"
    elif spread is None:
        hold, why = True, "no limb is seen with the torso in enough frames: held as configured"
    elif spread <= threshold:
        hold, why = True, f"the limbs keep one pose (spread {spread:.3f} <= {threshold:g} torso lengths)"
    else:
        hold, why = False, f"the limbs move (spread {spread:.3f} > {threshold:g} torso lengths): not held"
    return {"hold": hold, "holds": "limbs", "limb_spread": None if spread is None else round(spread, 4),
            "threshold": threshold, "why": why}  # fmt: skip
