"""Entry point of ``delta reshape``: a trained avatar with its body's shape changed, wearing its own exterior.

A shape edit names what to change: Anny's phenotype labels (``weight``, ``height``, ``age``, ``muscle``,
``gender``, ``proportions``: values in [0, 1]) and/or single shape coefficients (``beta0``, ``beta1``, …:
the value β_k takes, in standard deviations; the only kind of edit an SMPL-X body model has). A number
sets the label or coefficient; a signed string ("+0.3", "-0.2") changes it by that much.

A phenotype edit is made where the avatar's shape is: the avatar's phenotype is estimated from its
fitted β (the phenotype p̂ whose β(p̂) is nearest, :func:`estimate_phenotype`), the edit sets (or
changes) the named labels of p̂ (p'), and the avatar takes β + β(p') − β(p̂): the part of its shape
that no phenotype explains is kept. A set value is only as right as p̂, i.e. as the fitted shape; a
change is not (benchmarks/applications.csv measures both). The exterior follows the new shape by the body's own skinning
(:mod:`delta.applications.dress` says how); offsets and albedo stay as learned.
"""

from __future__ import annotations

import json
import logging
import re
import time
from pathlib import Path

import torch

from delta import DeltaError
from delta.applications.settings import ShowSettings
from delta.applications.show import show_edit
from delta.export.meshes import body_mesh, write_mesh
from delta.io import require_files, save_json
from delta.optim import Adam
from delta.synthetic.spec import edit_amount
from delta.training.run import load_trained

log = logging.getLogger(__name__)
BETA = re.compile(r"^beta(\d+)$")


def phenotype_betas_of(space, anny_model, values: torch.Tensor, num_shape: int) -> torch.Tensor:
    """(S,) β of phenotype ``values`` (P,) in [0, 1] (differentiable in ``values``)."""
    from delta.body.anny_convert import anny_rest, project_shape

    rest = anny_rest(anny_model, values[None].double())
    return project_shape(space, rest["rest_vertices"], rest["rest_bone_heads"])[0, :num_shape]


def estimate_phenotype(space, anny_model, betas: torch.Tensor, steps: int = 150) -> torch.Tensor:
    """(P,) the phenotype in (0, 1) whose β is nearest ``betas`` (S,) (Adam on the logits, from 0.5 each)."""
    target = betas.detach().double()
    logits = torch.zeros(len(space.phenotype_labels), dtype=torch.float64, requires_grad=True)
    opt = Adam([logits], lr=0.1)
    for _ in range(steps):
        opt.zero_grad()
        loss = (phenotype_betas_of(space, anny_model, torch.sigmoid(logits), len(target)) - target).square().sum()
        loss.backward()
        opt.step()
    return torch.sigmoid(logits).detach()


def split_edit(edit: dict, labels: list[str] | None, num_shape: int) -> tuple[dict, dict]:
    """(phenotype label -> (relative, amount), β index -> (relative, amount)) of a shape edit: a number sets
    the label or coefficient, a signed string ("+0.3") changes it; errors name the key at fault."""
    phen, betas = {}, {}
    for key, raw in edit.items():
        relative, value = edit_amount(key, raw)
        m = BETA.match(key)
        if m:
            k = int(m.group(1))
            if k >= num_shape:
                raise DeltaError(
                    f"shape edit '{key}': the body model has {num_shape} shape coefficients (beta0..beta{num_shape - 1})"
                )
            betas[k] = (relative, value)
        elif labels is None:
            raise DeltaError(f"shape edit '{key}': phenotype labels need Anny's shape space; this body model takes "
                             f"beta0..beta{num_shape - 1} only")  # fmt: skip
        elif key not in labels:
            raise DeltaError(f"shape edit '{key}': unknown label; known: {labels} and beta0..beta{num_shape - 1}")
        elif not (-1.0 if relative else 0.0) <= value <= 1.0:
            raise DeltaError(f"shape edit '{key}': {raw!r} is outside Anny's phenotype range [0, 1]")
        else:
            phen[key] = (relative, value)
    if not edit:
        raise DeltaError("the shape edit is empty: name phenotype labels or betaK coefficients to change")
    return phen, betas


def edit_betas(betas: torch.Tensor, edit: dict[str, float], space=None, anny_model=None) -> tuple[torch.Tensor, dict]:
    """The edited β (S,) and what was done (the estimated and the edited phenotype, when labels were named)."""
    labels = list(space.phenotype_labels) if space is not None else None
    phen, coeffs = split_edit(edit, labels, len(betas))
    new = betas.detach().clone().double()
    about: dict = {}
    if phen:
        estimated = estimate_phenotype(space, anny_model, new)
        target = estimated.clone()
        for key, (relative, value) in phen.items():
            i = labels.index(key)
            target[i] = min(max(float(target[i]) + value, 0.0), 1.0) if relative else value
        with torch.no_grad():
            new = new + phenotype_betas_of(space, anny_model, target, len(new)) - phenotype_betas_of(
                space, anny_model, estimated, len(new))  # fmt: skip
        about = {"estimated": dict(zip(labels, estimated.round(decimals=3).tolist())),
                 "edited": dict(zip(labels, target.round(decimals=3).tolist()))}  # fmt: skip
    for k, (relative, value) in coeffs.items():
        new[k] = new[k] + value if relative else value
    return new.to(betas.dtype), about


def reshape_avatar(model_path: str | Path, record: str | Path, body_path: str | Path, edit: dict[str, float],
                   out_dir: str | Path, shape_space: str | Path | None = None, anny_cache: str | Path | None = None,
                   settings: ShowSettings | None = None, truth: str | Path | None = None,
                   perceptual_dir: str | None = None, clothing: str | Path | None = None,
                   device: str = "cpu") -> dict:  # fmt: skip
    """Write ``reshaped.png`` ([capture frame | as trained | reshaped]), ``turntable.mp4`` and
    ``body_canonical.ply`` of the reshaped avatar, and ``reshape.json``; with ``truth`` (the generated capture
    of the subject with the edited phenotype), ``scores.csv`` (``clothing``: the avatar's exported
    clothing_nerf_space.ply, for the garment distances). Returns the summary."""
    t_start = time.perf_counter()
    settings = settings or ShowSettings()
    require_files(model=model_path, record=record, body_model=body_path)
    tr = load_trained(model_path, record, body_path, device)
    model = tr.model
    space = anny = None
    if any(not BETA.match(k) for k in edit) and shape_space is not None:
        from delta.body.anny_convert import ShapeSpace, build_anny

        if not Path(shape_space).is_file():
            raise DeltaError(f"{shape_space}: no such Anny shape-space file")
        space, anny = ShapeSpace.load(shape_space), build_anny(anny_cache)
    before = model.betas.detach().clone()
    new, about = edit_betas(before, edit, space, anny)
    tags = {"application": "reshape", "model": str(model_path), "edit": json.dumps(edit, sort_keys=True)}
    out = Path(out_dir)

    def reshape() -> None:
        model.betas.data[:] = new.to(model.betas)

    shown = show_edit(tr, record, out, "reshaped", reshape, settings, tags, truth, perceptual_dir, (clothing, clothing))
    write_mesh(out / "body_canonical.ply", body_mesh(model)[0])
    summary = {"model": str(model_path), "edit": dict(edit), **about, "betas_before": before.tolist(),
               "betas_after": new.tolist(), **shown, "seconds": round(time.perf_counter() - t_start, 2)}  # fmt: skip
    save_json(out / "reshape.json", summary)
    log.info("reshaped %s by %s: %s", model_path, edit, out)
    return summary
