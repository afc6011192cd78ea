"""The fit's exterior-aware silhouette: clothing and hair pixels the body need not fill, and its settings."""

import h5py
import numpy as np
import pytest
import torch

from delta import DeltaError
from delta.body.lbs import lbs
from delta.cameras.models import OrthographicCamera
from delta.fitting import silhouette as sil
from delta.fitting.fit import fit
from delta.fitting.settings import FitConfig, fit_config
from delta.fitting.run import exterior_masks
from delta.data.record import FrameRecord
from tests.fitting.test_robust import keypoints

D = torch.float64


def test_fill_weights_mix_by_exterior_coverage():
    ext = torch.tensor([[[0.0, 1.0], [0.5, 0.25]]], dtype=D)
    w = sil.fill_weights(ext, fill=1.0, exterior_fill=0.2)
    torch.testing.assert_close(w, torch.tensor([[[1.0, 0.2], [0.6, 0.8]]], dtype=D))
    assert sil.fill_weights(None, 0.7, 0.0) == 0.7


def test_uncovered_exterior_costs_exterior_fill():
    # the body covers the left half of a 2 x 4 mask that is all person; the right half is a dress
    rendered = torch.tensor([[[1.0, 1.0, 0.0, 0.0]] * 2], dtype=D)
    masks = torch.ones_like(rendered)
    dress = 1.0 - rendered
    for ext_fill, expect in ((1.0, 0.5), (0.25, 0.125), (0.0, 0.0)):
        term = sil.silhouette_term(rendered, masks, sil.fill_weights(dress, 1.0, ext_fill))
        torch.testing.assert_close(term, torch.tensor([expect], dtype=D))
    # the body outside the person mask costs 1 whatever the exterior says
    term = sil.silhouette_term(torch.ones_like(rendered), rendered, sil.fill_weights(dress, 1.0, 0.0))
    torch.testing.assert_close(term, torch.tensor([0.5], dtype=D))


def test_skin_edge_weight_lies_on_the_visible_skin_and_one_pixel_around_it():
    # a 1 x 6 strip of person: skin in columns 0-1, a dress in 2-3 (coverage 0.6 in column 2), background 4-5
    person = torch.tensor([[[1.0, 1.0, 1.0, 1.0, 0.0, 0.0]] * 3], dtype=D)
    dress = torch.tensor([[[0.0, 0.0, 0.6, 1.0, 0.0, 0.0]] * 3], dtype=D)
    w = sil.skin_edge_scale(person, dress, 8.0)
    # skin where person less dress is over a half (columns 0, 1), widened by one pixel (column 2)
    torch.testing.assert_close(w, torch.tensor([[[8.0, 8.0, 8.0, 1.0, 1.0, 1.0]] * 3], dtype=D))
    assert sil.skin_edge_scale(person, dress, 1.0) == 1.0
    assert sil.skin_edge_scale(person, None, 8.0) == 8.0  # no exterior mask: all of the person is body
    assert FitConfig().skin_edge_weight == 1.0  # off by default: docs/fitting.md


def test_silhouette_term_scales_both_errors_per_pixel():
    rendered = torch.tensor([[[1.0, 0.0, 0.5, 1.0]]], dtype=D)  # over, under, half under, right
    masks = torch.tensor([[[0.0, 1.0, 1.0, 1.0]]], dtype=D)
    fill = 0.5
    plain = sil.silhouette_term(rendered, masks, fill)
    torch.testing.assert_close(plain, torch.tensor([(1.0 + 0.5 + 0.5 * 0.25) / 4], dtype=D))
    scale = torch.tensor([[[3.0, 2.0, 1.0, 7.0]]], dtype=D)
    torch.testing.assert_close(sil.silhouette_term(rendered, masks, fill, scale),
                               torch.tensor([(3.0 + 2.0 * 0.5 + 0.5 * 0.25) / 4], dtype=D))  # fmt: skip
    torch.testing.assert_close(sil.silhouette_term(rendered, masks, fill, 4.0), 4.0 * plain)


