"""How much the fit's silhouette weighs against its keypoints, decided from the keypoints' own scatter.

The fit's objective adds a keypoint term (about a keypoint's squared pixel error, ``terms.keypoint_term``)
and the silhouette's (``sil_weight`` times the mean squared coverage error). Read as the negative
log-likelihood of two Gaussian measurements, each term's weight is the inverse of its measurement's
variance, so the silhouette's weight relative to the keypoints' grows with the keypoints' variance.
``FitConfig.sil_weight`` is set for a detector whose fitted keypoints scatter ``sil_scatter`` of the
record's side (0.51 px at 512²: the fit's median residual on clean renders of synthetic subjects, 0.45 px
on tight, 0.50 on loose). A capture whose fitted keypoints scatter more (the real dancer: 1.74 px) says
less with its keypoints than the weight assumes, and its outline relatively more: the last stage is
fitted again with the silhouette weighed by the squared ratio, at most ``sil_scatter_cap`` times. The
Gaussian reading is the rationale; the evidence is the dancer's held-out tail (+1.25 dB refined) with the
synthetic subjects left as they were (docs/fitting.md).

A close-up is left as fitted: its outline is hair and shirt more than body, and a tracked face's
points, not the body's keypoints, are what its residual measures. So is a capture that frames the body from
the hips up (no hip, knee or ankle keypoint in at least ``MIN_LEGS_SEEN`` of its frames): the image's edge
cuts its outline, what is left of it is hair and shirt more than body, and its keypoints scatter because the
hands leave the frame, not because the detector errs. The synthetic ``upper`` subject (keypoints at 2.97 px)
refitted at the cap had its arms folded before the torso: the body 129 mm from the truth on its training
frames against 32 mm as fitted (docs/fitting.md).

Shapes: F frames.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import torch

from delta.body.keypoints import OPENPOSE18
from delta.fitting.fit import FitResult, FitStart, fit
from delta.fitting.settings import FitConfig

log = logging.getLogger(__name__)

#: OpenPose-18's leg keypoints: where none is detected, the capture does not frame the legs.
LEGS = tuple(OPENPOSE18.index(f"{side}_{part}") for side in ("right", "left") for part in ("hip", "knee", "ankle"))
#: The capture frames the legs where at least this share of its frames has a leg keypoint detected (the
#: synthetic ``upper`` subject: none; loose, whose dress hides the knees: 0.94; tight 0.95).
MIN_LEGS_SEEN = 0.25


def legs_seen(detected: torch.Tensor, conf_threshold: float) -> float:
    """The share of frames of (F, K >= 14, 3) OpenPose-18 ``detected`` keypoints (x, y, confidence) with at
    least one hip, knee or ankle at ``conf_threshold`` or above (0 for no frame)."""
    if len(detected) == 0:
        return 0.0
    return float((detected[:, list(LEGS), 2] >= conf_threshold).any(1).double().mean())


def median_scatter(residual_px: torch.Tensor, flagged: torch.Tensor) -> float | None:
    """The median of the (F,) residuals over the frames not ``flagged`` (F,) with a finite one; None: no such frame."""
    used = residual_px[~flagged.to(torch.bool) & torch.isfinite(residual_px)]
    return float(used.median()) if len(used) else None


def silhouette_balance(residual_px: torch.Tensor, flagged: torch.Tensor, side: int, cfg: FitConfig,
                       masks: bool = True, close_up: bool = False, legs: float = 1.0) -> dict:  # fmt: skip
    """The silhouette's weight for the fit's last stage from the keypoints' scatter, with its evidence.

    Args:
        residual_px: (F,) each frame's mean keypoint residual after the fit (pixels of the record).
        flagged: (F,) bool: frames the fit interpolated (not evidence).
        side: the record's side in pixels (the reference scales with it).
        masks: the fit had person masks (no masks: no silhouette to weigh).
        close_up: a tracked face's close-up (left as fitted).
        legs: the share of frames whose legs are seen (:func:`legs_seen`; below ``MIN_LEGS_SEEN``: left as fitted).
    Returns:
        ``scatter_px`` (the median over the fitted frames; None without any), ``reference_px``, ``legs_seen``, ``factor``
        (>= 1; 1: the fit stands), ``sil_weight`` (the weight for a refit) and ``why``.
    """
    reference = cfg.sil_scatter * side
    scatter = median_scatter(residual_px, flagged)
    out = {"scatter_px": None if scatter is None else round(scatter, 3), "reference_px": round(reference, 3),
           "legs_seen": round(legs, 3), "factor": 1.0, "sil_weight": cfg.sil_weight}  # fmt: skip
    if not masks or cfg.sil_weight <= 0:
        return out | {"why": "no silhouette term: nothing to weigh"}
    if cfg.sil_scatter <= 0:
        return out | {"why": "off (sil_scatter 0)"}
    if close_up:
        return out | {"why": "a tracked face's close-up: its outline is hair and shirt more than body"}
    if legs < MIN_LEGS_SEEN:
        return out | {"why": f"the legs seen in {100 * legs:.0f} % of the frames (< {100 * MIN_LEGS_SEEN:.0f} %): "
                      "the image's edge cuts the outline, which is hair and shirt more than body"}  # fmt: skip
    if scatter is None:
        return out | {"why": "no fitted frame: no scatter measured"}
    if scatter <= reference:
        return out | {"why": f"keypoints scatter {scatter:.2f} px <= {reference:.2f} px: the weight as set"}
    factor = min((scatter / reference) ** 2, max(cfg.sil_scatter_cap, 1.0))
    factor = round(factor, 3) if math.isfinite(factor) else 1.0
    return out | {"factor": factor, "sil_weight": cfg.sil_weight * factor,
                  "why": f"keypoints scatter {scatter:.2f} px > {reference:.2f} px: silhouette x{factor:.2f}"
                  f"{' (the cap)' if factor >= cfg.sil_scatter_cap else ''}"}  # fmt: skip


def fit_balanced(model, kp_map, detected: torch.Tensor, camera, cfg: FitConfig, *, side: int,
                 close_up: bool = False, legs: float = 1.0, **kwargs) -> tuple[FitResult, dict]:  # fmt: skip
    """:func:`delta.fitting.fit.fit`, then, where :func:`silhouette_balance` weighs the silhouette more, its
    last stage again from that fit with the new weight. ``kwargs`` go to both fits (a ``start`` only to the
    first). Returns the result and the decision (with ``scatter_px_after``, the refit's median residual)."""
    res = fit(model, kp_map, detected, camera, cfg, **kwargs)
    balance = silhouette_balance(res.residual_px, res.flagged, side, cfg, masks=kwargs.get("masks") is not None,
                                 close_up=close_up, legs=legs)  # fmt: skip
    log.info("the silhouette's weight: %s", balance["why"])
    if balance["factor"] <= 1:
        return res, balance
    kwargs["start"] = FitStart(res.betas, res.pose, res.transl)
    again = fit(model, kp_map, detected, res.camera, dataclasses.replace(cfg, sil_weight=balance["sil_weight"]),
                **kwargs)  # fmt: skip
    again.neighbour_starts = res.neighbour_starts + again.neighbour_starts
    again.neighbour_refits = res.neighbour_refits + again.neighbour_refits
    after = median_scatter(again.residual_px, again.flagged)
    balance["scatter_px_after"] = None if after is None else round(after, 3)
    return again, balance
