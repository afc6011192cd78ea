"""Frame records: crop/undistort consistency, dataset adapters, bad input."""

import json
import shutil

import h5py
import numpy as np
import pytest
import torch

from delta import DeltaError
from delta.cameras.crop import CropBox, crop_camera
from delta.cameras.models import OrthographicCamera, PinholeCamera, look_at
from delta.data.record import FrameRecord
from delta.data.sources import peoplesnapshot_source, synthetic_source
from delta.preprocess.frames import prepare, square_box


def random_points(n=100):
    return torch.from_numpy(np.random.default_rng(0).uniform(-0.7, 0.7, size=(n, 3)))


@pytest.mark.parametrize("box", [CropBox(100, 40, 300, 128), CropBox(-20, -10, 600, 512), CropBox(3, 7, 50, 200)])
def test_cropped_cameras_project_where_the_crop_moves_points(box):
    R, t = look_at(torch.tensor([0.2, 0.1, 3.0], dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                   torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))  # fmt: skip
    K = torch.tensor([[500.0, 0, 260], [0, 505, 240], [0, 0, 1]], dtype=torch.float64)
    pin = PinholeCamera(K, R, t, torch.zeros(5, dtype=torch.float64), 520, 480)
    ortho = OrthographicCamera(torch.tensor(0.9, dtype=torch.float64), torch.tensor([0.1, -0.05], dtype=torch.float64),
                               500, 500)  # fmt: skip
    X = random_points()
    for cam in (pin, ortho):
        uv, depth = cam.project(X)
        uv2, depth2 = crop_camera(cam, box).project(X)
        torch.testing.assert_close(uv2, box.apply_to_points(uv))
        torch.testing.assert_close(depth2, depth)


def test_a_person_cut_by_the_image_edge_is_not_padded_beyond_it():
    """Inside the image the square is centred on the person; a person running off the bottom
    (head and shoulders) gets a square whose bottom is the image's bottom edge."""
    m = np.zeros((200, 300), np.uint8)
    m[50:150, 100:140] = 255  # 40 wide, 100 tall, centre (120, 100)
    box = square_box(iter([m]), 0.1, 64)
    assert (box.size, box.u0, box.v0) == (120, 60, 40)  # side 100 * 1.2; centred
    m = np.zeros((200, 300), np.uint8)
    m[120:200, 100:160] = 255  # the chest runs off the bottom edge
    box = square_box(iter([m]), 0.1, 64)
    assert box.size == 96 and box.v0 + box.size == 200 and box.u0 == 130 - 48
    m = np.zeros((200, 300), np.uint8)
    m[0:60, 0:30] = 255  # cut by the top and the left edges
    box = square_box(iter([m]), 0.1, 64)
    assert (box.u0, box.v0, box.size) == (0, 0, 72)


def gt_keypoints3d(capture, frame_ids):
    with h5py.File(capture / "gt" / "frames.h5") as g:
        return torch.from_numpy(g["keypoints3d"][:][frame_ids].astype(np.float64))


@pytest.mark.slow
@pytest.mark.parametrize("subject", ["tight", "loose"])
def test_synthetic_record_is_consistent_with_ground_truth(tmp_path, tiny_captures, subject):
    capture = tiny_captures / subject
    summary = prepare(synthetic_source(capture, subject), tmp_path / "frames.h5", 96)
    with FrameRecord(tmp_path / "frames.h5") as rec:
        assert len(rec) == summary["frames"] and rec.size == 96
        assert rec.h5["images"].shape == (len(rec), 96, 96, 3)
        ids = rec.h5["frame_ids"][:]
        for i in range(len(rec)):  # undistortion + crop + resize moved the keypoints with the camera
            uv, _ = rec.camera(i).project(gt_keypoints3d(capture, ids[i : i + 1])[0])
            np.testing.assert_allclose(rec.h5["keypoints"][i][:, :2], uv.numpy(), atol=0.02)
        splits = json.loads((capture / "gt" / "splits.json").read_text())
        assert sorted(ids[rec.indices("test_view")].tolist()) == splits["test_view"]
        assert sorted(ids[rec.indices("test_pose")].tolist()) == splits["test_pose"]
        assert rec.sources["person"] == "dataset:gt/frames.h5:alpha" and rec.sources["images"] == f"video:{subject}.mp4"
        person = rec.h5["person"][:]
        assert (rec.h5["clothing"][:].astype(bool) <= (person > 0)).all()
        # the person sits inside the square crop with a margin: no mask on the border rows/columns
        assert person[:, 0].max() == 0 and person[:, -1].max() == 0 and person[:, :, 0].max() == 0
        # the background of the image is the capture's constant colour where the mask is empty
        bg = rec.h5["images"][0][person[0] == 0]
        assert np.abs(bg.astype(int) - np.median(bg, axis=0)).max() <= 2


