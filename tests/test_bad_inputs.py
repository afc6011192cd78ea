"""Inputs that cannot give an avatar stop with one line that says why, and leave no output behind:
a capture without a person, a camera that cannot image, a malformed camera file, masks of the wrong
shape. A capture that is only partly bad is prepared and fitted, its bad frames listed.

Everything is generated here, tiny (64 x 48 videos of 6 frames); the steps run through ``delta.cli.main``.
"""

import json
import pickle
import re

import cv2
import h5py
import numpy as np
import pytest
import torch

from delta.cli import main

W, H, N = 64, 48, 6  # not square: a swapped width and height shows
#: a person standing in the middle of the frame, facing the camera (OpenPose-18 order, pixels)
STICK = np.array([[32, 7], [32, 11], [28, 11], [26, 17], [25, 22], [36, 11], [38, 17], [39, 22], [30, 24],
                  [30, 33], [30, 42], [34, 24], [34, 33], [34, 42], [31, 6], [33, 6], [30, 7], [34, 7]], float)  # fmt: skip
LIMBS = [(0, 1), (1, 2), (2, 3), (3, 4), (1, 5), (5, 6), (6, 7), (1, 8), (8, 9), (9, 10), (1, 11), (11, 12),
         (12, 13), (8, 11)]  # fmt: skip


def person_mask() -> np.ndarray:
    m = np.zeros((H, W), np.uint8)
    for a, b in LIMBS:
        cv2.line(m, tuple(int(v) for v in STICK[a]), tuple(int(v) for v in STICK[b]), 255, 3)
    cv2.circle(m, (32, 7), 3, 255, -1)
    return m


