"""Captures and frame records: dataset adapters, videos, persons, records (torch-free at this level: the
workflow reads what each dataset kind ships before any job starts)."""

#: a frame record's splits, in the order of their codes (the record's ``split`` column)
SPLITS = ("train", "test_view", "test_pose")

#: what each dataset kind ships, so the DAG runs only the missing steps
PROVIDES = {
    "synthetic": ("person", "clothing", "skin", "hair", "keypoints", "face_points"),
    "peoplesnapshot": ("person", "keypoints"),
    "video": (),
}

#: People Snapshot's novel-view protocol (InstantAvatar, GART, 3DGS-Avatar): [start, end (inclusive), step], 0-based
STANDARD_SPLITS = {
    "male-3-casual": {"train": [0, 455, 4], "test": [456, 675, 4]},
    "male-4-casual": {"train": [0, 659, 6], "test": [660, 872, 6]},
    "female-3-casual": {"train": [0, 445, 4], "test": [446, 647, 4]},
    "female-4-casual": {"train": [0, 335, 4], "test": [335, 523, 4]},
}
