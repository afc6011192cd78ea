"""``benchmarks/pose_registration.py``'s measures against rotations made by hand: a constant offset and a
known turn per frame about the vertical are told apart, and a model's poses moved from the fit by a known
angle read that angle."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "pose_registration.py"
_SPEC = importlib.util.spec_from_file_location("pose_registration", _PATH)
pose_registration = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(pose_registration)


def _poses(root: Rotation, joints: int = 4) -> np.ndarray:
    out = np.zeros((len(root), joints, 3))
    out[:, 0] = root.as_rotvec()
    return out


def test_a_constant_offset_and_a_turn_about_the_vertical_are_told_apart():
    rng = np.random.default_rng(0)
    heading = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    truth = Rotation.from_euler("y", heading[:, None]) * Rotation.from_rotvec(rng.normal(0, 0.05, (40, 3)))
    wander = np.radians(1.5) * np.sin(2 * heading)  # the fit's turn about the vertical, frame by frame
    offset = Rotation.from_rotvec([0.0, 0.0, np.radians(0.4)])
    fit = offset * Rotation.from_euler("y", wander[:, None]) * truth
    got = pose_registration.root_deviation(_poses(fit), _poses(truth))
    assert got["root_offset_deg"] == pytest.approx(0.4, abs=0.02)
    assert got["root_dev_yaw_std_deg"] == pytest.approx(np.degrees(wander).std(), rel=0.02)
    assert got["root_dev_tilt_std_deg"] < 0.05
    same = pose_registration.root_deviation(_poses(offset * truth), _poses(truth))
    assert same["root_dev_mean_deg"] < 1e-6 and same["root_offset_deg"] == pytest.approx(0.4, abs=1e-6)


def test_poses_moved_by_a_known_angle_read_it():
    start = np.random.default_rng(1).normal(0, 0.3, (10, 5, 3))
    turned = (Rotation.from_rotvec([np.radians(2.0), 0, 0]) * Rotation.from_rotvec(start.reshape(-1, 3))).as_rotvec()
    got = pose_registration.moved(turned.reshape(start.shape), start)
    assert got["root_moved_deg"] == pytest.approx(2.0, abs=1e-6)
    assert got["joints_moved_deg"] == pytest.approx(2.0, abs=1e-6)
    assert pose_registration.moved(start, start) == {"root_moved_deg": 0.0, "joints_moved_deg": 0.0}