def blob_mask() -> np.ndarray:
    """What a matting model made of a frame without anybody: a soft blob over 15 % of the image."""
    m = np.zeros((H, W), np.uint8)
    cv2.ellipse(m, (W // 2, H // 2), (14, 10), 0, 0, 360, 255, -1)
    assert 0.12 < (m > 127).mean() < 0.17
    return m


def capture(root, frames: str, seed: int = 0) -> dict:
    """``root/clip.mp4`` whose frames are 'p' (a person), 'g' (grey) or 'n' (noise), with the matting and
    keypoint steps' files of what the models find in them: the person's mask and keypoints, or a blob
    and no confident keypoint."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(root / "clip.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 10, (W, H))
    masks = np.zeros((len(frames), H, W), np.uint8)
    keypoints = np.zeros((len(frames), 18, 3), np.float32)
    for i, kind in enumerate(frames):
        if kind == "p":
            image = np.full((H, W, 3), 90, np.uint8)
            image[person_mask() > 0] = (40, 160, 220)
            masks[i], keypoints[i, :, :2], keypoints[i, :, 2] = person_mask(), STICK, 0.9
        else:
            image = np.full((H, W, 3), 128, np.uint8) if kind == "g" else rng.integers(0, 256, (H, W, 3), np.uint8)
            masks[i] = blob_mask()
            if kind == "n":  # a detector guessing at noise: points anywhere, none confident
                keypoints[i, :, :2] = rng.uniform(0, W, (18, 2))
                keypoints[i, :, 2] = rng.uniform(0, 0.25, 18)
        writer.write(image)
    writer.release()
    return write_steps(root, masks, keypoints)


def write_steps(root, masks, keypoints) -> dict:
    with h5py.File(root / "matte.h5", "w") as f:
        f["person"] = masks
        f.attrs["model"] = "mediapipe:test.onnx"
    with h5py.File(root / "keypoints.h5", "w") as f:
        f["keypoints"] = keypoints
        f.attrs["model"] = "mediapipe:test.onnx"
    return {"matte": root / "matte.h5", "keypoints": root / "keypoints.h5"}


def read(path, key: str) -> np.ndarray:
    with h5py.File(path) as f:
        return f[key][:]


def prepare_args(root, out, steps=None, kind="video", config=None) -> list[str]:
    """``delta prepare`` of ``root``'s clip; ``steps`` {name: file}, by default the matting and keypoint steps'."""
    steps = {"m": root / "matte.h5", "k": root / "keypoints.h5"} if steps is None else steps
    steps = [str(s) for s in steps.values()]
    args = ["prepare", "--kind", kind, "--root", str(root), "--subject", "clip", "--resolution", "32",
            "--out", str(out), "--summary", str(out.with_suffix(".json"))]  # fmt: skip
    if config is not None:
        args += ["--settings", json.dumps({"frames": config})]
    return args + (["--steps", *steps] if steps else [])


def fails(capsys, argv: list[str], pattern: str) -> str:
    """Run the CLI: exit status 2 and one error line (no traceback) matching ``pattern``."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith(f"delta {argv[0]}: error: ")]
    assert len(errors) == 1 and "Traceback" not in err, err
    assert re.search(pattern, errors[0]), errors[0]
    return errors[0]


def fit_args(record, body, out) -> list[str]:
    return ["fit-init", "--record", str(record), "--body", str(body), "--out", str(out)]


def nothing_written(out) -> None:
    """Neither the output nor a temporary file beside it (atomic writes leave ``.{stem}.*.part*``)."""
    assert not out.exists()
    assert not list(out.parent.glob(f".{out.stem}.*")), list(out.parent.iterdir())
    assert not out.with_suffix(".json").exists()


# ------------------------------------------------------------------------------------------------ cameras
@pytest.mark.parametrize("camera, pattern", [
    ({"K": [[0, 0, 0], [0, 0, 0], [0, 0, 0]]}, r"camera K has focal lengths fx = 0, fy = 0; both must be > 0"),
    ({"K": [[50, 0, float("nan")], [0, 50, 24], [0, 0, 1]]}, r"camera K is not finite: \[\[50\.0, 0\.0, nan\]"),
    ({"K": [[50, 0, 32], [0, 50, 24], [0, 0, 1]], "dist": [0.1, float("nan")]}, r"camera distortion is not finite"),
    ({"K": [[50, 0, 32], [0, 50, 24], [0, 1, 1]]}, r"camera K's last row is \[0\.0, 1\.0, 1\.0\], expected \[0, 0, 1\]"),
], ids=["zero K", "NaN in K", "NaN in distortion", "K's last row"])  # fmt: skip
def test_a_camera_that_cannot_image_stops_prepare(tmp_path, capsys, camera, pattern):
    capture(tmp_path / "in", "pppppp")
    (tmp_path / "in" / "clip.camera.json").write_text(json.dumps(camera))  # NaN is written as NaN
    out = tmp_path / "frames.h5"
    fails(capsys, prepare_args(tmp_path / "in", out), r"clip\.camera\.json: " + pattern)
    nothing_written(out)


@pytest.mark.parametrize("text, pattern", [
    ('{"K": [[50, 0, 32], [0, 50, 24], [0, 0, 1]]', r"not valid JSON \(Expecting ',' delimiter"),
    ('{"dist": [0, 0, 0, 0, 0]}', r"expected a 'K' \(3x3\) entry"),
    ('{"K": [[50, 0, 32], [0, 50, 24]]}', r"'K' must be a 3x3 array of numbers, found \[\[50, 0, 32\], \[0, 50, 24\]\]"),
    ('{"K": [["50", 0, 32], [0, 50, 24], [0, 0, 1]]}', r"'K' must be a 3x3 array of numbers, found \[\[\"50\""),
    ('{"K": [[50, 0, 32], [0, 50, 24], [0, 0, 1]], "dist": "none"}', r"'dist' must be a list of at most 5 numbers"),
    ('{"K": [[50, 0, 32], [0, 50, 24], [0, 0, 1]], "distortion": [0.1]}', r"unknown key\(s\) \['distortion'\]"),
    ('[[50, 0, 32], [0, 50, 24], [0, 0, 1]]', r"expected a JSON object with 'K' \(3x3\)"),
], ids=["invalid JSON", "missing K", "K 2x3", "K of strings", "dist a string", "unknown key", "not an object"])  # fmt: skip
def test_a_malformed_camera_json_is_named(tmp_path, capsys, text, pattern):
    capture(tmp_path / "in", "pppppp")
    (tmp_path / "in" / "clip.camera.json").write_text(text)
    out = tmp_path / "frames.h5"
    fails(capsys, prepare_args(tmp_path / "in", out), r"clip\.camera\.json: " + pattern)
    nothing_written(out)


def peoplesnapshot(root, camera: dict | None = None) -> dict:
    """The capture in People Snapshot's layout (``root/clip/``), its camera.pkl replaced by ``camera``."""
    from delta.data.peoplesnapshot import write_layout
    from delta.data.sources import default_camera

    capture(root / "raw", "pppppp")
    with h5py.File(root / "raw" / "matte.h5") as m, h5py.File(root / "raw" / "keypoints.h5") as k:
        write_layout(root / "clip", "clip", root / "raw" / "clip.mp4", default_camera(W, H), list(m["person"][:] // 255),
                     k["keypoints"][:])  # fmt: skip
    if camera is not None:
        (root / "clip" / "camera.pkl").write_bytes(pickle.dumps(camera, protocol=2))
    return {"train": [0, 3, 1], "test": [4, 5, 1]}


GOOD_PKL = {"camera_f": np.array([50.0, 50.0]), "camera_c": np.array([32.0, 24.0]), "camera_k": np.zeros(5),
            "camera_rt": np.zeros(3), "camera_t": np.zeros(3), "width": W, "height": H}  # fmt: skip


@pytest.mark.parametrize("change, pattern", [
    ({"camera_f": np.zeros(2)}, r"camera K has focal lengths fx = 0, fy = 0; both must be > 0"),
    ({"camera_rt": np.array([0.0, np.nan, 0.0])}, r"camera key 'camera_rt' is not finite: \[0\.0, nan, 0\.0\]"),
    ({"camera_k": np.array([0.1, np.inf])}, r"camera key 'camera_k' is not finite"),
    ({"camera_f": "fifty"}, r"camera key 'camera_f' must hold numbers, found 'fifty'"),
    ({"camera_c": np.zeros(3)}, r"camera key 'camera_c' holds 3 values, expected 2"),
    ({"width": 0}, r"camera key 'width' must be a whole number of pixels > 0, found 0"),
], ids=["zero focal", "NaN rotation", "inf distortion", "string", "3 values", "width 0"])  # fmt: skip
def test_a_bad_peoplesnapshot_camera_stops_prepare(tmp_path, capsys, change, pattern):
    config = peoplesnapshot(tmp_path, {**GOOD_PKL, **change})
    out = tmp_path / "frames.h5"
    fails(capsys, prepare_args(tmp_path, out, {}, "peoplesnapshot", config), r"clip/camera\.pkl: " + pattern)
    nothing_written(out)


def test_the_peoplesnapshot_layout_with_a_good_camera_prepares(tmp_path, capsys):
    config = peoplesnapshot(tmp_path, GOOD_PKL)
    assert main(prepare_args(tmp_path, tmp_path / "frames.h5", {}, "peoplesnapshot", config)) == 0


# -------------------------------------------------------------------------------------------------- masks
@pytest.mark.parametrize("shape, pattern", [
    ((N, H, W, 3), r"matte\.h5: 'person' has shape \(6, 48, 64, 3\), expected \(N >= 6, 48, 64\): one 64x48 mask a "
                   r"frame of clip\.mp4"),
    ((N, H, W - 4), r"matte\.h5: 'person' has shape \(6, 48, 60\), expected \(N >= 6, 48, 64\)"),
    ((N, W, H), r"matte\.h5: 'person' has shape \(6, 64, 48\), expected \(N >= 6, 48, 64\)"),
    ((N - 2, H, W), r"matte\.h5: 'person' has shape \(4, 48, 64\), expected \(N >= 6, 48, 64\)"),
], ids=["3 channels", "narrower", "transposed", "too few frames"])  # fmt: skip
def test_masks_of_the_wrong_shape_stop_prepare(tmp_path, capsys, shape, pattern):
    steps = capture(tmp_path / "in", "pppppp")
    write_steps(tmp_path / "in", np.full(shape, 255, np.uint8), read(steps["keypoints"], "keypoints"))
    out = tmp_path / "frames.h5"
    fails(capsys, prepare_args(tmp_path / "in", out), pattern)
    nothing_written(out)


def test_peoplesnapshot_masks_with_channels_stop_prepare(tmp_path, capsys):
    config = peoplesnapshot(tmp_path)
    with h5py.File(tmp_path / "clip" / "masks.hdf5", "w") as f:
        f["masks"] = np.ones((N, H, W, 3), np.uint8)
    out = tmp_path / "frames.h5"
    fails(
        capsys,
        prepare_args(tmp_path, out, {}, "peoplesnapshot", config),
        r"clip/masks\.hdf5: 'masks' has shape \(6, 48, 64, 3\), expected \(N, 48, 64\)",
    )
    nothing_written(out)


def test_keypoints_of_the_wrong_shape_stop_prepare(tmp_path, capsys):
    steps = capture(tmp_path / "in", "pppppp")
    write_steps(tmp_path / "in", read(steps["matte"], "person"), np.zeros((N, 17, 3), np.float32))
    out = tmp_path / "frames.h5"
    fails(
        capsys,
        prepare_args(tmp_path / "in", out),
        r"keypoints\.h5: 'keypoints' has shape \(6, 17, 3\), expected \(N >= 6, 18, 3\)",
    )
    nothing_written(out)


def test_masks_with_a_channel_axis_of_one_are_read_as_masks(tmp_path):
    """(N, H, W, 1), as an image library writes a single-channel stack, is the same masks: read squeezed."""
    steps = capture(tmp_path / "in", "pppppp")
    masks, keypoints = read(steps["matte"], "person"), read(steps["keypoints"], "keypoints")
    write_steps(tmp_path / "in", masks[..., None], keypoints)
    assert main(prepare_args(tmp_path / "in", tmp_path / "frames.h5")) == 0
    write_steps(tmp_path / "in", masks, keypoints)
    assert main(prepare_args(tmp_path / "in", tmp_path / "plain.h5")) == 0
    with h5py.File(tmp_path / "frames.h5") as a, h5py.File(tmp_path / "plain.h5") as b:
        np.testing.assert_array_equal(a["person"][:], b["person"][:])


# ---------------------------------------------------------------------------------------------- no person
@pytest.mark.parametrize("video", ["gggggg", "nnnnnn"], ids=["grey", "noise"])
def test_a_video_without_a_person_stops_prepare(tmp_path, capsys, video):
    capture(tmp_path / "in", video)
    out = tmp_path / "out" / "frames.h5"
    fails(capsys, prepare_args(tmp_path / "in", out),
          r"clip\.mp4: no person found: 0 of 6 frames have >= 4 keypoints with confidence >= 0\.3 and a plausible "
          r"person mask \(0 have the keypoints, at most 0 in a frame; 6 have a plausible mask")  # fmt: skip
    nothing_written(out)


def test_speckled_masks_without_keypoints_are_no_person(tmp_path, capsys):
    """Without keypoints the masks decide: scattered specks (a matting model on noise) are nobody."""
    steps = capture(tmp_path / "in", "pppppp")
    speckle = (np.random.default_rng(1).random((N, H, W)) < 0.2).astype(np.uint8) * 255
    with h5py.File(steps["matte"], "r+") as f:
        f["person"][...] = speckle
    out = tmp_path / "frames.h5"
    fails(
        capsys,
        prepare_args(tmp_path / "in", out, {"m": steps["matte"]}),
        r"clip\.mp4: no person found: 0 of 6 frames have a plausible person mask: .* one connected region",
    )
    nothing_written(out)


def record(path, keypoints, masks, K=None) -> None:
    """A frame record as ``delta prepare`` writes it (32 px, pinhole)."""
    n, size = len(keypoints), masks.shape[1]
    with h5py.File(path, "w") as h5:
        h5["images"] = np.zeros((n, size, size, 3), np.uint8)
        h5["person"] = masks
        h5["keypoints"] = keypoints.astype(np.float32)
        h5["frame_ids"] = np.arange(10, 10 + n)
        h5["split"] = np.zeros(n, np.uint8)
        h5.attrs["camera_model"] = "pinhole"
        h5["K"] = np.array([[40.0, 0, 16], [0, 40, 16], [0, 0, 1]]) if K is None else K
        h5["R"], h5["t"] = np.eye(3), np.zeros(3)


def test_a_record_without_a_usable_frame_stops_fit_init(tmp_path, capsys, anny_files):
    """Every frame flagged (no confident keypoint; one with keypoints has an empty mask): no fit, no
    ``residual_px_mean: nan``."""
    keypoints = np.zeros((4, 18, 3))
    keypoints[2, :, :2], keypoints[2, :, 2] = STICK[:, :2] / 2, 0.9
    masks = np.zeros((4, 32, 32), np.uint8)
    masks[[0, 1, 3], 8:24, 10:22] = 255
    record(tmp_path / "frames.h5", keypoints, masks)
    out = tmp_path / "init"
    fails(capsys, fit_args(tmp_path / "frames.h5", anny_files["body"], out),
          r"frames\.h5: no person found: 0 of 4 frames have >= 4 keypoints with confidence >= 0\.3 and a non-empty "
          r"person mask \(1 have the keypoints, at most 18 in a frame; 3 have a non-empty mask\)")  # fmt: skip
    assert not out.exists()


def test_non_finite_fit_results_name_the_frames():
    from delta import DeltaError
    from delta.fitting.fit import FitResult
    from delta.fitting.run import check_result

    F, ids = 4, np.array([3, 5, 7, 9])
    res = FitResult(torch.zeros(2), torch.zeros(F, 4, 3), torch.zeros(F, 3), None, torch.zeros(F, dtype=torch.bool),
                    torch.zeros(F, dtype=torch.bool), torch.zeros(F, dtype=torch.bool), torch.ones(F))  # fmt: skip
    check_result("r.h5", res, ids)
    res.transl[1, 2] = float("nan")
    res.residual_px[3] = float("nan")
    with pytest.raises(DeltaError, match=r"r\.h5: the fit gave a non-finite translation, reprojection residual at "
                                         r"2 of 4 frames \[5, 9\]"):  # fmt: skip
        check_result("r.h5", res, ids)


def test_a_record_with_a_singular_camera_stops_fit_init(tmp_path, capsys, anny_files):
    """A record whose camera cannot image (written before the adapters checked cameras) is not fitted."""
    keypoints = np.zeros((2, 18, 3))
    keypoints[:, :, :2], keypoints[:, :, 2] = STICK[:, :2] / 2, 0.9
    masks = np.full((2, 32, 32), 255, np.uint8)
    record(tmp_path / "frames.h5", keypoints, masks, K=np.zeros((3, 3)))
    out = tmp_path / "init"
    fails(
        capsys,
        fit_args(tmp_path / "frames.h5", anny_files["body"], out),
        r"frames\.h5: camera K has focal lengths fx = 0, fy = 0",
    )
    assert not out.exists()


# ------------------------------------------------------------------------------------------- partly bad
def test_a_partly_bad_capture_is_prepared_and_fitted_with_its_bad_frames_listed(tmp_path, anny_files):
    capture(tmp_path / "in", "pgpnpg")
    out = tmp_path / "frames.h5"
    assert main(prepare_args(tmp_path / "in", out)) == 0
    summary = json.loads(out.with_suffix(".json").read_text())
    assert summary["frames"] == 6 and summary["few_keypoints"] == [1, 3, 5] and summary["skipped_empty"] == []
    settings = json.dumps({"iterations": [5, 5, 5], "sil_size": 16, "facing_starts": 2})
    assert main(["fit-init", "--record", str(out), "--body", anny_files["body"], "--out", str(tmp_path / "init"),
                 "--settings", settings]) == 0  # fmt: skip
    fitted = json.loads((tmp_path / "init" / "summary.json").read_text())
    assert fitted["flagged"] == 3 and fitted["flagged_frames"] == [1, 3, 5]
    assert np.isfinite(fitted["residual_px_mean"])
    with np.load(tmp_path / "init" / "params.npz") as p:
        assert p["flagged"].tolist() == [False, True] * 3 and np.isfinite(p["transl"]).all()