@pytest.mark.slow
def test_peoplesnapshot_adapter_matches_the_synthetic_record(tmp_path, tiny_captures):
    ps = prepare(peoplesnapshot_source(tiny_captures / "ps", "tight", {"train": [0, 4, 1], "test": [5, 6, 1]}),
                 tmp_path / "ps.h5", 96)  # fmt: skip
    prepare(synthetic_source(tiny_captures / "tight", "tight"), tmp_path / "syn.h5", 96)
    assert ps["sources"] == {"person": "dataset:masks.hdf5", "keypoints": "dataset:keypoints.hdf5"}
    with FrameRecord(tmp_path / "ps.h5") as a, FrameRecord(tmp_path / "syn.h5") as b:
        assert len(a) == len(b) == 7
        assert abs(a.h5.attrs["crop"][2] - b.h5.attrs["crop"][2]) <= 2  # binary vs soft masks: same box
        np.testing.assert_allclose(a.camera().K.numpy(), b.camera().K.numpy(), rtol=0.03)
        iou = ((a.h5["person"][:] > 127) & (b.h5["person"][:] > 127)).sum() / (
            (a.h5["person"][:] > 127) | (b.h5["person"][:] > 127)
        ).sum()
        assert iou > 0.85  # boundary pixels of a thin 128² person: binary centre samples vs soft alpha
        assert a.indices("test_view").tolist() == [5, 6]


def test_empty_video_is_named(tmp_path, tiny_captures):
    capture = tmp_path / "tight"
    shutil.copytree(tiny_captures / "tight", capture)
    (capture / "tight.mp4").write_bytes(b"not a video")
    with pytest.raises(DeltaError, match="tight.mp4"):
        prepare(synthetic_source(capture, "tight"), tmp_path / "out.h5", 64)
    assert not (tmp_path / "out.h5").exists() and not list(tmp_path.glob(".out*"))


def test_frame_count_mismatch_is_named(tmp_path, tiny_captures):
    with pytest.raises(DeltaError, match=r"asked for frame 50 but the dataset's annotations hold 7 frames"):
        prepare(peoplesnapshot_source(tiny_captures / "ps", "tight", {"train": [0, 50, 10], "test": [1, 2, 1]}),
                tmp_path / "out.h5", 64)  # fmt: skip
    assert not (tmp_path / "out.h5").exists()


def test_frames_without_a_person_are_skipped_and_recorded(tmp_path, tiny_captures):
    root = tmp_path / "ps"
    shutil.copytree(tiny_captures / "ps", root)
    with h5py.File(root / "tight" / "masks.hdf5", "r+") as f:
        f["masks"][2] = 0
    summary = prepare(peoplesnapshot_source(root, "tight", {"train": [0, 4, 1], "test": [5, 6, 1]}),
                      tmp_path / "out.h5", 64)  # fmt: skip
    assert summary["skipped_empty"] == [2] and summary["frames"] == 6
    with FrameRecord(tmp_path / "out.h5") as rec:
        assert 2 not in rec.h5["frame_ids"][:].tolist() and rec.h5.attrs["skipped_empty"].tolist() == [2]


def test_missing_peoplesnapshot_files_say_where(tmp_path):
    with pytest.raises(DeltaError, match=r"missing .*male-3-casual.mp4.*datasets.peoplesnapshot.root"):
        peoplesnapshot_source(tmp_path, "male-3-casual", {"train": [0, 4, 1], "test": [5, 6, 1]})


def test_bad_split_range_is_named(tmp_path, tiny_captures):
    with pytest.raises(DeltaError, match=r"subjects.tight.train: expected \[start, end, step\]"):
        peoplesnapshot_source(tiny_captures / "ps", "tight", {"train": [0, 4], "test": [5, 6, 1]})


def clip_with_masks(tmp_path, tiny_captures) -> None:
    """tmp_path/clip.mp4 (the tight capture's video) and m.h5, its person masks as a matting step writes them."""
    shutil.copy(tiny_captures / "tight" / "tight.mp4", tmp_path / "clip.mp4")
    with h5py.File(tiny_captures / "tight" / "gt" / "frames.h5") as g, h5py.File(tmp_path / "m.h5", "w") as f:
        f.create_dataset("person", data=g["alpha"][:])
        f.attrs["model"] = "rvm:test.onnx"


