"""How the held-out frames are scored: the settings alone, so that the command line is built without torch."""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from delta import DeltaError
from delta.data import SPLITS as _SPLITS

_f = dataclasses.field
#: each split's code in a frame record
SPLITS = {name: code for code, name in enumerate(_SPLITS)}


@dataclasses.dataclass
class EvalSettings:
    """Scoring the trained avatars on their held-out frames (results/{dataset}/{subject}/eval/).

    The config section ``evaluation`` and the options of ``delta evaluate`` are generated from these fields.
    """

    stage: int = _f(default=2, metadata={"minimum": 1, "maximum": 2})
    """Which training stage's model the workflow evaluates and exports."""
    splits: tuple[str, ...] = _f(
        default=("test_view", "test_pose"), metadata={"choices": tuple(SPLITS), "min_items": 1}
    )
    """Which frames are scored (frames of these splits in the record)."""
    max_frames: int = _f(default=0, metadata={"minimum": 0})
    """At most this many frames per split, evenly spaced (0: all)."""
    refine_steps: int = _f(default=150, metadata={"minimum": 0})
    """Test-time refinement of each test frame's pose and camera, model frozen (0: off). 150 steps with the
    rate falling from 2e-3 to 1e-4: against 30 at 5e-4, held-out poses +1.08 dB on tight and +0.68 on loose,
    the long-haired real head's tail +0.70 dB, held-out views −0.14 to +0.24 dB, at 2.5–3× the refinement's
    time (docs/evaluation.md)."""
    report_unrefined: bool = True
    """With refinement on, also score each frame before it (both rows are written)."""
    refine_rays: int = _f(default=4096, metadata={"minimum": 1})
    """Rays a refinement step draws from the test frame."""
    refine_lr: float = _f(default=2e-3, metadata={"exclusive_minimum": 0, "maximum": 1})
    """Learning rate of the test-time refinement."""
    refine_lr_end: float = _f(default=1e-4, metadata={"exclusive_minimum": 0, "maximum": 1})
    """The refinement's rate at its last step, reached geometrically from ``refine_lr`` (equal to it: constant)."""
    refine_tol: float = _f(default=0.0, metadata={"minimum": 0, "maximum": 1})
    """Stop a frame's refinement once its windowed loss falls by less than this fraction (0: always
    ``refine_steps``). The steps taken and the loss before and after are in each refined row."""
    refine_check: int = _f(default=10, metadata={"minimum": 0})
    """Every this many steps (and after the last) the refinement measures its probe loss and keeps the pose of
    the lowest, the given pose included (0: the last step's pose, unchecked). On tight's held-out views the
    unchecked 30 steps ended 0.23 dB apart on a CPU and a GPU, checked 0.04 apart (docs/evaluation.md)."""
    refine_confirm: int = _f(default=65536, metadata={"minimum": 0})
    """With ``refine_check``: the pose the checks kept must also score below the pose as given on an independent
    draw of this many rays, else the frame keeps the pose as given (0: the probe decides alone). A close
    frame's 4096-ray probe can prefer by 0.1 % a pose the whole frame scores 0.6 dB lower (docs/evaluation.md)."""
    refine_sides: bool = False
    """Before the refinement's steps, try each arm and leg with its upper bone, its lower bone or both swung
    to their other side along the view (the same keypoints: one view does not tell them apart, and the steps
    cannot cross from one to the other) and keep a limb so where its render matches the frame clearly better
    (``delta.eval.heldout.choose_sides``). Off by default: on tight it put six thighs right, on loose six of
    its nine swings were wrong, each scoring higher all the same (docs/fitting.md)."""
    supersample: int = _f(default=2, metadata={"minimum": 1, "maximum": 8})
    """Rays a pixel along each axis, averaged: the frames are area-downsampled photographs whose
    edge pixels mix person and background; one centre ray a pixel cannot (tight subject, four
    test views: 1 → 2 → 4 raised PSNR 25.4 → 26.8 → 27.1 dB)."""
    worst: int = _f(default=3, metadata={"minimum": 0, "maximum": 50})
    """Per split, side-by-sides (reference | render | error, whole frames) of this many frames with the
    lowest PSNR (after refinement when it is on), written to eval/worst/ and shown in the report."""
    lpips_alex: Optional[tuple[str, str]] = None
    """Standard LPIPS-Alex: [torchvision's alexnet-owt-7be5be79.pth, the lpips package's weights/v0.1/alex.pth]
    (the user's files); not given: ST-LPIPS only."""
    perceptual_dir: Optional[str] = _f(default=None, metadata={"config": False})
    """Folder of alex_shift_tolerant.pth (ST-LPIPS); None: no perceptual column."""


def pick_frames(split: np.ndarray, names: tuple[str, ...], max_frames: int) -> list[tuple[int, str]]:
    """(frame, split name) of the frames scored: each split's, at most ``max_frames`` evenly spaced (0: all)."""
    out = []
    for name in names:
        if name not in SPLITS:
            raise DeltaError(f"evaluation.splits: unknown split '{name}' (expected one of {sorted(SPLITS)})")
        idx = np.flatnonzero(split == SPLITS[name])
        if max_frames and len(idx) > max_frames:
            idx = idx[np.linspace(0, len(idx) - 1, max_frames).round().astype(int)]
        out += [(int(i), name) for i in idx]
    return out
