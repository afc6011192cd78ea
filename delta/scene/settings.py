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

#: The keys the analysis decides (dotted paths of the training settings). ``stage2.iterations`` is
#: decided as a multiple of the resolved one (the scene's ``stage2.length_factor``).
DECIDED = ("exterior", "capture", "render.max_dist", "render.samples", "stage2.iterations")


def user_decided(user_set: list[str], stage: int | None = None) -> list[str]:
    """The config's own keys (``user_set``, dotted) that overrule a scene decision, sorted; with a
    ``stage``, only those that stage reads (another stage's key must not rerun it)."""
    other = {1: "stage2.", 2: "stage1."}.get(stage, "\0")
    return sorted(k for k in set(user_set) if k in DECIDED and not k.startswith(other))


def _get(d: dict, dotted: str):
    for part in dotted.split("."):
        if not isinstance(d, dict) or part not in d:
            return None
        d = d[part]
    return d


def scene_settings(scene_path: str | Path, resolved: dict, user_set: list[str]) -> dict:
    """The training settings the scene decides, as an override: every decision of ``scene.json`` whose
    key the user did not set (``user_set``: dotted keys of the config's overrides); ``exterior`` and
    ``capture`` only where ``resolved`` leaves them ``auto``; stage 2's steps as ``resolved``'s times the
    scene's ``stage2.length_factor``."""
    try:
        decisions = json.loads(Path(scene_path).read_text())["decisions"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise DeltaError(f"{scene_path}: not a scene analysis ({e}); rerun the analyze_scene rule") from None
    out: dict = {}
    for key in DECIDED:
        value = _get(decisions, key)
        if key == "stage2.iterations":
            factor, steps = _get(decisions, "stage2.length_factor"), _get(resolved, key)
            value = None if factor is None or steps is None else math.ceil(steps * float(factor) - 1e-9)
        if value is None or key in user_set:
            continue
        if key in ("exterior", "capture") and resolved.get(key) != "auto":
            continue
        *parents, leaf = key.split(".")
        node = out
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return out