def test_fit_config_merges_in_order_and_names_bad_keys():
    cfg = fit_config({"exterior_fill": 0.1, "sil_weight": 10}, {"sil_weight": 20.0, "iterations": [1, 2, 3]})
    assert (cfg.exterior_fill, cfg.sil_weight, cfg.iterations) == (0.1, 20.0, (1, 2, 3))
    assert fit_config() == FitConfig()
    for bad, word in (({"sil_wieght": 1}, "sil_wieght"), ({"iterations": [5, 5]}, "iterations"),
                      ({"sil_size": 6.5}, "sil_size"), ({"exterior_fill": -0.5}, "exterior_fill"),
                      ({"lr": float("nan")}, "lr"), ({"limit_weight": "high"}, "limit_weight")):  # fmt: skip
        with pytest.raises(DeltaError, match=f"fitting.subjects.loose.*{word}"):
            fit_config(bad, where="fitting.subjects.loose")


def test_exterior_masks_unite_clothing_and_hair(tmp_path):
    path = tmp_path / "r.h5"
    with h5py.File(path, "w") as h5:
        h5["images"] = np.zeros((1, 2, 2, 3), np.uint8)
        h5["person"] = np.full((1, 2, 2), 255, np.uint8)
        h5["keypoints"] = np.zeros((1, 18, 3), np.float32)
        h5["frame_ids"], h5["split"] = np.arange(1), np.zeros(1, np.uint8)
        h5.attrs["camera_model"] = "orthographic"
    with FrameRecord(path) as rec:
        assert exterior_masks(rec) is None
    with h5py.File(path, "a") as h5:
        h5["clothing"] = np.array([[[255, 0], [0, 0]]], np.uint8)
        h5["hair"] = np.array([[[0, 255], [0, 0]]], np.uint8)
    with FrameRecord(path) as rec:
        np.testing.assert_array_equal(exterior_masks(rec), [[[255, 255], [0, 0]]])


def test_a_wide_skirt_does_not_widen_the_body_when_it_is_exterior(body):
    """The person mask is the body plus a wide band over the hips and thighs (a skirt). Treating the
    band as body (exterior_fill 1) pulls the fitted body into it; as exterior (0), the body stays
    out of it (its share of the fitted silhouette that lies in the skirt is measured)."""
    model, kp_map = body
    size = 96
    truth = OrthographicCamera(torch.full((2,), 0.9, dtype=D), torch.tensor([[0.0, 0.05]] * 2, dtype=D), size, size)
    pose = torch.zeros(2, model.num_joints, 3, dtype=D)
    pose[1, 0, 1] = 0.3
    detected = keypoints(model, kp_map, truth, pose)
    coarse = sil.coarse_mesh(model, FitConfig.sil_cell)
    out = lbs(model, torch.zeros(2, model.num_shape, dtype=D), pose)
    uv = truth.project(out.vertices[:, coarse.vertex_ids])[0]
    body_px = (sil.frames_silhouette(uv, coarse.faces, size, (size, size), sigma=1e-3) > 0.5).numpy()
    hips = truth.project(out.joints[:, [model.joint_names.index(n) for n in ("upperleg01.L", "upperleg01.R")]])[0]
    skirt = np.zeros_like(body_px)
    for f in range(2):
        u0, u1 = sorted(hips[f, :, 0].tolist())
        v = int(hips[f, :, 1].mean())
        skirt[f, v - 4 : v + 22, max(int(u0) - 14, 0) : int(u1) + 15] = True
    person = (body_px | skirt).astype(np.uint8) * 255
    exterior = (skirt & ~body_px).astype(np.uint8) * 255
    template = OrthographicCamera(torch.tensor(1.0, dtype=D), torch.zeros(2, dtype=D), size, size)
    spill = {}
    for ext_fill in (1.0, 0.0):
        cfg = FitConfig(iterations=(30, 30, 50), sil_size=48, exterior_fill=ext_fill)
        res = fit(model, kp_map, detected, template, cfg, masks=person, exterior=exterior)
        fitted = lbs(model, res.betas[None].expand(2, -1), res.pose)
        uv = res.camera.project(fitted.vertices[:, coarse.vertex_ids])[0]
        mine = (sil.frames_silhouette(uv, coarse.faces, size, (size, size), sigma=1e-3) > 0.5).numpy()
        spill[ext_fill] = (mine & (exterior > 0)).sum() / mine.sum()
    assert spill[0.0] < 0.5 * spill[1.0], spill