def test_generic_video_with_a_step_file(tmp_path, tiny_captures):
    """Any video: default camera unless a camera.json is given; masks from a model step's file."""
    from delta.data.sources import video_source
    from delta.preprocess.steps import attach

    clip_with_masks(tmp_path, tiny_captures)
    src = video_source(tmp_path, "clip", {"train": [0, 4, 1], "test": [5, 6, 1]})
    assert src.origin["camera"] == "default" and src.camera.K[0, 0] == 1.2 * 128
    attach(src, tmp_path / "m.h5")
    summary = prepare(src, tmp_path / "out.h5", 64)
    assert summary["sources"] == {"person": "model:rvm:test.onnx", "camera": "default"}
    (tmp_path / "clip.camera.json").write_text(json.dumps({"K": [[300, 0, 64], [0, 300, 64], [0, 0, 1]]}))
    src = video_source(tmp_path, "clip", {})
    assert src.origin["camera"] == "file" and src.camera.K[0, 0] == 300 and len(src.frames) == 7
    src.close()


def test_a_step_files_keypoint_depths_reach_the_record_as_they_are(tmp_path, tiny_captures):
    """The keypoints' relative depths are carried to the record row by row (a crop moves the image, not them),
    NaN kept; a table of the wrong shape is refused naming the file and the dataset."""
    from delta.data.sources import video_source
    from delta.preprocess.steps import attach

    clip_with_masks(tmp_path, tiny_captures)
    depth = np.random.default_rng(0).normal(size=(7, 18)).astype(np.float32)
    depth[3, 5] = np.nan
    with h5py.File(tmp_path / "m.h5", "a") as f:
        f.create_dataset("keypoint_depth", data=depth)
    src = video_source(tmp_path, "clip", {"train": [1, 4, 1], "test": [6, 6, 1]})
    attach(src, tmp_path / "m.h5")
    summary = prepare(src, tmp_path / "out.h5", 64)
    assert summary["sources"]["keypoint_depth"] == "model:rvm:test.onnx"
    with FrameRecord(tmp_path / "out.h5") as rec:
        ids, got = rec.h5["frame_ids"][:], rec.h5["keypoint_depth"][:]
    np.testing.assert_array_equal(got, depth[ids])  # NaN where NaN
    with h5py.File(tmp_path / "m.h5", "a") as f:
        del f["keypoint_depth"]
        f.create_dataset("keypoint_depth", data=depth[:, :17])
    src = video_source(tmp_path, "clip", {})
    with pytest.raises(DeltaError, match=r"m\.h5: 'keypoint_depth' has shape \(7, 17\), expected \(N >= 7, 18\)"):
        attach(src, tmp_path / "m.h5")
    src.close()


def test_a_frame_in_two_splits_fills_both_rows(tmp_path, tiny_captures):
    """A one-frame capture (a photograph) lists its frame as training and test: both rows hold the frame."""
    from delta.data.record import FrameRecord
    from delta.data.sources import video_source
    from delta.preprocess.steps import attach

    clip_with_masks(tmp_path, tiny_captures)
    src = video_source(tmp_path, "clip", {"train": [2, 2, 1], "test": [2, 2, 1]})
    attach(src, tmp_path / "m.h5")
    prepare(src, tmp_path / "out.h5", 64)
    with FrameRecord(tmp_path / "out.h5") as rec:
        assert list(rec.h5["frame_ids"][:]) == [2, 2] and list(rec.h5["split"][:]) == [0, 1]
        images, full = rec.h5["images"][:], rec.h5["full"]["images"][:]
        person = rec.h5["person"][:]
    assert images[0].any() and np.array_equal(images[0], images[1]) and np.array_equal(full[0], full[1])
    assert person[0].max() == 255 and np.array_equal(person[0], person[1])


