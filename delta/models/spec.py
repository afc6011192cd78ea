"""What an avatar is made of: its fields, scales, capture and renderer (torch-free: the workflow resolves
presets from it before any job starts)."""

from __future__ import annotations

import dataclasses
import math
from typing import Optional, Union

from delta import DeltaError
from delta.fields.spec import FieldSpec
from delta.render.settings import RenderSettings


@dataclasses.dataclass
class AvatarSpec:
    """Architecture of the avatar (a preset fills it)."""

    nerf: Optional[FieldSpec]
    """The exterior field; None: the capture has no exterior, no NeRF is built."""
    offsets: FieldSpec
    albedo: FieldSpec
    deformation: Optional[FieldSpec] = None
    """F_e; None in stage 1."""
    offset_scale: float = 0.04
    """Largest offset (m)."""
    mouth_shade: Union[float, tuple[float, float, float]] = 1.0
    """The albedo of the mouth's inside starts at this fraction of the skin colour, one for all three channels
    or one each (red, green, blue; 1: the skin colour; :func:`delta.models.avatar.mouth_prior`)."""
    nerf_margin: float = 0.3
    """The NeRF's box: the canonical template's box plus this margin (m)."""
    deformation_scale: float = 0.05
    time_freqs: int = 0
    """F_e also reads the frame's time (``time_features`` with this many frequencies; 0: pose only)."""
    pose_knots: int = 0
    """Knots of the smooth-in-time heading and placement correction (``Trajectory``); 0: none."""
    render: RenderSettings = dataclasses.field(default_factory=RenderSettings)
    capture: str = "full"
    """``full`` or ``upper``: the lower body is left out of backward skinning and the NeRF's box."""
    frozen_joints: tuple[int, ...] = ()
    """Joints whose pose is not optimised (their gradient is zeroed)."""
    clothing_off_head: bool = False
    """The clothing layer holds no density at the points the head's vertices carry (backward skinning's
    nearest vertex; a capture whose clothing never covers the head): a collar is carried by the neck and
    chest, not the chin (:meth:`delta.fields.networks.LayeredNeRF.with_layers`). Only with a ``clothing``
    layer."""
    layers: tuple[str, ...] = ()
    """The exterior's layers, each its own NeRF (``clothing``, ``hair``: :class:`LayeredNeRF`); empty:
    one NeRF for the whole exterior."""


def shade_value(value, where: str = "training.mouth_shade") -> Union[float, tuple[float, float, float]]:
    """A mouth shade as the spec holds it: a number, or three (red, green, blue), each in [0, 1]."""
    many = isinstance(value, (list, tuple))
    values = list(value) if many else [value]
    if (many and len(values) != 3) or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and 0 <= v <= 1 for v in values
    ):
        raise DeltaError(f"{where}: {value!r} (expected a number in [0, 1], or three: red, green, blue)")
    return tuple(float(v) for v in values) if many else float(value)
