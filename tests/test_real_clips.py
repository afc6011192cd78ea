"""The real path on real footage: ``../shared/real/dress_dance.mp4`` (a dancer in a white studio, a static,
level camera; see that folder's README) through the model steps, the record and the init fit, with the
shipped offline models. Skipped where the folder is absent (a clean clone elsewhere, CI)."""

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

from delta.cli import main
from delta.data.video import probe_video

REAL = Path(os.environ.get("DELTA_REAL_CLIPS", Path(__file__).resolve().parents[2] / "shared" / "real"))
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
    # one dancer, sharp: nothing dropped, nobody removed; in frame 101 her raised hand leaves the picture on
    # the right (checked by eye), the only frame of these that the person runs off
    assert summary["frames"] == 14 and summary["few_keypoints"] == [] and summary["implausible_mask"] == []
    assert summary["blurred"] == [] and summary["other_people"] == []
    assert summary["cut_by_edge"] == {"frames": [101], "edges": {"right": 1}}
    out = tmp_path / "init"
    assert main(["fit-init", "--record", str(record), "--body", anny_files["body"], "--out", str(out)]) == 0
    fit = json.loads((out / "summary.json").read_text())
    assert fit["flagged"] == 0 and fit["residual_px_mean"] < 12.0
    # a level camera: the dancer stands along its vertical (measured 2.2° on all 101 frames)
    assert fit["upright"]["tilt_from_camera_vertical_deg"] < 6.0
    with np.load(out / "params.npz") as p:
        up = p["up"]
    assert math.degrees(math.acos(-float(up[1]))) < 6.0  # the camera's y points down
