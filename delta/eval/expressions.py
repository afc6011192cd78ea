"""A tracked face's expressions against a synthetic capture's truth.

A talking capture's ``gt/params.npz`` holds the facial-action activations the generator rendered
(``expression`` (F, E), ``expression_names``). An avatar of a tracked face carries its own per frame
(the init fit's, refined by training, and by test-time refinement on held-out frames). Two errors per frame:

- ``expr_mae``: the mean absolute difference of the activations over the truth's actions (an action
  the body model lacks counts as fitted at 0, one the truth lacks as truly 0);
- ``expr_err_mm``: what that difference does to the face: the mean length (mm) of the body model's
  expression displacement ``exprdirs · (e_fit − e_true)`` over the vertices some action moves, on the
  neutral face (no pose, no shape): an error in a barely visible action weighs little, a wrong jaw much.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from delta import DeltaError


@dataclasses.dataclass
class ExpressionTruth:
    """The truth's activations of the scored frames, in the body model's action order."""

    values: dict[int, np.ndarray]
    """Video frame id -> (E,) the truth's activations for the model's actions (0 for those it lacks)."""
    unmodelled: dict[int, np.ndarray]
    """Video frame id -> the truth's activations of the actions the model lacks (counted as fitted at 0)."""


def truth_expressions(params_npz: str | Path, frame_ids, model_names: list[str]) -> ExpressionTruth | None:
    """The truth's activations at ``frame_ids`` for a model whose actions are ``model_names``; None when the
    capture made no expressions (a still face) or the model has none."""
    path = Path(params_npz)
    if not path.is_file():
        raise DeltaError(f"{path}: no such ground-truth parameter file")
    with np.load(path, allow_pickle=False) as p:
        if "expression" not in p.files or not model_names:
            return None
        if "expression_names" not in p.files:
            raise DeltaError(f"{path}: 'expression' without 'expression_names'")
        truth, names = p["expression"], [str(n) for n in p["expression_names"]]
    if truth.ndim != 2 or truth.shape[1] != len(names):
        raise DeltaError(f"{path}: 'expression' is {truth.shape}, expected (frames, {len(names)})")
    column = {n: i for i, n in enumerate(names)}
    shared = [column.get(n, -1) for n in model_names]
    missing = [i for i, n in enumerate(names) if n not in set(model_names)]
    values, unmodelled = {}, {}
    for fid in frame_ids:
        fid = int(fid)
        if not 0 <= fid < len(truth):
            raise DeltaError(f"{path}: no expression for frame {fid} (it holds {len(truth)} frames)")
        row = truth[fid].astype(np.float64)
        values[fid] = np.array([row[c] if c >= 0 else 0.0 for c in shared])
        unmodelled[fid] = row[missing]
    return ExpressionTruth(values, unmodelled)


def face_moved(exprdirs: torch.Tensor) -> torch.Tensor:
    """(V,) bool: the vertices some action moves."""
    return exprdirs.detach().abs().flatten(1).amax(1) > 0


def expression_errors(fitted: torch.Tensor, truth: ExpressionTruth, frame_id: int, exprdirs: torch.Tensor,
                      moved: torch.Tensor) -> dict[str, float]:  # fmt: skip
    """``expr_mae`` and ``expr_err_mm`` of one frame's fitted activations ``fitted`` (E,) against the truth
    (``exprdirs`` (V, 3, E) the body model's, ``moved`` its :func:`face_moved`)."""
    true = truth.values[int(frame_id)]
    fit = fitted.detach().double().cpu().numpy()
    diff = fit - true
    absolute = np.concatenate([np.abs(diff), np.abs(truth.unmodelled[int(frame_id)])])
    displacement = torch.einsum("vce,e->vc", exprdirs[moved].double().cpu(), torch.from_numpy(diff))
    return {"expr_mae": float(absolute.mean()), "expr_err_mm": 1000 * float(displacement.norm(dim=1).mean())}


class AvatarExpressions:
    """Scores an avatar's per-frame expressions against a capture's truth (``params_npz``) at the video
    frames ``frame_ids``: the actions it fits (its body model's first ``E`` for ``E`` fitted columns)."""

    def __init__(self, model, params_npz: str | Path, frame_ids):
        self.model = model
        fitted = model.expression.shape[1]
        self.truth = truth_expressions(params_npz, frame_ids, list(model.body.expression_names)[:fitted])
        self.dirs = model.body.exprdirs[..., :fitted]
        self.moved = face_moved(self.dirs)

    @classmethod
    def of(cls, model, params_npz: str | Path, frame_ids) -> AvatarExpressions | None:
        """None where there is nothing to score: a still face, or a capture that made no expressions."""
        if model.expression is None:
            return None
        scorer = cls(model, params_npz, frame_ids)
        return scorer if scorer.truth is not None else None

    def __call__(self, frame: int, frame_id: int) -> dict[str, float]:
        return expression_errors(self.model.expression[frame], self.truth, frame_id, self.dirs, self.moved)


def train_expression_errors(model, frame_ids, params_npz: str | Path, frames) -> dict[str, float]:
    """``train_expr_mae`` and ``train_expr_err_mm``: the mean errors over the training frames ``frames``
    (model frame indices; ``frame_ids`` the record's video ids) as training left them; empty for a still face."""
    scorer = AvatarExpressions.of(model, params_npz, [int(frame_ids[f]) for f in frames])
    if scorer is None:
        return {}
    rows = [scorer(int(f), int(frame_ids[f])) for f in frames]
    return {f"train_{k}": float(np.mean([r[k] for r in rows])) for k in ("expr_mae", "expr_err_mm")}
