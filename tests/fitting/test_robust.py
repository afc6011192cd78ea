"""Stress cases of the init fit (finite parameters, flags, never NaN), starting from dataset parameters,
and the SMPL-X path on a fake model with the official key names."""

import h5py
import numpy as np
import pytest
import torch

from delta.body.smplx_loader import load_smplx
from delta.cameras.models import OrthographicCamera, PinholeCamera, look_at
from delta.fitting.fit import FitStart, KeypointModel, fit
from delta.fitting.settings import FitConfig
from delta.fitting.run import run
from tests.conftest import make_smplx_arrays

D = torch.float64
QUICK = FitConfig(iterations=(20, 20, 10))


def pinhole(distance=3.0, size=256, focal=350.0):
    R, t = look_at(
        torch.tensor([0.0, 0.0, distance], dtype=D), torch.zeros(3, dtype=D), torch.tensor([0.0, 1.0, 0.0], dtype=D)
    )
    K = torch.tensor([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]], dtype=D)
    return PinholeCamera(K, R, t, torch.zeros(5, dtype=D), size, size)


def keypoints(model, kp_map, cam, pose, transl=None):
    transl = torch.zeros(pose.shape[0], 3, dtype=D) if transl is None else transl
    uv, _ = cam.project(KeypointModel(model, kp_map)(torch.zeros(model.num_shape, dtype=D), pose, transl))
    return torch.cat([uv, torch.ones_like(uv[..., :1])], -1)


def finite(res):
    return all(torch.isfinite(t).all() for t in (res.betas, res.pose, res.transl))


def test_extreme_starting_poses_stay_finite(body):
    model, kp_map = body
    cam = pinhole()
    pose = torch.zeros(2, model.num_joints, 3, dtype=D)
    detected = keypoints(model, kp_map, cam, pose)
    gen = torch.Generator().manual_seed(0)
    wild = torch.pi * (2 * torch.rand(2, model.num_joints, 3, generator=gen, dtype=D) - 1)
    wild[0, :, 0] = torch.pi  # exactly π about x everywhere in frame 0
    start = FitStart(torch.full((model.num_shape,), 3.0, dtype=D), wild, torch.zeros(2, 3, dtype=D))
    res = fit(model, kp_map, detected, cam, FitConfig(iterations=(0, 0, 60)), start=start)
    assert finite(res) and not res.flagged.any() and torch.isfinite(res.residual_px).all()


def test_single_frame_and_no_keypoints_anywhere(body):
    model, kp_map = body
    cam = pinhole()
    detected = keypoints(model, kp_map, cam, torch.zeros(1, model.num_joints, 3, dtype=D))
    one = fit(model, kp_map, detected, cam, QUICK)
    assert finite(one) and one.residual_px[0] < 20
    none = fit(model, kp_map, torch.zeros(3, 18, 3, dtype=D), cam, QUICK)
    assert finite(none) and none.flagged.all() and none.few_keypoints.all() and torch.isnan(none.residual_px).all()
    nans = fit(model, kp_map, torch.full((2, 18, 3), float("nan"), dtype=D), cam, QUICK)  # a detector's NaNs
    assert finite(nans) and nans.flagged.all()


@pytest.mark.parametrize("height_px", [20.0, 1500.0])
def test_tiny_and_huge_subjects(body, height_px):
    """A body ~20 px tall, and one much taller than the 256 px image (keypoints off the image)."""
    model, kp_map = body
    pose = torch.zeros(2, model.num_joints, 3, dtype=D)
    kp3d = KeypointModel(model, kp_map)(torch.zeros(model.num_shape, dtype=D), pose, torch.zeros(2, 3, dtype=D))
    distance = 350.0 * float(kp3d[0, :, 1].amax() - kp3d[0, :, 1].amin()) / height_px
    cam_s = pinhole(distance=distance)
    detected = keypoints(model, kp_map, cam_s, pose)
    masks = np.zeros((2, 256, 256), np.uint8)
    masks[0, 100:160, 110:150] = 255  # a rough blob; frame 1's mask is empty
    res = fit(model, kp_map, detected, cam_s, FitConfig(iterations=(30, 30, 15)), masks=masks)
    assert finite(res) and res.flagged.tolist() == [False, True] and res.empty_mask.tolist() == [False, True]
    if height_px < 100:  # the tiny one is still fitted (the huge one only has to stay finite and flagged)
        assert res.residual_px[0] < 3.0


def test_recovers_camera_scale_from_keypoints_and_silhouette(body):
    """Orthographic: noiseless keypoints and the true coarse-mesh silhouette give back the scale.

    The silhouette is rendered 4 x 4 points a pixel and area-averaged like the mask: at one point
    a pixel the 32 px silhouette's thin limbs biased the scale 5-6 % low (0.85 for 0.9), at 2 x 2
    3.5 % (measured)."""
    from delta.body.lbs import lbs
    from delta.fitting import silhouette as sil

    model, kp_map = body
    truth = OrthographicCamera(torch.full((2,), 0.9, dtype=D), torch.tensor([[0.05, 0.1]] * 2, dtype=D), 128, 128)
    pose = torch.zeros(2, model.num_joints, 3, dtype=D)
    pose[1, model.joint_names.index("lowerleg01.L"), 0] = 0.6
    detected = keypoints(model, kp_map, truth, pose)
    out = lbs(model, torch.zeros(2, model.num_shape, dtype=D), pose)
    coarse = sil.coarse_mesh(model, FitConfig.sil_cell)
    uv = truth.project(out.vertices[:, coarse.vertex_ids])[0]
    masks = sil.frames_silhouette(uv, coarse.faces, 128, (128, 128), sigma=1e-3) > 0.5
    template = OrthographicCamera(torch.tensor(1.0), torch.zeros(2), 128, 128)
    cfg = FitConfig(iterations=(60, 60, 30), shape_weight=10.0, sil_size=32, sil_supersample=4)
    res = fit(model, kp_map, detected, template, cfg, masks=masks.numpy().astype(np.uint8) * 255)
    assert not res.flagged.any() and res.residual_px.max() < 1.5  # px on a 128 px image
    assert (res.camera.scale / 0.9 - 1).abs().max() < 0.03


