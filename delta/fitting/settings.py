"""The init fit's settings (torch-free: the workflow validates them before any job starts)."""

from __future__ import annotations

import dataclasses
import math

from delta import DeltaError
from delta.data.person import CONF_THRESHOLD, MIN_KEYPOINTS


@dataclasses.dataclass
class FitConfig:
    iterations: tuple[int, int, int] = (150, 200, 150)
    lr: float = 0.03
    sigma_px: float = 30.0
    """Robust-penalty scale of the keypoint residuals (pixels)."""
    pose_weight: float = 2e-3
    shape_weight: float = 1e-3
    bend_weight: float = 1.0
    limit_weight: float = 100.0
    """Joint-angle limits (limits.py), per squared radian beyond the range."""
    unobserved_weight: float = 10.0
    """Holds at rest, per squared radian, the rotations no keypoint sees (``unobserved_projectors``);
    left free they follow the silhouette's noise (wrists and feet turned 0.3 rad on the synthetic subjects)."""
    smooth_weight: float = 0.05
    accel_weight: float = 0.0
    """Second-order temporal smoothness (``terms.acceleration``) of the pose, translation and orthographic
    camera: a steady turn costs nothing, so frames whose heading the keypoints barely constrain (a
    subject facing the camera under an orthographic one, where width changes with cos θ) follow
    their neighbours' rate."""
    static_weight: float = 0.0
    """Holds the body pose (every joint but the root) of the capture's own sequence near its mean
    (``terms.static_pose``): for a subject who keeps one pose while turning. A novel-pose sequence
    (``sequence`` label other than 0) is never held. A tracked face may hold its torso instead
    (``still_torso``). 0: off (a capture with motion)."""
    static_spread: float = 0.15
    """The hold applies only where the capture's subject keeps one pose: its limbs' extent along the
    torso varies over the frames by at most this many torso lengths (``delta.fitting.hold``; a dancer
    0.48, a turn in place 0.04-0.06). A large value holds every capture."""
    still_torso: float = 0.0
    """A tracked face's torso keeps still where its neck and shoulder keypoints move by at most this many
    shoulder widths (standard deviation over the frames) or are not seen: the fit then gives every frame
    one torso (the root's turn and place, every joint below the neck) and turns only the neck and head
    (``delta.fitting.hold``; the synthetic talkers 0.001, a full body turning 0.49). 0: off (needs
    ``static_weight`` > 0; the workflow's config sets 0.05: docs/fitting.md)."""
    min_keypoints: int = MIN_KEYPOINTS
    conf_threshold: float = CONF_THRESHOLD
    sil_weight: float = 300.0
    """Silhouette term (mean squared coverage error a frame); 0 turns it off. Set for keypoints that scatter
    ``sil_scatter``; a capture whose keypoints scatter more gets more (``delta.fitting.balance``)."""
    sil_scatter: float = 0.001
    """The keypoint scatter ``sil_weight`` is set for, as a fraction of the record's side (0.51 px at 512²: the
    fit's median residual on clean synthetic renders, 0.45 px on tight, 0.50 on loose). Where the fitted
    keypoints' median residual r exceeds it, the last stage is fitted again with the silhouette weighed
    (r / reference)² more (the real dancer: 1.74 px, × 11.5; docs/fitting.md). 0: off."""
    sil_scatter_cap: float = 20.0
    """The most ``sil_scatter`` multiplies the silhouette's weight by."""
    sil_size: int = 64
    """Resolution (pixels a side) the masks and the mesh are compared at."""
    sil_sigma: float = 0.3
    """Softness of the rasterised silhouette (grid pixels², of the supersampled grid). Where several triangles
    lie along the outline their joined coverage reaches outside it: the soft outline stands 0.50 grid px
    outside the hard one at 0.3 (4 px of a 512² crop at 64²) and the fit's body lies that much inside the
    mask; 0.11 at 0.03 fitted tight's body nearer the truth (38 against 43 mm) and scored 1.4 dB lower on its
    held-out views (``benchmarks/silhouette_bias.csv``; docs/fitting.md)."""
    sil_supersample: int = 1
    """Points a pixel side the silhouette is rendered at, then area-averaged like the masks."""
    sil_fill: float = 1.0
    """Weight of mask pixels the body leaves uncovered (skin and, without an exterior mask, everything)."""
    facing_starts: int = 8
    """Stage 1 starts each frame from this many headings (turns about the body's vertical, evenly spaced)
    and keeps the one whose keypoints fit best: one start from the camera-facing pose falls into the
    mirror minimum when the subject faces away. 1: only the camera-facing start."""
    exterior_fill: float = 1.0
    """The same weight on exterior pixels (clothing, hair) when the fit is given their mask: 1 treats them
    as body (tight clothing); near 0 lets the body stay inside them (a dress, long hair)."""
    sil_cell: float = 0.03
    """Vertex-clustering cell (metres) of the coarse silhouette mesh."""
    skin_edge_weight: float = 1.0
    """Weight of the silhouette's grid pixels within one pixel of the visible skin (the person mask less the
    clothing and hair masks), either side of its edge: there the mask shows the body's own outline, which
    under clothing it does not. 1: as any pixel (docs/fitting.md)."""
    forward_start: float = 0.0
    """With > 0, the body-pose stage also runs each frame from its arms, its legs and both swung this far
    forward (radians, ``limits.forward_directions``; 0.4 measured). A frame keeps the pose from rest unless
    that pose hides limb keypoints the detector saw behind the body (``visibility.hidden_seen``: a crossed
    forearm fitted behind the torso) and another start hides fewer; then the fewest, the cheapest of those.
    0 (the default): from rest only; on tight it cost the capture's frames more than it gained
    (docs/fitting.md)."""
    neighbour_reach: int = 1
    """``neighbour_sweeps`` times during the last stage (evenly spaced), a frame that is not held
    (``static_weight``) and costs a fifth more (``fit.KEEP_MARGIN``, at least ``fit.KEEP_FLOOR``) than one of
    the frames up to this many before and after it in its sequence costs on its own frame also starts from
    their poses: every copy, its own among them, is fitted ``neighbour_steps`` steps to its frame alone, and a
    neighbour's replaces the frame's pose where the frame's own copy costs a fifth more; then the joint stage
    goes on. Across a motion a local minimum (an arm folded the wrong way) is seldom every frame's, so a
    neighbour's basin gets a frame out of its own. On tight's novel segment: the fit's objective 86.8 -> 76.8,
    one frame's arms out of a wrong fold (+2 dB), body error 65 -> 55 mm (docs/fitting.md). 0: off."""
    neighbour_sweeps: int = 1
    neighbour_steps: int = 100
    """Steps each copy of a sweep is fitted (its rate falls from the stage's to a tenth of it)."""
    depth_weight: float = 0.3
    """The detector's relative depths (``terms.depth_term`` over ``DEPTH_BONES``), where the record has
    them, against the keypoint term's bound: 1 weighs every bone wholly on the wrong side like every
    keypoint wholly off. They choose the side a limb swings to, which the keypoints and the mask leave
    open; a tie-break needs little weight (0.3 and 1 fit tight alike, docs/fitting.md). 0: off."""
    depth_sigma: float = 0.1
    """Robust-penalty scale of a bone's depth on the wrong side (metres)."""
    depth_margin: float = 0.1
    """A bone's detected depth difference below this (metres) says no side."""
    depth_pair_margin: float = 0.05
    """The same for the bones across the torso (``DEPTH_PAIRS``: hip to hip), which say which way the
    pelvis is turned; they also vote in stage 1's choice of heading, where a face turned away from the
    torso otherwise picks the torso's mirror turn. Beyond 5 cm the detected hips' order is the synthetic
    truth's in every frame of tight and loose (docs/fitting.md)."""


