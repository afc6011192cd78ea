"""What phone videos do to the real path, each with a small generated clip and a clear outcome: a portrait
clip stored with a display rotation, a variable frame rate, a long video thinned to a configured count,
motion-blurred frames, a person running off the image, and somebody else in the picture."""

import dataclasses
import json
import struct

import cv2
import h5py
import numpy as np
import pytest

from delta import DeltaError
from delta.cli import main
from delta.data.sources import default_camera, synthetic_source, video_source
from delta.data.video import iter_video, probe_video, select_frames, thin
from delta.preprocess.frames import prepare

pytestmark = pytest.mark.slow


def write_clip(path, frames, fps: float = 25.0) -> str:
    """An mp4v clip of (H, W, 3) uint8 RGB frames."""
    h, w = frames[0].shape[:2]
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    for f in frames:
        out.write(cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2BGR))
    out.release()
    return str(path)


def _box(data: bytes, kind: bytes, start: int = 0, end: int | None = None) -> int:
    """Offset of the first ``kind`` box among the boxes in data[start:end] (its size field)."""
    end = len(data) if end is None else end
    k = start
    while k < end:
        size = struct.unpack(">I", data[k : k + 4])[0]
        if data[k + 4 : k + 8] == kind:
            return k
        k += size
    raise AssertionError(f"no {kind!r} box")


def _path(data: bytes, kinds: list[bytes]) -> list[int]:
    """Offsets of the nested boxes moov/trak/..., outermost first."""
    out, start, end = [], 0, len(data)
    for kind in kinds:
        k = _box(data, kind, start, end)
        out.append(k)
        start, end = k + 8, k + struct.unpack(">I", data[k : k + 4])[0]
    return out


def set_display_rotation(path, degrees: int) -> None:
    """Write a display rotation into the clip's track header, as a phone does for a portrait video."""
    data = bytearray(open(path, "rb").read())
    tkhd = _path(data, [b"moov", b"trak", b"tkhd"])[-1]
    assert data[tkhd + 8] == 0  # version 0: the matrix sits 44 bytes after the box's type
    c, s = {90: (0, 1), 180: (-1, 0), 270: (0, -1)}[degrees]
    one = 1 << 16
    data[tkhd + 48 : tkhd + 84] = struct.pack(">9i", c * one, s * one, 0, -s * one, c * one, 0, 0, 0, 1 << 30)
    open(path, "wb").write(bytes(data))


