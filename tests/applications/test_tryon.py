"""Try-on: the exterior laid over the frame by its opacity, and ``delta try-on`` on a fitted frame end to end."""

import json

import cv2
import numpy as np
import pytest
import torch

from delta.applications.tryon import composite
from delta.cli import main
from delta.data.frames import load_full_frames
from delta.export.video import to_bgr


def test_the_frame_shows_where_the_exterior_is_transparent():
    g = torch.Generator().manual_seed(0)
    photo, nerf = torch.rand(6, 5, 3, generator=g), torch.rand(6, 5, 3, generator=g)
    alpha = torch.zeros(6, 5)
    alpha[2:4, 1:3] = 1.0
    alpha[5, 4] = 0.25
    out = composite(photo, {"nerf_mask": alpha, "nerf": nerf})
    assert torch.equal(out[alpha == 0], photo[alpha == 0])
    assert torch.equal(out[alpha == 1], nerf[alpha == 1])
    torch.testing.assert_close(out[5, 4], 0.25 * nerf[5, 4] + 0.75 * photo[5, 4])


@pytest.mark.slow
def test_the_try_on_command_dresses_a_fitted_frame(tiny_trained, tiny_training, tmp_path):
    tight, loose = tiny_training["tight"], tiny_trained["loose"]
    out = tmp_path / "tryon"
    code = main(["try-on", "--record", tight["record"], "--init", tight["init"], "--body", tight["body"], "--frame", "1",
                 "--wearer-model", loose["model"], "--wearer-record", loose["record"], "--out", str(out),
                 "--turntable-frames", "2"])  # fmt: skip
    assert code == 0
    about = json.loads((out / "tryon.json").read_text())
    assert about["frame"] == 1 and 0 <= about["covered"] <= 1 and about["turntable_frames"] == 2
    full = load_full_frames(tight["record"], [1])
    W, H = full.size
    image = cv2.imread(str(out / "tryon.png"))
    assert image.shape == (H, 3 * W, 3)
    np.testing.assert_array_equal(image[:, :W], to_bgr(full.images[0]))  # the frame itself, first
    assert main(["try-on", "--record", tight["record"], "--init", tight["init"], "--body", tight["body"],
                 "--frame", "999", "--wearer-model", loose["model"], "--wearer-record", loose["record"],
                 "--out", str(tmp_path / "x")]) == 2  # fmt: skip
