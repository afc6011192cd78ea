"""What ``delta prepare`` is told: its settings alone, so that the command line is built without torch."""

from __future__ import annotations

import dataclasses
from typing import Optional


@dataclasses.dataclass
class PrepareSettings:
    """How ``delta prepare`` makes a subject's frame record: what the workflow resolves for one job."""

    kind: str = dataclasses.field(default="video", metadata={"choices": ("synthetic", "peoplesnapshot", "video")})
    """Which adapter reads the capture."""
    resolution: int = dataclasses.field(default=512, metadata={"minimum": 32, "maximum": 2048})
    """Side of the square training images."""
    crop_margin: float = dataclasses.field(default=0.08, metadata={"minimum": 0, "maximum": 1})
    """Margin added around the person's box on each side, as a fraction of its side."""
    frames: dict = dataclasses.field(default_factory=dict)
    """The subject's frame ranges, ``{"train": [first, last, step], "test": [...]}`` (video, People Snapshot)."""
    max_frames: dict = dataclasses.field(default_factory=lambda: {"train": 300, "test": 100})
    """A video subject's ranges are each thinned evenly to at most this many frames (0: all)."""
    use_provided: Optional[tuple[str, ...]] = dataclasses.field(
        default=None, metadata={"choices": ("person", "clothing", "skin", "hair", "keypoints", "face_points")}
    )
    """The dataset's own arrays to use (None: all it ships); model steps give the rest."""
    score_size: int = dataclasses.field(default=0, metadata={"minimum": 0, "maximum": 4096})
    """Long side of the whole frames kept for scoring and exports (0: the dataset's protocol: People
    Snapshot's 1080² frames halved to 540², any other capture at its own size up to 1080)."""
