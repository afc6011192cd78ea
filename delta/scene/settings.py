"""What training takes from a scene analysis: its decisions, where the user's config is silent.

Pure and light (no torch): the workflow reads :data:`DECIDED` when it builds a training job's
parameters, so that a config key the scene never decides does not touch a stage it does not
concern.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from delta import DeltaError

#: The keys the analysis decides (dotted paths of the training settings).
DECIDED = (
    "exterior",
    "capture",
    "resolution",
    "render.max_dist",
    "render.samples",
    "render.shell",
    "stage1.rays",
    "stage2.iterations",
    "semantic",
    "weights.semantic",
    "weights.skin_inside",
    "weights.face_points",
    "mouth_shade",
    "nerf.color_cell",
)
#: The paper's head weights (DELTA §Implementation, head videos) where they differ from its body weights
#: (:class:`delta.loss_weights.LossWeights`: semantic 0.0005, skin_inside 0.01); a tracked face takes them,
#: and the term that holds its face points to the detected ones through training (``face_points``: not the
#: paper's; without it the short-haired real head's training moved its face 8.6 px down the frames, its
#: shape drifting while the poses stayed, and the albedo smeared: docs/heads.md).
HEAD_WEIGHTS = {"semantic": 0.015, "skin_inside": 0.001, "face_points": 10.0}
#: The paper's stage-2 semantic loss for a head: the perceptual loss (its body's is ID-MRF), the loss its
#: head weight 0.015 was chosen for (ID-MRF at that weight scored the short-haired talker's held-out
#: frames 0.3-0.6 dB under it, and its stage 2 under its stage 1: docs/heads.md).
HEAD_SEMANTIC = "perceptual"
#: The most memory the training frames may hold (bytes) where the scene decides their size: 400 frames
#: fit up to 579² pixels. The workflow sizes a training job's memory by it.
FRAME_BUDGET = 1 << 30
#: Keys decided as a multiple of the resolved setting: the key -> the scene's factor for it.
SCALED = {"stage2.iterations": "stage2.length_factor"}
#: Keys decided from another decided key: taken only where the user set neither (stage 1's rays spend what
#: the scene's samples a ray leave of a step; a user's own samples keep the preset's rays).
#: The semantic loss and its weight are one decision: a config that sets either keeps its own pair.
#: The colour cell is not decided where the config sets the colour grids' own size.
DEPENDS = {"stage1.rays": ("render.samples",), "semantic": ("weights.semantic",), "weights.semantic": ("semantic",),
           "nerf.color_cell": ("nerf.color_max_res", "nerf.color_levels")}  # fmt: skip
#: Keys decided within what the resolved settings allow: key -> (its floor, its ceiling) among them (the
#: floor also where the ceiling is lower or unset). A run of another preset than the one the scene was
#: analysed for (a sweep's variant) keeps its own rays where that preset allows no more, never fewer.
CAPPED = {"stage1.rays": ("stage1.rays", "stage1.max_rays")}
#: Keys decided only where the resolved settings leave them ``auto``.
AUTO = ("exterior", "capture")
#: Top-level training settings a stage never reads: changing them leaves that stage's work valid (its job's
#: parameters and checkpoint fingerprint hash the rest: :func:`delta.training.presets.stage_view`).
NOT_READ_BY_STAGE = {1: ("stage2", "deformation", "semantic"), 2: ("stage1",)}


def set_keys(overrides: list[dict], prefix: str = "") -> list[str]:
    """The dotted keys a list of overrides sets (a nested dict's leaves; an empty dict is a leaf), sorted."""
    keys = []
    for over in overrides:
        for k, v in over.items():
            keys += set_keys([v], f"{prefix}{k}.") if isinstance(v, dict) and v else [f"{prefix}{k}"]
    return sorted(set(keys))


def user_decided(user_set: list[str], stage: int | None = None) -> list[str]:
    """The config's own keys (``user_set``, dotted) that overrule a scene decision, sorted; with a
    ``stage``, only those that stage reads (another stage's key must not rerun it)."""
    unread = NOT_READ_BY_STAGE.get(stage, ())
    followed = {k for keys in DEPENDS.values() for k in keys}
    return sorted(k for k in set(user_set) if (k in DECIDED or k in followed) and k.split(".")[0] not in unread)


def _get(d: dict, dotted: str):
    for part in dotted.split("."):
        if not isinstance(d, dict) or part not in d:
            return None
        d = d[part]
    return d


def _decided(decisions: dict, resolved: dict, key: str):
    """The scene's value for ``key`` (None: not decided): as written, at most the resolved settings allow
    (:data:`CAPPED`), or the resolved setting times the scene's factor (:data:`SCALED`)."""
    if key in CAPPED:
        value = _get(decisions, key)
        floor, ceiling = (_get(resolved, k) or 0 for k in CAPPED[key])
        return None if value is None else max(min(value, max(floor, ceiling)), floor)
    if key not in SCALED:
        return _get(decisions, key)
    factor, base = _get(decisions, SCALED[key]), _get(resolved, key)
    return None if factor is None or base is None else math.ceil(base * float(factor) - 1e-9)


def scene_settings(scene_path: str | Path, resolved: dict, user_set: list[str]) -> dict:
    """The training settings the scene decides, as an override: every decision of ``scene.json`` whose
    key the user did not set (``user_set``: dotted keys of the config's overrides); :data:`AUTO` keys only
    where ``resolved`` leaves them ``auto``; :data:`SCALED` keys as ``resolved``'s times the scene's factor;
    :data:`DEPENDS` keys only where the user set none of the keys they follow."""
    try:
        decisions = json.loads(Path(scene_path).read_text())["decisions"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise DeltaError(f"{scene_path}: not a scene analysis ({e}); rerun the analyze_scene rule") from None
    out: dict = {}
    for key in DECIDED:
        value = _decided(decisions, resolved, key)
        overruled = key in user_set or any(k in user_set for k in DEPENDS.get(key, ()))
        if value is None or overruled or (key in AUTO and resolved.get(key) != "auto"):
            continue
        *parents, leaf = key.split(".")
        node = out
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return out
