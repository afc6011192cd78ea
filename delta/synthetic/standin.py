"""A synthetic stand-in for People Snapshot, for a user without the licensed dataset.

Each configured People Snapshot subject gets a synthetic subject named ``standin-<subject>``: an
Anny body of the same sex in casual clothes, turning twice in an A-pose in front of a pinhole camera
with lens distortion at the dataset's 1080² (the subjects of People Snapshot turn in an A-pose). The
workflow writes it in People Snapshot's file layout (video, masks.hdf5, camera.pkl, keypoints.hdf5)
and reads it through the same adapter as the real dataset, which takes only what the dataset ships;
its ground truth stays apart, for scoring. Its frame ranges have the real splits' shapes (training
frames, then held-out frames of the later turn), with ``frames`` of their counts, so that a run's
time stays affordable.
"""

from __future__ import annotations

import math

from delta.data import STANDARD_SPLITS

PREFIX = "standin-"
#: How each People Snapshot subject looks, roughly (sex, clothing, hair); other names get the first.
LOOKS: dict[str, dict] = {
    "male-3-casual": {
        "phenotype": {"gender": 0.9, "age": 0.4, "muscle": 0.55, "weight": 0.5, "height": 0.6},
        "skin_color": [0.82, 0.64, 0.54],
        "garments": [{"kind": "tshirt", "pattern": "plain", "colors": [[0.15, 0.16, 0.18], [0.2, 0.2, 0.22]]},
                     {"kind": "trousers", "pattern": "plain", "colors": [[0.22, 0.3, 0.5], [0.25, 0.33, 0.55]]}],
        "hair": "short",
    },
    "male-4-casual": {
        "phenotype": {"gender": 0.85, "age": 0.35, "muscle": 0.5, "weight": 0.45, "height": 0.55},
        "skin_color": [0.78, 0.6, 0.5],
        "garments": [{"kind": "longsleeve", "pattern": "checker", "colors": [[0.6, 0.15, 0.15], [0.2, 0.2, 0.25]]},
                     {"kind": "trousers", "pattern": "plain", "colors": [[0.3, 0.28, 0.24], [0.32, 0.3, 0.26]]}],
        "hair": "short",
    },
    "female-3-casual": {
        "phenotype": {"gender": 0.1, "age": 0.35, "weight": 0.4, "height": 0.45},
        "skin_color": [0.86, 0.7, 0.6],
        "garments": [{"kind": "tshirt", "pattern": "stripes", "colors": [[0.9, 0.88, 0.82], [0.2, 0.3, 0.6]]},
                     {"kind": "trousers", "pattern": "plain", "colors": [[0.12, 0.14, 0.2], [0.14, 0.16, 0.22]]}],
        "hair": "long",
        "hair_color": [0.3, 0.18, 0.1],
    },
    "female-4-casual": {
        "phenotype": {"gender": 0.15, "age": 0.3, "weight": 0.45, "height": 0.5},
        "skin_color": [0.8, 0.6, 0.5],
        "garments": [{"kind": "longsleeve", "pattern": "dots", "colors": [[0.25, 0.45, 0.3], [0.9, 0.9, 0.8]]},
                     {"kind": "shorts", "pattern": "plain", "colors": [[0.2, 0.25, 0.45], [0.22, 0.27, 0.47]]}],
        "hair": "long",
    },
}  # fmt: skip
#: The splits of a subject People Snapshot has no standard split for (male-3-casual's).
DEFAULT_SPLIT = STANDARD_SPLITS["male-3-casual"]


def _count(r: list[int]) -> int:
    return len(range(r[0], r[1] + 1, r[2]))


def standin(subject: str, resolution: int = 1080, frames: float = 0.25, seed: int = 0) -> tuple[str, dict, dict]:
    """(name, synthetic subject spec, frame ranges) of the stand-in of a People Snapshot subject.

    ``frames`` scales the real splits' frame counts, rounded up (at least 3 training and 2 held-out frames).
    """
    split = STANDARD_SPLITS.get(subject, DEFAULT_SPLIT)
    n_train = max(3, math.ceil(frames * _count(split["train"])))
    n_test = max(2, math.ceil(frames * _count(split["test"])))
    look = LOOKS.get(subject, LOOKS["male-3-casual"])
    spec = {
        **look,
        "seed": 100 + seed + sorted(LOOKS).index(subject) if subject in LOOKS else 100 + seed,
        "camera": "pinhole",
        "distortion": [-0.03, 0.01, 0.0, 0.0, 0.0],
        "resolution": resolution,
        "turn_frames": n_train + n_test,
        "novel_frames": 0,
        "turns": 2.0,
        "test_view_every": n_train + n_test,
    }
    ranges = {"train": [0, n_train - 1, 1], "test": [n_train, n_train + n_test - 1, 1]}
    return PREFIX + subject, spec, ranges
