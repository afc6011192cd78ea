"""The silhouette's weight decided from the keypoints' scatter: the decision, and what it buys a fit whose
keypoints scatter (the body's vertices against the truth's)."""

import dataclasses

import numpy as np
import pytest
import torch

from delta.body.lbs import lbs
from delta.cameras.models import OrthographicCamera
from delta.fitting import silhouette as sil
from delta.body.keypoints import OPENPOSE18
from delta.fitting.balance import LEGS, MIN_LEGS_SEEN, fit_balanced, legs_seen, silhouette_balance
from delta.fitting.fit import fit
from delta.fitting.settings import FitConfig, fit_config
from tests.fitting.test_robust import keypoints

D = torch.float64
SIDE = 500  # the reference is 0.5 px at this side


def decide(residual, flagged=None, side=SIDE, cfg=FitConfig(), **kw):
    residual = torch.as_tensor(residual, dtype=D)
    flagged = (
        torch.zeros(len(residual), dtype=torch.bool) if flagged is None else torch.as_tensor(flagged, dtype=torch.bool)
    )
    return silhouette_balance(residual, flagged, side, cfg, **kw)


def test_the_weight_grows_with_the_squared_scatter_above_the_reference():
    cfg = FitConfig()
    assert cfg.sil_scatter * SIDE == pytest.approx(0.5)
    for scatter in (0.2, 0.5):
        out = decide([scatter] * 3)
        assert (out["factor"], out["sil_weight"]) == (1.0, cfg.sil_weight), out
    weights = []
    for scatter, factor in ((0.75, 2.25), (1.0, 4.0), (1.5, 9.0)):
        out = decide([scatter] * 5)
        assert out["factor"] == pytest.approx(factor) and out["sil_weight"] == pytest.approx(cfg.sil_weight * factor)
        weights.append(out["sil_weight"])
    assert weights == sorted(weights)  # more scatter, more weight
    # the reference is a fraction of the record's side: the same pixels on a record twice as large scatter half
    assert decide([1.0] * 5, side=2 * SIDE)["factor"] == 1.0
    capped = decide([100.0] * 5)
    assert capped["factor"] == cfg.sil_scatter_cap and "cap" in capped["why"]


def test_the_evidence_is_the_median_of_the_fitted_frames():
    # a flagged frame's residual and a NaN are not evidence; one frame far off does not move the median
    out = decide([1.0, 1.0, 1.0, 50.0, float("nan"), 30.0], flagged=[0, 0, 0, 0, 0, 1])
    assert out["scatter_px"] == 1.0 and out["factor"] == pytest.approx(4.0)
    none = decide([float("nan")] * 2, flagged=[1, 1])
    assert none["factor"] == 1.0 and none["scatter_px"] is None and "no fitted frame" in none["why"]


def test_where_the_weight_stands_as_set():
    wide = [2.0] * 4
    assert "off" in decide(wide, cfg=fit_config({"sil_scatter": 0.0}))["why"]
    assert "no silhouette" in decide(wide, masks=False)["why"]
    assert "no silhouette" in decide(wide, cfg=fit_config({"sil_weight": 0}))["why"]
    assert "close-up" in decide(wide, close_up=True)["why"]
    for kw in ({"cfg": fit_config({"sil_scatter": 0.0})}, {"masks": False}, {"close_up": True}):
        assert decide(wide, **kw)["factor"] == 1.0


def test_the_legs_seen_are_the_frames_with_a_hip_knee_or_ankle_detected():
    conf = FitConfig().conf_threshold
    assert sorted(OPENPOSE18[k] for k in LEGS) == sorted(
        f"{side}_{part}" for side in ("left", "right") for part in ("hip", "knee", "ankle")
    )
    F = 8
    detected = torch.zeros(F, len(OPENPOSE18), 3, dtype=D)
    detected[:, : LEGS[0], 2] = 1.0  # head, shoulders and arms in every frame: framed from the hips up
    assert legs_seen(detected, conf) == 0.0
    detected[:3, OPENPOSE18.index("left_ankle"), 2] = 1.0  # one ankle in three frames, a hip in one more
    detected[3, OPENPOSE18.index("right_hip"), 2] = conf
    detected[4, OPENPOSE18.index("right_knee"), 2] = conf - 1e-3  # under the threshold: not seen
    assert legs_seen(detected, conf) == pytest.approx(4 / F)
    assert legs_seen(detected[:0], conf) == 0.0