def _record(path, model, kp_map, cam, pose, transl, params_model):
    n = pose.shape[0]
    detected = keypoints(model, kp_map, cam, pose, transl)
    with h5py.File(path, "w") as h5:
        h5["images"] = np.zeros((n, cam.width, cam.width, 3), np.uint8)
        h5["person"] = np.full((n, cam.width, cam.width), 255, np.uint8)
        h5["keypoints"] = detected.numpy().astype(np.float32)
        h5["frame_ids"] = np.arange(n)
        h5["split"] = np.zeros(n, np.uint8)
        h5.attrs["camera_model"] = "pinhole"
        for k in ("K", "R", "t"):
            h5[k] = getattr(cam, k).numpy()
        g = h5.create_group("body_params")
        g.attrs["model"] = params_model
        g["betas"], g["poses"], g["transl"] = np.zeros(model.num_shape), pose.numpy(), transl.numpy()


def test_fit_starts_from_the_records_parameters_for_the_same_model(body, anny_files, tmp_path):
    model, kp_map = body
    cam = pinhole(size=64, focal=90.0)
    pose = torch.zeros(2, model.num_joints, 3, dtype=D)
    pose[:, model.joint_names.index("lowerleg01.R"), 0] = torch.tensor([0.4, 0.9])
    pose[:, 0, 1] = 0.3
    transl = torch.tensor([[0.1, 0.0, 0.2], [0.0, 0.1, 0.0]], dtype=D)
    nothing = FitConfig(iterations=(0, 0, 0), sil_weight=0.0)
    for owner, expect in (("anny", "dataset"), ("smpl", "mean_pose")):
        _record(tmp_path / f"{owner}.h5", model, kp_map, cam, pose, transl, owner)
        summary = run(tmp_path / f"{owner}.h5", anny_files["body"], tmp_path / owner, overlays=1, cfg=nothing)
        assert summary["started_from"] == expect
        with np.load(tmp_path / owner / "params.npz") as p:
            same = np.allclose(p["poses"], pose.numpy(), atol=1e-6) and np.allclose(p["transl"], transl.numpy())
            assert str(p["started_from"]) == expect and same == (owner == "anny")
            if owner == "anny":  # the capture's up: the camera looks along +z at a body standing on its y
                np.testing.assert_allclose(p["up"], [0.0, 1.0, 0.0], atol=0.02)
                assert float(p["floor"]) < float(transl[:, 1].min()) - 0.5  # the feet, ~0.75 m under the root
        assert summary["upright"]["frames"] == 2


def test_smplx_fit_recovers_keypoints(tmp_path):
    arrays = make_smplx_arrays()
    np.savez(tmp_path / "SMPLX_NEUTRAL.npz", **arrays)
    model = load_smplx(tmp_path / "SMPLX_NEUTRAL.npz", num_shape=10, num_expression=10).to(dtype=D)
    # the fake mesh is random (no face to put nose, eyes and ears on): the 13 keypoints on joints, from the table
    from delta.body.keypoints import _JOINTS, OPENPOSE18, KeypointMap

    jw = torch.zeros(18, model.num_joints, dtype=D)
    for k, name in enumerate(OPENPOSE18):
        if name in _JOINTS["smplx"]:
            jw[k, model.joint_names.index(_JOINTS["smplx"][name])] = 1.0
    kp_map = KeypointMap(OPENPOSE18, jw, torch.zeros(18, model.num_vertices, dtype=D))
    cam = pinhole(distance=4.0)
    pose = torch.zeros(3, model.num_joints, 3, dtype=D)
    for name, value in (("left_knee", (0.5, 0, 0)), ("right_elbow", (0, 0.6, 0)), ("spine2", (0.1, 0.1, 0))):
        pose[1:, model.joint_names.index(name)] = torch.tensor(value, dtype=D)
    pose[:, 0, 1] = torch.tensor([-0.2, 0.0, 0.2], dtype=D)
    transl = torch.tensor([[0.05, -0.02, 0.1]] * 3, dtype=D)
    detected = keypoints(model, kp_map, cam, pose, transl)
    detected[:, jw.sum(1) == 0, 2] = 0.0
    res = fit(model, kp_map, detected, cam, FitConfig(iterations=(80, 150, 40), shape_weight=10.0))
    assert finite(res) and not res.flagged.any() and res.residual_px.max() < 2.0
    fitted = KeypointModel(model, kp_map)(res.betas, res.pose, res.transl)
    truth = KeypointModel(model, kp_map)(torch.zeros(model.num_shape, dtype=D), pose, transl)
    assert (fitted - truth).norm(dim=-1).mean() < 0.08
