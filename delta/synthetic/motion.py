"""Motion like People Snapshot: a turn in A-pose, then a segment of unseen poses.

Poses are axis-angle (F, J, 3) in the body model's world-aligned joint axes
(y up, the subject faces +z at zero global rotation). Anny's rest is an A-pose.
"""

from __future__ import annotations

import numpy as np

#: key poses of the novel-pose segment: joint name -> axis-angle (left = +x side; +x about the x axis bends
#: forward, +y about the y axis turns to the subject's left). Besides everyday poses, the large motions
#: an animated avatar meets: arms overhead, arms crossed over the chest, a deep forward bend, a head turn.
_KEY_POSES = [
    {"upperarm01.L": (0, 0, 0.9), "upperarm01.R": (0, 0, -0.9)},  # arms raised sideways
    {"upperleg01.L": (-0.5, 0, 0), "lowerleg01.L": (0.8, 0, 0), "upperarm01.R": (-0.6, 0, 0)},  # stepping
    {"lowerarm01.L": (0, -1.2, 0), "lowerarm01.R": (0, 1.2, 0), "spine02": (0, 0.35, 0)},  # bent elbows, twist
    {"upperarm01.L": (0, 0, 2.3), "upperarm01.R": (0, 0, -2.3), "lowerarm01.L": (0, 0, 0.3),
     "lowerarm01.R": (0, 0, -0.3)},  # arms overhead
    {"upperarm01.L": (-1.0, 0, -0.9), "lowerarm01.L": (0, -2.3, 0), "upperarm01.R": (-1.0, 0, 0.9),
     "lowerarm01.R": (0, 2.3, 0)},  # arms crossed over the chest
    {"spine05": (0.35, 0, 0), "spine04": (0.35, 0, 0), "spine03": (0.3, 0, 0), "spine02": (0.25, 0, 0),
     "neck01": (-0.3, 0, 0), "upperarm01.L": (0.6, 0, 0), "upperarm01.R": (0.6, 0, 0)},  # a deep forward bend
    {"neck01": (0, 0.45, 0), "neck02": (0, 0.4, 0), "head": (0.1, 0.4, 0)},  # the head turned to the left
    {"upperleg01.R": (-0.6, 0, 0.15), "lowerleg01.R": (1.0, 0, 0), "upperarm01.L": (0.5, 0, 0.3)},
    {"upperarm01.L": (0, 0, 1.3), "lowerarm01.L": (0, -0.6, 0), "neck01": (0.2, -0.5, 0), "neck02": (0, -0.4, 0)},  # and right
]  # fmt: skip


def _set(pose: np.ndarray, names: list[str], joint: str, value) -> None:
    if joint in names:
        pose[..., names.index(joint), :] = value


