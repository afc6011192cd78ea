"""The default parser within the matting step's person (``delta parse --person``): the parts partition
that person, a full-body frame parses as it does within the landmarker's own mask, a tracked head's mask
is not cut a second time, and a matting file that does not fit is named."""

import re

import h5py
import numpy as np
import pytest

from delta.cli import main
from delta.preprocess.steps import HEAD_MODELS

pytestmark = pytest.mark.slow


def _steps(tmp_path, video, model, *extra):
    args = ["--video", str(video), "--path", str(model), *extra]
    assert main(["matte", *args, "--model", "mediapipe", "--out", str(tmp_path / "matte.h5")]) == 0
    assert main(["parse", *args, "--model", "default", "--out", str(tmp_path / "own.h5")]) == 0
    person = ["--person", str(tmp_path / "matte.h5")]
    assert main(["parse", *args, "--model", "default", *person, "--out", str(tmp_path / "within.h5")]) == 0


def test_parts_partition_the_matting_steps_person_and_match_the_landmarkers_own(tmp_path, tiny_captures,
                                                                                mediapipe_pose_model):  # fmt: skip
    video = tiny_captures / "tight" / "tight.mp4"
    _steps(tmp_path, video, mediapipe_pose_model)
    with (
        h5py.File(tmp_path / "matte.h5") as m,
        h5py.File(tmp_path / "own.h5") as a,
        h5py.File(tmp_path / "within.h5") as b,
    ):
        person = m["person"][:] > 127
        assert person.any(axis=(1, 2)).all()
        total = sum(b[k][:].astype(int) for k in ("skin", "hair", "clothing"))
        assert (total == person).all()  # a partition of the matting step's person, pixel for pixel
        for k in ("skin", "hair", "clothing"):
            # the same model's mask, stored as bytes: only pixels at alpha 0.5 may fall the other way
            assert (a[k][:] != b[k][:]).mean() < 1e-3, k
        assert "within" not in b.attrs["model"] and b.attrs["model"] == a.attrs["model"]


def test_a_tracked_head_with_a_given_mask_is_not_cut_again(monkeypatch, mediapipe_pose_model):
    from delta.preprocess import face_tracking as ft

    head = ft.HeadLandmarker(*(mediapipe_pose_model.parent / n for n in HEAD_MODELS))
    face = np.zeros((468, 3), np.float32)
    face[:, :2] = np.random.default_rng(0).uniform(40, 80, (468, 2))
    face[:, 2] = 1.0
    head.tracker = lambda frame: face  # a face seen in every frame
    frame = np.full((128, 128, 3), 120, np.uint8)
    given = np.zeros((128, 128), np.float32)
    given[30:100, 30:100] = 1.0

    def cut(*_):
        raise AssertionError("GrabCut ran")

    monkeypatch.setattr(ft, "head_mask", cut)
    result = head(frame, mask=given)
    assert result.mask is given and result.presence == 1.0
    np.testing.assert_array_equal(result.landmarks, ft.blazepose_from_face(face))
    with pytest.raises(AssertionError, match="GrabCut ran"):  # without one the head's own mask is cut
        head(frame)


def test_a_matting_file_that_does_not_fit_is_named(tmp_path, tiny_captures, mediapipe_pose_model, capsys):
    video = tiny_captures / "tight" / "tight.mp4"
    args = ["parse", "--video", str(video), "--path", str(mediapipe_pose_model), "--out", str(tmp_path / "p.h5")]
    short = tmp_path / "short.h5"
    with h5py.File(short, "w") as f:
        f["person"] = np.zeros((2, 128, 128), np.uint8)
    assert main([*args, "--model", "default", "--person", str(short)]) != 0
    assert re.search(r"short\.h5: no person mask for video frame 2 \(the file holds 2 rows\)", capsys.readouterr().err)
    small = tmp_path / "small.h5"
    with h5py.File(small, "w") as f:
        f["person"] = np.zeros((40, 64, 64), np.uint8)
    assert main([*args, "--model", "default", "--person", str(small)]) != 0
    assert re.search(r"small\.h5: person masks are 64x64, the video's frames 128x128", capsys.readouterr().err)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["clothing"] = np.zeros((1, 4, 4), np.uint8)
    assert main([*args, "--model", "default", "--person", str(other)]) != 0
    assert re.search(r"other\.h5: not a matting step's file", capsys.readouterr().err)
    assert main([*args, "--model", "u2net_cloth", "--person", str(short)]) != 0
    assert re.search(r"--person: only the default parser", capsys.readouterr().err)
    assert not (tmp_path / "p.h5").exists()  # nothing half-written
