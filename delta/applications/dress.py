"""Entry point of ``delta dress``: one avatar's exterior (clothing or hair) put on another avatar's body.

Why this works without a correspondence step: both avatars are built on the same body model, and each
exterior NeRF lives in that model's canonical space at mean shape. A posed avatar reaches it by
backward skinning over its *own* posed vertices: a point near the body takes the skinning of its
nearest body vertices and undoes their shape displacement (``delta.deformers.knn``). Give avatar B the
exterior of avatar A and B's renderer carries A's garment through B's shape and B's pose: a broader
body moves the garment's canonical points outward with the body vertices under them, so the garment
neither tears nor floats. What the body model's template does not explain (A's garment shaped around
A's own offsets) travels as it is.

A layer alone (an avatar trained with ``training.layers: split``: clothing and hair each their own NeRF)
moves the same way: B wearing A's hair keeps its own clothing layer (and the reverse). The two layers
then come from two trainings, so neither avatar's F_e (fitted to its own exterior as a whole) nor its
occupancy grid is kept: the mixed exterior is rendered rigidly skinned, every sample evaluated. A body
avatar whose exterior is one NeRF has no layer to keep: it wears the given layers alone. A layer given
alone is first confined to where A's own training frames see it (:func:`confine`): behind the other
layer's surface it may hold density no image ever showed (hair grown inside a skirt).

What can be carried: A's exterior must lie within what B models. An upper-body capture's exterior
(hair, a shirt) goes onto a full body; a full-body exterior onto an upper-body avatar is refused (its
hips and legs have nothing to follow). A without an exterior has nothing to give; B without one
simply gains A's.
"""

from __future__ import annotations

import dataclasses
import logging
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from delta import DeltaError
from delta.applications.settings import ShowSettings
from delta.applications.show import show_edit
from delta.export.meshes import LAYER_MESH, MeshPart, read_mesh, write_mesh
from delta.fields.networks import LayeredNeRF
from delta.io import require_files, save_json
from delta.models.avatar import HybridAvatar
from delta.models.layer_support import confined_layers
from delta.training.run import Trained, load_trained

log = logging.getLogger(__name__)


def check_wearable(body: HybridAvatar, wearer: HybridAvatar, layers: Sequence[str] = ()) -> None:
    """Raise a DeltaError naming why ``wearer``'s exterior (its ``layers`` alone, when given) cannot go onto
    ``body``."""
    if wearer.nerf is None:
        raise DeltaError("the wearer avatar has no exterior (no clothing or hair was modelled): nothing to put on")
    if layers:
        has = tuple(getattr(wearer.nerf, "names", ()))
        if not has:
            raise DeltaError(f"the wearer's exterior is one NeRF: its {', '.join(layers)} cannot be told apart from "
                             "the rest; train it with training.layers: split to move a layer alone")  # fmt: skip
        missing = sorted(set(layers) - set(has))
        if missing:
            raise DeltaError(f"the wearer's exterior has the layers {list(has)}, not {missing}")
    if body.body.num_vertices != wearer.body.num_vertices or not torch.equal(
        body.body.faces.cpu(), wearer.body.faces.cpu()
    ):
        raise DeltaError(f"the avatars are built on different body models ({body.body.name}, {wearer.body.name}): "
                         "an exterior moves between avatars of the same body model only")  # fmt: skip
    uncovered = wearer.modelled & ~body.modelled
    if bool(uncovered.any()):
        raise DeltaError(f"the wearer's exterior covers a '{wearer.spec.capture}' capture, the body models only "
                         f"'{body.spec.capture}': {int(uncovered.sum())} body vertices the exterior follows are not "
                         "modelled on it (an upper-body exterior goes onto a full body, not the reverse)")  # fmt: skip


def confine(wearer: Trained, layers: Sequence[str]) -> None:
    """Confine the wearer's ``layers`` to where its own training frames see them, in place
    (:func:`delta.models.layer_support.confined_layers`)."""
    confined = confined_layers(wearer.model, wearer.data, layers)
    if confined:  # (none for an exterior of one NeRF or one layer)
        wearer.model.nerf.layers.update(confined)


def put_on(body: HybridAvatar, wearer: HybridAvatar, layers: Sequence[str] = ()) -> None:
    """Give ``body`` the exterior of ``wearer`` in place: its NeRF, its F_e and occupancy grid, and the render
    settings that reach them. ``body``'s frames leave the training sequence of F_e (no time code).

    ``layers``: only these layers of the wearer's; ``body`` keeps its own other layers (see the module)."""
    check_wearable(body, wearer, layers)
    dev = body.canonical_vertices.device
    if layers:
        given = {n: wearer.nerf.layers[n].to(dev) for n in layers}
        own = dict(body.nerf.layers) if isinstance(body.nerf, LayeredNeRF) else {}
        kept = {n: layer for n, layer in own.items() if n not in given}
        if body.nerf is not None and not own:
            log.warning("the body avatar's exterior is one NeRF: it is taken off, the wearer's %s put on alone",
                        ", ".join(layers))  # fmt: skip
        if kept:
            _wear_mixed(body, wearer, LayeredNeRF.of(kept | given), "hair" in given)
            return
    _wear(body, wearer, LayeredNeRF.of(given) if layers else wearer.nerf.to(dev))


