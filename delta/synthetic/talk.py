"""A face that talks: per-frame facial-action activations (ARKit names, Anny's facial actions).

The training segment talks: the jaw opens and closes with syllables (~4 a second) grouped into
words and pauses, the lips round now and then, smiles and brows drift slowly, the eyes blink
every few seconds. The held-out segment moves through expressions the talk never makes (a puffed
cheek, a frown, a wide-eyed surprise, the tongue out, the mouth pulled aside): what a head avatar
must do for expressions it has not seen.
"""

from __future__ import annotations

import numpy as np

from delta.synthetic.motion import through_keys

#: key expressions of the held-out segment; every action here but the jaw is absent from the talk
_KEY_EXPRESSIONS = [
    {"mouthSmileLeft": 0.95, "mouthSmileRight": 0.95, "cheekSquintLeft": 0.7, "cheekSquintRight": 0.7,
     "eyeSquintLeft": 0.4, "eyeSquintRight": 0.4},  # a broad smile
    {"browInnerUp": 0.9, "browOuterUpLeft": 0.8, "browOuterUpRight": 0.8, "eyeWideLeft": 0.8, "eyeWideRight": 0.8,
     "jawOpen": 0.6},  # surprise
    {"cheekPuff": 0.9, "mouthClose": 0.3},  # puffed cheeks
    {"mouthFrownLeft": 0.8, "mouthFrownRight": 0.8, "browDownLeft": 0.7, "browDownRight": 0.7,
     "noseSneerLeft": 0.5, "noseSneerRight": 0.5},  # a frown
    {"jawOpen": 0.5, "tongueOut": 0.8},  # the tongue out
    {"mouthLeft": 0.8, "eyeSquintLeft": 0.6, "jawLeft": 0.4},  # the mouth pulled aside
    {"mouthPucker": 1.0, "mouthRollLower": 0.3},  # a kiss
]  # fmt: skip

#: actions the talk drives: the jaw and lips with syllables, slow smiles and brows, blinks
TALK_ACTIONS = ("jawOpen", "mouthFunnel", "mouthPucker", "mouthSmileLeft", "mouthSmileRight", "mouthLowerDownLeft",
                "mouthLowerDownRight", "mouthUpperUpLeft", "mouthUpperUpRight", "browInnerUp", "eyeBlinkLeft",
                "eyeBlinkRight", "mouthClose")  # fmt: skip


def _set(out: np.ndarray, names: list[str], action: str, values) -> None:
    if action in names:
        out[:, names.index(action)] = values


def talk_sequence(names: list[str], frames: int, fps: int, seed: int) -> np.ndarray:
    """(F, E) activations in [0, 1] of a face talking (see the module docstring)."""
    out = np.zeros((frames, len(names)))
    if frames == 0:
        return out
    rng = np.random.default_rng(seed + 11)
    t = np.arange(frames) / fps
    end = t[-1] + 1.0
    # words: ~1.2 s of syllables, then a pause of ~0.4 s
    speaking = np.zeros(frames, bool)
    start = 0.0
    while start < end:
        length, pause = rng.uniform(0.6, 1.8), rng.uniform(0.2, 0.7)
        speaking |= (t >= start) & (t < start + length)
        start += length + pause
    rate = rng.uniform(3.5, 4.5)
    syllable = np.clip(np.sin(2 * np.pi * rate * t + rng.uniform(0, 2 * np.pi)), 0, None)
    loud = 0.25 + 0.2 * np.clip(np.sin(2 * np.pi * 0.31 * t + rng.uniform(0, 6)), 0, None)
    jaw = np.where(speaking, loud * syllable, 0.0)
    _set(out, names, "jawOpen", jaw)
    _set(out, names, "mouthLowerDownLeft", 0.6 * jaw)
    _set(out, names, "mouthLowerDownRight", 0.6 * jaw)
    rounding = np.clip(np.sin(2 * np.pi * 0.9 * t + rng.uniform(0, 6)), 0, None) ** 3 * speaking
    _set(out, names, "mouthFunnel", 0.5 * rounding)
    _set(out, names, "mouthPucker", 0.3 * rounding)
    _set(out, names, "mouthClose", 0.15 * (1 - speaking))
    smile = 0.3 * np.clip(np.sin(2 * np.pi * 0.07 * t + rng.uniform(0, 6)), 0, None)
    _set(out, names, "mouthSmileLeft", smile)
    _set(out, names, "mouthSmileRight", 0.9 * smile)
    _set(out, names, "mouthUpperUpLeft", 0.2 * jaw)
    _set(out, names, "mouthUpperUpRight", 0.2 * jaw)
    _set(out, names, "browInnerUp", 0.35 * np.clip(np.sin(2 * np.pi * 0.13 * t + rng.uniform(0, 6)), 0, None))
    blink = np.zeros(frames)
    moment = rng.uniform(0.5, 2.0)
    while moment < end:
        blink = np.maximum(blink, np.clip(1.5 - np.abs(t - moment) / 0.06, 0, 1))  # shut for 60 ms
        moment += rng.uniform(2.0, 4.5)
    _set(out, names, "eyeBlinkLeft", blink)
    _set(out, names, "eyeBlinkRight", blink)
    return np.clip(out, 0.0, 1.0)


def novel_expressions(names: list[str], frames: int, seed: int) -> np.ndarray:
    """(F, E) activations through the held-out key expressions, from and back to a neutral face."""
    if frames == 0:
        return np.zeros((0, len(names)))
    rng = np.random.default_rng(seed + 12)
    keys = np.zeros((len(_KEY_EXPRESSIONS), len(names)))
    for k, key in enumerate(_KEY_EXPRESSIONS):
        for action, value in key.items():
            if action in names:
                keys[k, names.index(action)] = value
    keys = keys[rng.permutation(len(keys))]
    # neutral between key expressions: each expression is reached and released
    path = np.concatenate([np.stack([np.zeros(len(names)), key]) for key in keys] + [np.zeros((1, len(names)))])
    return through_keys(path, frames)