def set_frame_durations(path, weights: list[int]) -> None:
    """Rewrite the clip's sample durations (time-to-sample table) in proportion to ``weights`` so that its
    frames are unevenly spaced, as a phone's variable frame rate records them, over the same total time
    (the track's duration and edit list stay true); the parent boxes' sizes follow (moov lies after mdat)."""
    data = bytearray(open(path, "rb").read())
    boxes = _path(data, [b"moov", b"trak", b"mdia", b"minf", b"stbl", b"stts"])
    assert boxes[0] > _box(data, b"mdat")  # chunk offsets point before moov: they stay valid
    stts = boxes[-1]
    old = struct.unpack(">I", data[stts : stts + 4])[0]
    entries = struct.unpack(">I", data[stts + 12 : stts + 16])[0]
    table = struct.unpack(f">{2 * entries}I", data[stts + 16 : stts + 16 + 8 * entries])
    total = sum(n * d for n, d in zip(table[::2], table[1::2]))
    durations = [total * w // sum(weights) for w in weights]
    durations[-1] += total - sum(durations)
    body = struct.pack(">I", len(durations)) + b"".join(struct.pack(">II", 1, d) for d in durations)
    new = struct.pack(">I", 16 + 8 * len(durations)) + b"stts" + bytes(4) + body
    grow = len(new) - old
    data[stts : stts + old] = new
    for k in boxes[:-1]:
        data[k : k + 4] = struct.pack(">I", struct.unpack(">I", data[k : k + 4])[0] + grow)
    open(path, "wb").write(bytes(data))


def numbered(count: int, h: int = 48, w: int = 64) -> list[np.ndarray]:
    """Frames that say their own number: a bar whose position is the frame index."""
    out = []
    for i in range(count):
        f = np.full((h, w, 3), 30, np.uint8)
        f[4 + 2 * (i % 18) : 8 + 2 * (i % 18), 8:56] = 230
        f[40:44, 4 + 2 * (i // 18) : 8 + 2 * (i // 18)] = 230
        out.append(f)
    return out


def which(frame: np.ndarray) -> int:
    rows = frame[:, 8:56, 0].mean(1) > 128
    cols = frame[40:44, :, 0].mean(0) > 128
    return (int(np.flatnonzero(rows)[0]) - 4) // 2 + 18 * ((int(np.flatnonzero(cols)[0]) - 4) // 2)


def test_a_portrait_clip_stored_with_a_display_rotation_is_read_upright(tmp_path):
    upright = numbered(6, h=64, w=48)
    path = write_clip(tmp_path / "phone.mp4", [np.rot90(f, 1) for f in upright])  # stored landscape
    set_display_rotation(path, 90)
    info = probe_video(path)
    assert (info.width, info.height, info.rotation, info.frames) == (48, 64, 90, 6)
    got = dict(iter_video(path, set(range(6))))
    for i, f in enumerate(upright):
        assert got[i].shape == f.shape and np.abs(got[i].astype(int) - f.astype(int)).mean() < 4
    source = video_source(tmp_path, "phone", {"train": [0, 5, 1]})
    assert (source.camera.width, source.camera.height) == (48, 64)  # the default camera is portrait too
    assert source.origin["rotation"] == "90 degrees, applied"


def test_a_variable_frame_rate_clip_keeps_every_frame_in_order(tmp_path):
    path = write_clip(tmp_path / "vfr.mp4", numbered(30), fps=30.0)
    set_frame_durations(path, [2 if i % 3 else 5 for i in range(30)])  # gaps of 2 and 5 units
    info = probe_video(path)
    assert info.frames == 30
    assert [which(f) for _, f in iter_video(path)] == list(range(30))  # decoding order, none lost or doubled
    assert [i for i, _ in iter_video(path, {3, 17, 29})] == [3, 17, 29]
    # a header that promises more frames than the video holds: a step reads to the end, a record refuses
    assert [i for i, _ in iter_video(path, {28, 29, 30, 31}, to_end=True)] == [28, 29]
    with pytest.raises(DeltaError, match=r"vfr\.mp4: the video ends after 30 frames, but frame\(s\) \[30, 31\]"):
        list(iter_video(path, {29, 30, 31}))


def test_a_long_video_is_thinned_evenly_to_the_configured_count(tmp_path):
    assert thin(list(range(0, 1000, 2)), 5) == [0, 250, 500, 748, 998]
    assert thin([4, 5, 6], 5) == [4, 5, 6] and thin([4, 5, 6], 0) == [4, 5, 6] and thin([4, 5, 6], 1) == [4]
    frames, note = select_frames({"test": [900, 999, 1]}, 1000, "k", {"train": 100, "test": 10})
    train = [i for i, s in frames if s == 0]
    test = [i for i, s in frames if s == 1]
    assert len(train) == 100 and train[0] == 0 and train[-1] == 999  # the default range: every frame
    assert len(test) == 10 and test[0] == 900 and test[-1] == 999
    assert note == {"train": [1000, 100], "test": [100, 10]}
    assert select_frames({"train": [0, 9, 1]}, 10, "k", {"train": 300})[1] == {}  # short: untouched
    # through the adapter, said in the record's sources
    write_clip(tmp_path / "long.mp4", numbered(40))
    source = video_source(tmp_path, "long", {"train": [0, 35, 1], "test": [36, 39, 1]}, {"train": 6, "test": 0})
    assert [i for i, s in source.frames if s == 0] == [0, 7, 14, 21, 28, 35]
    assert [i for i, s in source.frames if s == 1] == [36, 37, 38, 39]
    assert source.origin["thinned"] == "train 36 -> 6"


def test_the_keypoint_step_analyses_only_the_selected_frames(tiny_captures, mediapipe_pose_model, tmp_path):
    video = tiny_captures / "tight" / "tight.mp4"
    out = tmp_path / "kp.h5"
    code = main(["keypoints", "--video", str(video), "--model", "mediapipe", "--path", str(mediapipe_pose_model),
                 "--out", str(out), "--frames", json.dumps({"train": [0, 6, 1]}),
                 "--max-frames", json.dumps({"train": 3})])  # fmt: skip
    assert code == 0
    with h5py.File(out) as f:
        kp = f["keypoints"][:]
    analysed = sorted(np.flatnonzero(kp[..., 2].max(-1) > 0).tolist())
    assert kp.shape[0] == 7 and analysed == [0, 3, 6]  # [0, 6] thinned to 3: the others never decoded


def tight_source(tiny_captures, video=None):
    source = synthetic_source(tiny_captures / "tight", "tight")
    return source if video is None else dataclasses.replace(source, video=video)


def frames_of(source) -> dict[int, np.ndarray]:
    return dict(iter_video(source.video, {i for i, _ in source.frames}))


def test_motion_blurred_training_frames_are_listed_and_left_out(tiny_captures, tmp_path):
    source = tight_source(tiny_captures)
    clean = prepare(source, tmp_path / "clean.h5", size=64)
    assert clean["blurred"] == [] and clean["skipped_blurred"] == []  # a sharp capture loses nothing
    source = tight_source(tiny_captures)
    frames = frames_of(source)
    kernel = np.zeros((9, 9), np.float32)
    kernel[4] = 1 / 9  # 9 pixels of horizontal motion
    smeared = {0, 2}
    clip = [cv2.filter2D(frames[i], -1, kernel) if i in smeared else frames[i] for i in sorted(frames)]
    source = tight_source(tiny_captures, tmp_path / "blur.mp4")
    write_clip(source.video, clip)
    train = {i for i, s in source.frames if s == 0}
    summary = prepare(source, tmp_path / "blur.h5", size=64)
    assert summary["blurred"] == sorted(smeared)
    assert summary["skipped_blurred"] == sorted(smeared & train)
    with h5py.File(tmp_path / "blur.h5") as f:
        kept = set(f["frame_ids"][:][f["split"][:] == 0].tolist())
    assert kept == train - smeared


def test_a_person_running_off_the_image_is_kept_and_said(tiny_captures, tmp_path):
    source = tight_source(tiny_captures)
    frames = frames_of(source)
    person, keypoints = source.provided["person"], source.provided["keypoints"]
    left = {i: int(np.flatnonzero((person(i) > 127).any(0))[0]) for i in (1, 2)}
    shift = {i: left[i] + 10 for i in (1, 2)}  # pixels to the left: the person leaves by the left edge
    moved = lambda a, i: np.roll(a, -shift.get(i, 0), axis=1) if i in shift else a  # noqa: E731
    cut = lambda a, i: np.concatenate([a[:, shift[i] :], np.zeros_like(a[:, : shift[i]])], 1) if i in shift else a  # noqa: E731

    def kp(i):
        k = keypoints(i).copy()
        k[:, 0] -= shift.get(i, 0)
        k[k[:, 0] < 0, 2] = 0.0  # off the image: not detected
        return k

    source = dataclasses.replace(tight_source(tiny_captures, tmp_path / "cut.mp4"),
                                 provided={"person": lambda i: cut(person(i), i), "keypoints": kp})  # fmt: skip
    write_clip(source.video, [cut(moved(frames[i], i), i) for i in sorted(frames)])
    summary = prepare(source, tmp_path / "cut.h5", size=64)
    assert summary["cut_by_edge"] == {"frames": [1, 2], "edges": {"left": 2}}
    assert summary["frames"] == len(source.frames) and summary["skipped_empty"] == [] and summary["blurred"] == []
    u0, _, side, _ = summary["crop"]
    assert u0 == 0  # the crop ends at the edge the person runs off


def test_somebody_else_in_the_picture_is_removed_and_said(tiny_captures, tmp_path):
    """A second, smaller person beside the tracked one: the record keeps the person with the keypoints."""
    source = tight_source(tiny_captures)
    frames = frames_of(source)
    person, keypoints = source.provided["person"], source.provided["keypoints"]
    H, W = frames[0].shape[:2]

    def other(a):
        """The frame's person, shrunk to 0.8 and moved 60 px to the right, as a second person."""
        small = cv2.resize(a, None, fx=0.8, fy=0.8, interpolation=cv2.INTER_NEAREST)
        out = np.zeros_like(a)
        h, w = small.shape[:2]
        out[H - h :, 60 : 60 + w] = small[:, : W - 60]
        return out

    def wide(a):
        return np.concatenate([a, np.zeros_like(a)], 1)

    def second(a):
        """``a``'s second person, in the right half of the wide frame."""
        return np.roll(wide(other(a)), W, axis=1)

    def two_masks(i):
        return np.maximum(wide(person(i)), second(person(i)))

    def two_frames(i):
        img = wide(frames[i])
        img[:, W:] = frames[i][0, 0]  # the background continues
        there = second(person(i)) > 127
        img[there] = second(frames[i])[there]
        return img

    video = tmp_path / "two.mp4"
    write_clip(video, [two_frames(i) for i in sorted(frames)])
    source = dataclasses.replace(source, video=video, camera=default_camera(2 * W, H),
                                 provided={"person": two_masks, "keypoints": keypoints},
                                 origin={"person": "test", "keypoints": "test"})  # fmt: skip
    shown = sorted({i for i, _ in source.frames})
    alone = {i: wide(person(i)) > 127 for i in shown}  # (the source's files close with the record written)
    summary = prepare(source, tmp_path / "two.h5", size=64)
    assert summary["other_people"] == shown
    with h5py.File(tmp_path / "two.h5") as f:
        ids, full = f["frame_ids"][:], f["full"]["person"][:] > 127
    for k, i in enumerate(ids):
        one = cv2.resize(alone[i].astype(np.uint8), full.shape[:0:-1], interpolation=cv2.INTER_NEAREST) > 0
        assert (full[k] & ~one).sum() <= 0.02 * one.sum()  # nothing of the second person
        assert (one & ~full[k]).sum() <= 0.02 * one.sum()  # all of the tracked one


def test_one_person_goes_by_the_keypoints_and_by_nothing_else():
    from delta.data.person import one_person

    mask = np.zeros((50, 80), np.uint8)
    mask[5:45, 5:25] = 255  # the tracked person (its keypoints)
    mask[10:40, 50:70] = 255  # somebody else, 75 % of its size
    mask[30:32, 40:42] = 255  # a speck
    kp = np.array([[15, 20, 0.9], [12, 30, 0.8], [60, 20, 0.1]])  # the third is not confident
    out, others = one_person(mask, kp)
    assert others == 1 and out[20, 60] == 0 and out[20, 10] == 255 and out[31, 41] == 255
    kp[0, :2] = [60, 20]  # a hand on the other region: it stays (a hand the matting cut off)
    out, others = one_person(mask, kp)
    assert others == 0 and out[20, 60] == 255
    for nobody in (None, np.zeros((3, 3))):  # no confident keypoint: nothing to go by, nothing removed
        out, others = one_person(mask, nobody)
        assert others == 0 and np.array_equal(out, mask)
