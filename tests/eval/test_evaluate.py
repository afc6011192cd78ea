"""Scoring a (tiny) trained avatar on its test frames."""

import math

import numpy as np
import pytest
import torch

from delta import DeltaError
from delta.eval.evaluate import EvalSettings, evaluate, face_pixels, pick_frames, summarize, train_body_error_mm
from delta.training.run import load_trained

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def trained(tiny_trained):
    t = tiny_trained["tight"]
    return load_trained(t["model"], t["record"], t["body"]), t


def test_frames_per_split_are_evenly_spaced():
    split = np.array([0, 1, 0, 1, 1, 1, 2, 2, 1])
    assert pick_frames(split, ("test_view",), 0) == [(1, "test_view"), (3, "test_view"), (4, "test_view"),
                                                      (5, "test_view"), (8, "test_view")]  # fmt: skip
    assert [f for f, _ in pick_frames(split, ("test_view", "test_pose"), 2)] == [1, 8, 6, 7]
    with pytest.raises(DeltaError, match="unknown split 'val'"):
        pick_frames(split, ("val",), 0)


def test_rows_scores_and_convention(trained):
    tr, t = trained
    st = EvalSettings(splits=("test_view", "test_pose"), refine_steps=2, refine_rays=64)
    df = evaluate(tr, t["record"], st, gt_meshes=f"{t['capture']}/gt/meshes.h5", subject="tight")
    frames = pick_frames(tr.data.split, st.splits, 0)
    assert len(df) == 2 * len(frames)  # before and after refinement
    assert list(df["refined"]) == [False, True] * len(frames)
    assert set(df["background"]) == {"white"} and set(df["image"]) == {"full"}
    assert (df["resolution"] == tr.data.resolution).all()
    assert df["psnr"].between(5, 60).all() and df["ssim"].between(0, 1).all() and (df["l1"] > 0).all()
    # a few steps from the GT init: the body stays within centimetres of the GT body
    assert df["body_err_mm"].between(0, 30).all()
    assert train_body_error_mm(tr, f"{t['capture']}/gt/meshes.h5") < 30
    # the mesh silhouette lines up with the person (at 32², arms and hair edges cost much of the IoU)
    assert (df["mesh_iou"] > 0.4).all()
    s = summarize(df)
    assert set(s) == {split for _, split in frames}
    assert s["test_view"]["refined"]["frames"] == sum(1 for _, sp in frames if sp == "test_view")


def test_face_pixels_lie_on_the_head(trained):
    tr, _ = trained
    f = int(np.flatnonzero(tr.data.split == 1)[0])
    with torch.no_grad():
        mesh = tr.model.posed_mesh(f)[0]
    face = face_pixels(tr.model, f, mesh.vertices)
    person = tr.data.person[f] > 0.5
    rows = torch.nonzero(person.any(1)).squeeze(1)
    assert face.any(), "a front-ish view shows some of the face"
    # the face is in the top fifth of the person's height
    top, height = int(rows[0]), int(rows[-1] - rows[0] + 1)
    face_rows = torch.nonzero(face.any(1)).squeeze(1)
    assert int(face_rows.max()) < top + height / 5 + 1


def test_missing_or_foreign_model_files_are_named(tmp_path, trained):
    _, t = trained
    with pytest.raises(DeltaError, match="none.pt: file not found"):
        load_trained(tmp_path / "none.pt", t["record"], t["body"])
    torch.save({"model": {}}, tmp_path / "bad.pt")
    with pytest.raises(DeltaError, match="bad.pt: missing 'stage'"):
        load_trained(tmp_path / "bad.pt", t["record"], t["body"])


def test_psnr_rises_with_refinement_from_a_perturbed_pose(trained):
    tr, t = trained
    model, data = tr.model, tr.data
    f = int(np.flatnonzero(data.split == 1)[0])
    with torch.no_grad():
        model.transl[f] += torch.tensor([0.03, 0.0, 0.0])  # shift the test frame 3 cm sideways
    st = EvalSettings(splits=("test_view",), max_frames=1, refine_steps=40, refine_rays=256, refine_lr=2e-3)
    df = evaluate(tr, t["record"], st)
    before, after = df["psnr"].tolist()
    assert after > before + 0.5 and not math.isnan(after)


@pytest.mark.parametrize("subject", ["tight", "loose"])
def test_a_common_resolution_renders_the_same_rays(tiny_trained, subject):
    """Loaded at twice its training resolution, an avatar renders the sub-pixel rays of its own
    resolution's 2×2 supersampling: the 2× render area-downsampled is that supersampled render
    (pinhole intrinsics rescaled; an orthographic camera is resolution-free)."""
    from delta.models.image import render_image

    t = tiny_trained[subject]
    own = load_trained(t["model"], t["record"], t["body"])
    big = load_trained(t["model"], t["record"], t["body"], resolution=2 * own.data.resolution)
    n = own.data.resolution
    assert big.data.resolution == 2 * n and big.data.images.shape[1:3] == (2 * n, 2 * n)
    assert big.settings.resolution == n and big.model.resolution == 2 * n
    f = int(np.flatnonzero(own.data.split == 1)[0])
    a = render_image(own.model, f, supersample=2)
    b = render_image(big.model, f, supersample=1)
    for key in ("rgb", "silhouette"):
        down = b[key].reshape(n, 2, n, 2, -1).mean((1, 3)).reshape(a[key].shape)
        torch.testing.assert_close(down, a[key], atol=2e-5, rtol=0)
    assert a["rgb"].std() > 0.05, "a blank render would pass trivially"
    df = evaluate(big, t["record"], EvalSettings(splits=("test_view",), max_frames=1, refine_steps=0, supersample=1))
    assert (df["resolution"] == 2 * n).all() and (df["train_resolution"] == n).all()
    with pytest.raises(DeltaError, match="resolution"):
        load_trained(t["model"], t["record"], t["body"], resolution=-1)