def test_peoplesnapshot_standard_splits_and_missing_ranges(tmp_path, tiny_captures):
    from delta.data import STANDARD_SPLITS

    start, end, step = STANDARD_SPLITS["male-3-casual"]["train"]
    assert len(range(start, end + 1, step)) == 114  # as the published protocol counts
    root = tmp_path / "ps"
    shutil.copytree(tiny_captures / "ps" / "tight", root / "male-3-casual")
    (root / "male-3-casual" / "tight.mp4").rename(root / "male-3-casual" / "male-3-casual.mp4")
    src = peoplesnapshot_source(root, "male-3-casual", {})
    assert src.frames[:3] == [(0, 0), (4, 0), (8, 0)] and (456, 1) in src.frames
    src.close()
    shutil.copytree(root / "male-3-casual", root / "someone")
    (root / "someone" / "male-3-casual.mp4").rename(root / "someone" / "someone.mp4")
    with pytest.raises(DeltaError, match="someone: give 'train' and 'test' frame ranges"):
        peoplesnapshot_source(root, "someone", {})


def test_peoplesnapshot_reconstructed_poses_reach_the_record(tmp_path, tiny_captures):
    root = tmp_path / "ps"
    shutil.copytree(tiny_captures / "ps", root)
    pose = np.random.default_rng(0).normal(size=(7, 72))
    with h5py.File(root / "tight" / "reconstructed_poses.hdf5", "w") as f:
        f["pose"], f["trans"], f["betas"] = pose, np.zeros((7, 3)), np.arange(10.0)
    summary = prepare(peoplesnapshot_source(root, "tight", {"train": [0, 4, 2], "test": [5, 6, 1]}),
                      tmp_path / "out.h5", 64)  # fmt: skip
    assert summary["sources"]["smpl"] == "dataset:reconstructed_poses.hdf5"
    with FrameRecord(tmp_path / "out.h5") as rec:
        np.testing.assert_array_equal(rec.h5["smpl_pose"][:], pose[[0, 2, 4, 5, 6]])
        np.testing.assert_array_equal(rec.h5["smpl_betas"][:], np.arange(10.0))


def test_scoring_size_follows_the_protocol():
    from delta.preprocess.frames import scoring_size

    assert scoring_size("peoplesnapshot", 1080, 1080) == (540, 540)  # People Snapshot is scored at 540²
    assert scoring_size("synthetic", 512, 512) == (512, 512)  # a synthetic capture at its own size
    assert scoring_size("video", 1920, 1080) == (1080, 608)  # a long side of at most 1080
    assert scoring_size("video", 640, 480) == (640, 480)
    assert scoring_size("peoplesnapshot", 1080, 1080, score_size=270) == (270, 270)
    assert scoring_size("synthetic", 256, 256, score_size=512) == (256, 256)  # never larger than the capture


@pytest.mark.slow
def test_whole_frames_map_onto_the_crop(tmp_path, tiny_captures):
    """People Snapshot's whole frames are kept at half size; a point of the capture, halved, is carried
    by the whole frames' view geometry to where the crop puts it (the record's keypoints)."""
    from delta.data.frames import load_full_frames
    from delta.models.image import View
    from delta.preprocess.frames import scoring_size

    src = peoplesnapshot_source(tiny_captures / "ps", "tight", {"train": [0, 4, 1], "test": [5, 6, 1]})
    W, H = src.camera.width, src.camera.height
    keypoints = [np.asarray(src.provided["keypoints"](i)) for i in range(7)]
    und = __import__("delta.preprocess.frames", fromlist=["Undistorter"]).Undistorter(src.camera)
    prepare(src, tmp_path / "ps.h5", 96, full_size=scoring_size("peoplesnapshot", W, H))
    full = load_full_frames(tmp_path / "ps.h5", [0, 5])
    assert full.size == ((W + 1) // 2, (H + 1) // 2) and full.images.shape[1:3] == (full.size[1], full.size[0])
    scale, shift = full.view_geometry(96)
    view = View(full.size[1], full.size[0], scale, shift)
    with FrameRecord(tmp_path / "ps.h5") as rec:
        for row, frame in ((0, 0), (1, 5)):
            kp = keypoints[frame]
            ok = kp[:, 2] > 0
            halved = und.points(kp[ok, :2]) * np.array([full.size[0] / W, full.size[1] / H])
            mapped = view.to_model(torch.from_numpy(halved)).numpy()
            np.testing.assert_allclose(mapped, rec.h5["keypoints"][frame][ok, :2], atol=1e-3)
            # and the whole frame's person, where the crop lies, is the record's (up to resampling)
            assert abs(full.person[row].sum().item() * (96 / full.crop[2] * W / full.size[0]) ** 2
                       - rec.h5["person"][frame].astype(np.float64).sum() / 255) < 0.05 * rec.h5["person"][frame].sum() / 255  # fmt: skip
