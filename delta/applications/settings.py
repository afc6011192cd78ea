"""How a trained avatar is driven by a motion (config group ``applications.animate.settings``)."""

from __future__ import annotations

import dataclasses

from delta.settings import check

_f = dataclasses.field


@dataclasses.dataclass
class AnimateSettings:
    """An avatar driven by another motion (results/{dataset}/{subject}/animate/{motion}/).

    The config section ``applications.animate.settings`` and the options of ``delta animate`` are
    generated from these fields.
    """

    fps: float = _f(default=12.0, metadata={"exclusive_minimum": 0})
    """Frame rate of the video: the motion is sampled at this rate (never faster than its own)."""
    max_frames: int = _f(default=48, metadata={"minimum": 0})
    """At most this many frames of the motion, from its start (0: all of it)."""
    anchor: int = _f(default=-1, metadata={"minimum": -1})
    """The capture's frame (a row of its record) whose camera, place and heading the motion starts from
    (-1: the first training frame)."""
    meshes: bool = False
    """Also write the posed body and clothing meshes of every frame (meshes/body_00000.ply, ...)."""

    def __post_init__(self) -> None:
        check(self, "applications.animate.settings")


@dataclasses.dataclass
class ShowSettings:
    """How an edited avatar is shown: dressed in another's exterior (results/{dataset}/{subject}/dress/{exterior}/)
    or reshaped (results/{dataset}/{subject}/reshape/{shape}/).

    The config sections ``applications.dress.settings`` and ``applications.reshape.settings`` and the options
    of ``delta dress`` and ``delta reshape`` are generated from these fields.
    """

    turntable_frames: int = _f(default=12, metadata={"minimum": 2, "maximum": 720})
    """Frames of the edited avatar's turntable (one full turn)."""
    fps: int = _f(default=12, metadata={"minimum": 1, "maximum": 120})
    """Frame rate of the turntable."""
    score_frames: int = _f(default=5, metadata={"minimum": 0, "maximum": 1000})
    """Test frames scored against the generated truth of the edit, where the subject is synthetic (0: none)."""
    supersample: int = _f(default=2, metadata={"minimum": 1, "maximum": 8})
    """Rays a pixel along each axis when scoring (as evaluation's)."""

    def __post_init__(self) -> None:
        check(self, "applications.dress/reshape.settings")