def turn_sequence(names: list[str], frames: int, turns: float, fps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(F, J, 3) poses of a subject turning ``turns`` times in place, and the turn rate (rad/s) per frame."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / fps
    angle = 2 * np.pi * turns * np.arange(frames) / max(frames, 1)
    pose = np.zeros((frames, len(names), 3))
    pose[:, 0, 1] = angle
    phase = rng.uniform(0, 2 * np.pi, size=6)
    breathe = np.sin(2 * np.pi * 0.3 * t + phase[0])
    for side, sign in (("L", 1.0), ("R", -1.0)):
        arm = 0.07 * np.sin(2 * np.pi * 0.4 * t + phase[1] + (0 if sign > 0 else 1.3))
        _set(pose, names, f"upperarm01.{side}", np.stack([0.05 * breathe, 0 * t, sign * arm], -1))
        elbow = 0.1 + 0.06 * np.sin(2 * np.pi * 0.25 * t + phase[2])
        _set(pose, names, f"lowerarm01.{side}", np.stack([0 * t, -sign * elbow, 0 * t], -1))
    _set(pose, names, "spine03", np.stack([0.02 * breathe, 0.04 * np.sin(2 * np.pi * 0.2 * t + phase[3]), 0 * t], -1))
    _set(pose, names, "neck01", np.stack([0.05 * np.sin(2 * np.pi * 0.3 * t + phase[4]),
                                          0.08 * np.sin(2 * np.pi * 0.15 * t + phase[5]), 0 * t], -1))  # fmt: skip
    rate = np.full(frames, 2 * np.pi * turns * fps / max(frames, 1))
    return pose, rate


def novel_sequence(names: list[str], frames: int, seed: int) -> np.ndarray:
    """(F, J, 3) poses interpolated through key poses not seen in the turn, at varied facing angles."""
    if frames == 0:
        return np.zeros((0, len(names), 3))
    rng = np.random.default_rng(seed + 1)
    keys = np.zeros((len(_KEY_POSES), len(names), 3))
    for k, key in enumerate(_KEY_POSES):
        for joint, value in key.items():
            _set(keys[k], names, joint, value)
        keys[k, 0, 1] = rng.uniform(-0.8, 0.8)  # face the camera from different angles
    return through_keys(keys, frames)


def through_keys(keys: np.ndarray, frames: int) -> np.ndarray:
    """(F, ...) values moving through (K, ...) ``keys`` at an even pace, easing in and out of each
    (smoothstep), from the first key to the last."""
    s = np.linspace(0, len(keys) - 1, frames)
    lo = np.floor(s).astype(int).clip(0, len(keys) - 2) if len(keys) > 1 else np.zeros(frames, int)
    w = (s - lo).reshape((-1,) + (1,) * (keys.ndim - 1))
    w = w * w * (3 - 2 * w)
    hi = np.minimum(lo + 1, len(keys) - 1)
    return (1 - w) * keys[lo] + w * keys[hi]


#: the head's share of a head turn, nod or tilt, spread down the neck (Anny's and SMPL-X's neck joints)
_HEAD_CHAIN = (("neck01", 0.3), ("neck02", 0.3), ("head", 0.4), ("neck", 0.5))

#: key head poses of the held-out segment of a ``face`` motion: (yaw, pitch, roll) in rad, +yaw to the
#: subject's left, +pitch down; beyond the training frames' reach (yaw ±0.45, pitch ±0.15, roll ±0.06)
_KEY_HEAD_POSES = [(0.6, -0.3, 0.0), (-0.55, 0.25, 0.1), (0.0, 0.0, 0.3), (0.75, 0.1, -0.15), (-0.2, -0.35, -0.2)]


def _head_pose(pose: np.ndarray, names: list[str], yaw, pitch, roll) -> None:
    for joint, share in _HEAD_CHAIN:
        if joint in names:
            _set(pose, names, joint, share * np.stack([pitch, yaw, roll], -1))


def face_sequence(names: list[str], frames: int, fps: int, seed: int) -> np.ndarray:
    """(F, J, 3) poses of a subject facing the camera who turns, nods and tilts the head as one does
    talking, the shoulders still but for breathing."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / fps
    phase = rng.uniform(0, 2 * np.pi, size=4)
    pose = np.zeros((frames, len(names), 3))
    yaw = 0.45 * np.sin(2 * np.pi * 0.11 * t + phase[0])
    pitch = 0.1 * np.sin(2 * np.pi * 0.23 * t + phase[1]) + 0.05 * np.sin(2 * np.pi * 0.7 * t + phase[2])
    roll = 0.06 * np.sin(2 * np.pi * 0.17 * t + phase[3])
    _head_pose(pose, names, yaw, pitch, roll)
    _set(pose, names, "spine03", np.stack([0.015 * np.sin(2 * np.pi * 0.3 * t), 0 * t, 0 * t], -1))
    return pose


def novel_face_sequence(names: list[str], frames: int, seed: int) -> np.ndarray:
    """(F, J, 3) head poses through key poses the ``face`` motion's training frames never reach."""
    if frames == 0:
        return np.zeros((0, len(names), 3))
    keys = np.asarray(_KEY_HEAD_POSES)
    rng = np.random.default_rng(seed + 1)
    values = through_keys(keys[rng.permutation(len(keys))], frames)
    pose = np.zeros((frames, len(names), 3))
    _head_pose(pose, names, values[:, 0], values[:, 1], values[:, 2])
    return pose