def fit_config(*overrides: dict, where: str = "fitting") -> FitConfig:
    """FitConfig from the defaults with ``overrides`` (dicts of its field names) applied in order.

    Unknown keys and values of the wrong kind raise a DeltaError naming ``where`` and the key.
    """
    fields = {f.name for f in dataclasses.fields(FitConfig)}
    values: dict = {}
    for over in overrides:
        for key, value in (over or {}).items():
            if key not in fields:
                raise DeltaError(f"{where}: unknown key '{key}' (known: {', '.join(sorted(fields))})")
            default = getattr(FitConfig, key)
            if key == "iterations":
                if not (isinstance(value, (list, tuple)) and len(value) == 3
                        and all(isinstance(v, int) and v >= 0 for v in value)):  # fmt: skip
                    raise DeltaError(f"{where}: 'iterations' must be three step counts >= 0, got {value!r}")
                value = tuple(value)
            elif isinstance(default, int) and not isinstance(default, bool):
                if not isinstance(value, int) or isinstance(value, bool):
                    raise DeltaError(f"{where}: '{key}' must be an integer, got {value!r}")
            elif not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
                raise DeltaError(f"{where}: '{key}' must be a finite number, got {value!r}")
            if isinstance(value, (int, float)) and value < 0:
                raise DeltaError(f"{where}: '{key}' must be >= 0, got {value!r}")
            values[key] = value
    return FitConfig(**values)