def test_a_capture_without_its_legs_in_view_is_left_as_fitted():
    """Keypoints that scatter (hands leaving the frame) over an outline the image's edge cuts: no refit, and
    the evidence says why; legs in view at the threshold weigh the silhouette as any capture's."""
    wide = [2.0] * 4
    out = decide(wide, legs=MIN_LEGS_SEEN - 0.01)
    assert out["factor"] == 1.0 and out["sil_weight"] == FitConfig().sil_weight and "legs seen" in out["why"]
    assert out["legs_seen"] == pytest.approx(MIN_LEGS_SEEN - 0.01)
    assert decide(wide, legs=MIN_LEGS_SEEN)["factor"] == pytest.approx(16.0)
    assert decide(wide)["factor"] == pytest.approx(16.0)  # legs given as seen unless said otherwise


def test_scattered_keypoints_refit_with_the_outline_weighed_more(body):
    """Two frames of a turned body, masks its exact outline, each keypoint misplaced by 3 px at 96² (the same
    way in both frames, as a detector errs): the fit is fitted again with the silhouette weighed by the cap,
    and its outline then lies nearer the mask than the fit's with the weight as set. Keypoints without scatter
    leave the weight as set and the fit as it was, and so do the scattered ones where the legs are not in view.
    The silhouette is drawn sharper than the fit's default: at 0.3 grid px² its outline stands half a grid pixel
    out, a limb's width at 96², which the heavier weight would turn into a thinner body (test_silhouette_limits)."""
    model, kp_map = body
    size, F = 96, 2
    truth = OrthographicCamera(torch.full((F,), 0.9, dtype=D), torch.tensor([[0.0, 0.05]] * F, dtype=D), size, size)
    pose = torch.zeros(F, model.num_joints, 3, dtype=D)
    pose[1, 0, 1] = 0.4
    exact = keypoints(model, kp_map, truth, pose)
    coarse = sil.coarse_mesh(model, FitConfig.sil_cell)
    out = lbs(model, torch.zeros(F, model.num_shape, dtype=D), pose)
    uv = truth.project(out.vertices[:, coarse.vertex_ids])[0]
    masks = (sil.frames_silhouette(uv, coarse.faces, size, (size, size), sigma=1e-3) > 0.5).numpy()
    masks = masks.astype(np.uint8) * 255
    noisy = exact.clone()
    noisy[..., :2] += 3.0 * torch.randn(exact.shape[1], 2, generator=torch.Generator().manual_seed(0), dtype=D)
    template = OrthographicCamera(torch.tensor(1.0, dtype=D), torch.zeros(2, dtype=D), size, size)
    cfg = FitConfig(iterations=(30, 40, 60), sil_size=48, neighbour_reach=0, sil_sigma=0.03)

    def iou(res):
        """The fitted coarse body's hard silhouette against the mask."""
        fitted = lbs(model, res.betas[None].expand(F, -1), res.pose)
        mine = res.camera.project(fitted.vertices[:, coarse.vertex_ids])[0]
        drawn = sil.frames_silhouette(mine, coarse.faces, size, (size, size), sigma=1e-3) > 0.5
        return float(sil.soft_iou(drawn.double(), torch.from_numpy(masks > 0).double()).mean())

    plain = fit(model, kp_map, noisy, template, cfg, masks=masks)
    balanced, why = fit_balanced(model, kp_map, noisy, template, cfg, side=size, masks=masks)
    assert why["factor"] == cfg.sil_scatter_cap and why["sil_weight"] == cfg.sil_weight * cfg.sil_scatter_cap, why
    assert why["scatter_px"] > 1.0 and why["scatter_px_after"] > why["scatter_px"], why  # the outline pulls
    assert iou(balanced) > iou(plain) + 0.01, (iou(balanced), iou(plain))
    # the same keypoints from a capture whose legs are out of view: the plain fit, not refitted
    framed, why = fit_balanced(model, kp_map, noisy, template, cfg, side=size, masks=masks, legs=0.0)
    assert why["factor"] == 1.0 and "legs seen" in why["why"] and "scatter_px_after" not in why, why
    torch.testing.assert_close(framed.pose, plain.pose)
    quiet_cfg = dataclasses.replace(cfg, iterations=(20, 20, 20), sil_scatter=0.05)  # 4.8 px
    quiet, why = fit_balanced(model, kp_map, exact, template, quiet_cfg, side=size, masks=masks)
    assert why["factor"] == 1.0 and "scatter_px_after" not in why, why
    torch.testing.assert_close(quiet.pose, fit(model, kp_map, exact, template, quiet_cfg, masks=masks).pose)