def _wear_mixed(body: HybridAvatar, wearer: HybridAvatar, nerf: LayeredNeRF, their_hair: bool) -> None:
    """``body`` with layers of two avatars: no F_e, no occupancy grid, no mirror where no frame looked (each
    avatar's reads its own exterior), the larger room of the two; the hair carried as its avatar carried it
    (``their_hair``: the wearer's)."""
    b, w = body.spec, wearer.spec
    carriage = (w if their_hair else b).render.hair_carriage
    body.exterior_mirror = None
    room = max(b.render.max_dist, w.render.max_dist)
    samples = max(b.render.samples, w.render.samples)
    body.nerf, body.deformation, body.occupancy = nerf, None, None
    body.spec = dataclasses.replace(b, deformation=None, nerf_margin=max(b.nerf_margin, w.nerf_margin), layers=nerf.names,
                                    render=dataclasses.replace(b.render, max_dist=room, samples=samples,
                                                               hair_carriage=carriage))  # fmt: skip
    body.frame_time.fill_(float("nan"))


def _wear(body: HybridAvatar, wearer: HybridAvatar, nerf) -> None:
    """``body`` with ``nerf`` (the wearer's exterior, or layers of it) and the wearer's F_e, occupancy and mirror
    where no frame looked (both canonical spaces are the body model's)."""
    dev = body.canonical_vertices.device
    body.nerf = nerf
    body.exterior_mirror = wearer.exterior_mirror
    body.deformation = wearer.deformation.to(dev) if wearer.deformation is not None else None
    body.occupancy = wearer.occupancy.to(dev) if wearer.occupancy is not None else None
    w = wearer.spec
    body.spec = dataclasses.replace(body.spec, nerf=w.nerf, deformation=w.deformation, nerf_margin=w.nerf_margin,
                                    deformation_scale=w.deformation_scale, time_freqs=w.time_freqs,
                                    layers=tuple(getattr(nerf, "names", ())),
                                    render=dataclasses.replace(w.render, knn_vertices=body.spec.render.knn_vertices))  # fmt: skip
    body.frame_time.fill_(float("nan"))


def worn_surface(clothing: str | Path | None, wearer_clothing: str | Path | None, layers: Sequence[str],
                 kept: Sequence[str], out: Path) -> str | Path | None:  # fmt: skip
    """The exterior's surface once dressed, for the garment distances: the wearer's whole exterior
    (``wearer_clothing``), or with ``layers`` given, the wearer's meshes of those layers and the body's own
    of the ``kept`` ones (each ``layer_{layer}_nerf_space.ply`` beside the exports' clothing_nerf_space.ply; a
    layer with no mesh adds nothing), written to ``out``. None where an export is not given."""
    if not layers or wearer_clothing is None or (kept and clothing is None):
        return wearer_clothing
    parts = [Path(wearer_clothing).with_name(LAYER_MESH.format(layer=n, space="nerf_space")) for n in layers]
    parts += [Path(clothing).with_name(LAYER_MESH.format(layer=n, space="nerf_space")) for n in kept]
    meshes = [read_mesh(p) for p in parts if p.is_file()]
    if not meshes:
        return None
    starts = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    write_mesh(out, MeshPart(np.concatenate([m.vertices for m in meshes]),
                             np.concatenate([m.faces + k for m, k in zip(meshes, starts)]),
                             np.concatenate([m.colors for m in meshes])))  # fmt: skip
    return out


def dress_avatar(body_model: str | Path, body_record: str | Path, wearer_model: str | Path,
                 wearer_record: str | Path, body_path: str | Path, out_dir: str | Path,
                 settings: ShowSettings | None = None, truth: str | Path | None = None,
                 perceptual_dir: str | None = None, clothing: str | Path | None = None,
                 wearer_clothing: str | Path | None = None, device: str = "cpu",
                 wearer_body: str | Path | None = None, layers: Sequence[str] = ()) -> dict:  # fmt: skip
    """Write ``dressed.png`` ([the body's capture frame | the body avatar as trained | wearing the other's
    exterior]), ``turntable.mp4`` of the dressed avatar and ``dress.json``; with ``truth`` (the generated
    capture of the body subject wearing the other's exterior), ``scores.csv`` (:mod:`delta.applications.truth`;
    ``clothing`` / ``wearer_clothing``: the two avatars' exported clothing_nerf_space.ply, for the garment
    distances as trained and dressed; ``wearer_body``: the body model the wearer was trained on, when not
    ``body_path``: a tracked face's, with its expressions; ``layers``: only these layers of the wearer's
    exterior, see :func:`put_on`). Returns the summary."""
    t_start = time.perf_counter()
    settings = settings or ShowSettings()
    require_files(body_avatar_model=body_model, body_avatar_record=body_record, wearer_model=wearer_model,
                  wearer_record=wearer_record, body_model=body_path, wearer_body_model=wearer_body or body_path)  # fmt: skip
    body = load_trained(body_model, body_record, body_path, device)
    wearer = load_trained(wearer_model, wearer_record, wearer_body or body_path, device)
    check_wearable(body.model, wearer.model, layers)
    confine(wearer, layers)
    about = {"application": "dress", "model": str(body_model), "wearer": str(wearer_model), "layers": list(layers)}
    kept = [n for n in getattr(body.model.nerf, "names", ()) if n not in layers]
    with tempfile.TemporaryDirectory() as tmp:
        dressed = worn_surface(clothing, wearer_clothing, layers, kept, Path(tmp) / "worn_nerf_space.ply")
        shown = show_edit(body, body_record, Path(out_dir), "dressed", lambda: put_on(body.model, wearer.model, layers),
                          settings, about, truth, perceptual_dir, (clothing, dressed))  # fmt: skip
    summary = {"body_model": str(body_model), "wearer_model": str(wearer_model), **shown,
               "body_capture": body.model.spec.capture, "wearer_capture": wearer.model.spec.capture,
               "seconds": round(time.perf_counter() - t_start, 2)}  # fmt: skip
    save_json(Path(out_dir) / "dress.json", summary)
    log.info("%s wears %s's exterior: %s", body_model, wearer_model, out_dir)
    return summary
