"""Entry points of the training rules: results/{dataset}/{subject}/stage1/ and stage2/.

Stage 1 starts from the init fit (init/params.npz); stage 2 from stage 1's model.pt,
adding F_e and the semantic loss. Each writes ``model.pt`` (the rule's output, written
last), ``losses.csv``, ``settings.json``, previews, and keeps ``checkpoint.pt`` for resuming.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from pathlib import Path

import torch

from delta import DeltaError
from delta.body.model import load_body_model
from delta.cameras.models import OrthographicCamera
from delta.data.frames import FrameData, frame_times, load_frames
from delta.data.record import FrameRecord
from delta.fields.networks import time_features
from delta.io import atomic_path, load_state, save_json
from delta.models.avatar import HybridAvatar, InitParams
from delta.models.init import load_init
from delta.models.spec import AvatarSpec, shade_value
from delta.models.unseen import mirror_from_state, mirror_state, unseen_parts
from delta.render.settings import OccupancySettings
from delta.scene.analysis import MIN_EXTERIOR_FRACTION
from delta.scene.settings import scene_settings
from delta.scene.framing import MAX_CLOTHING_ON_HEAD, clothing_on_head, detect_capture, framed_vertices
from delta.training.presets import TrainSettings, deep_merge, resolve
from delta.training.scope import frozen_joints
from delta.training.trainer import file_digest, train_stage

log = logging.getLogger(__name__)


def pick_device(name: str) -> torch.device:
    if name == "cuda" and not torch.cuda.is_available():
        raise DeltaError("device: cuda is configured but torch sees no CUDA device (use 'auto' or 'cpu')")
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    return torch.device(name)


def wants_exterior(st: TrainSettings, data: FrameData) -> bool:
    """Model only what the scene requires: a NeRF only where clothing or hair is seen."""
    if st.exterior != "auto":
        return st.exterior == "yes"
    frac = data.exterior.total(data.train) / max(data.person.total(data.train), 1.0)
    log.info("exterior pixels: %.1f%% of the person%s", 100 * frac,
             "" if frac >= MIN_EXTERIOR_FRACTION else " -> no NeRF is built")  # fmt: skip
    return frac >= MIN_EXTERIOR_FRACTION


def exterior_layers(st: TrainSettings, data: FrameData) -> tuple[str, ...]:
    """The exterior's layers: clothing and hair apart (``layers: split``) where the training frames show
    both (each at least ``MIN_EXTERIOR_FRACTION`` of the person), else none (one NeRF)."""
    if st.layers != "split":
        return ()
    if data.hair is None:
        raise DeltaError("training.layers: split needs the frames' hair mask (load_frames(..., hair=True))")
    person = max(data.person.total(data.train), 1.0)
    hair = data.hair.total(data.train) / person
    clothing = (data.exterior.total(data.train) - data.hair.total(data.train)) / person  # hair <= exterior
    both = min(hair, clothing) >= MIN_EXTERIOR_FRACTION
    log.info("exterior layers: clothing %.1f%%, hair %.1f%% of the person -> %s", 100 * clothing, 100 * hair,
             "one NeRF each" if both else "one NeRF (not both seen)")  # fmt: skip
    return ("clothing", "hair") if both else ()


def resolve_scope(body, st: TrainSettings, init: InitParams, data: FrameData) -> dict:
    """What this capture needs modelled: ``capture`` (full/upper), ``frozen_joints`` (logged), the
    exterior's ``layers`` and the ``framed`` vertices (V,) bool, which the fields' boxes hold."""
    capture = st.capture
    if capture == "auto":
        capture = detect_capture(body, init.betas, init.poses, init.transl, init.camera, data.train, data.resolution)
    frozen = frozen_joints(body, st.freeze, st.freeze_rest, init.poses[data.train])
    if frozen:
        names = [body.joint_names[j] for j in frozen]
        log.info("frozen joints (%d): %s", len(frozen), ", ".join(names[:12]) + (" ..." if len(names) > 12 else ""))
    if capture == "upper":
        log.info("capture 'upper': the lower body is not modelled (no skinning samples or NeRF box there)")
    framed = framed_vertices(body, init.betas, init.poses, init.transl, init.camera, data.train, data.resolution)
    log.info("the training frames frame %d of the body's %d vertices: the fields' boxes hold those modelled",
             int(framed.sum()), len(framed))  # fmt: skip
    layers = exterior_layers(st, data)
    return {"capture": capture, "frozen_joints": frozen, "layers": layers,
            "clothing_off_head": clothing_off_head(body, st, init, data, layers), "framed": framed}  # fmt: skip


def clothing_off_head(body, st: TrainSettings, init: InitParams, data: FrameData, layers) -> bool:
    """Whether the clothing layer is barred from the head (``training.clothing_on_head``; ``auto``: where the
    capture's clothing covers at most :data:`MAX_CLOTHING_ON_HEAD` of the fitted head's projected vertices)."""
    if "clothing" not in layers or st.clothing_on_head == "yes":
        return False
    if st.clothing_on_head == "no":
        return True
    share = clothing_on_head(body, init.betas, init.poses, init.transl, init.camera, data.train, data.resolution,
                             lambda f: (data.exterior[f] - data.hair[f]) > 0.5)  # fmt: skip
    off = share is not None and share <= MAX_CLOTHING_ON_HEAD
    shown = "no head in view" if share is None else f"{100 * share:.1f}% of the fitted head's projected vertices"
    log.info("clothing on the head: %s (at most %g%% bars the clothing layer from the head) -> %s", shown,
             100 * MAX_CLOTHING_ON_HEAD, "barred" if off else "allowed")  # fmt: skip
    return off


def scoped(spec: AvatarSpec, scope: dict) -> AvatarSpec:
    """``spec`` with a scope's capture, frozen joints and exterior layers (and whether its clothing is barred
    from the head, and where a trained model gives it, the mouth's shade it was trained with)."""
    return dataclasses.replace(spec, capture=scope["capture"], frozen_joints=tuple(scope["frozen_joints"]),
                               layers=tuple(scope.get("layers", ())),
                               clothing_off_head=bool(scope.get("clothing_off_head", False)),
                               mouth_shade=shade_value(scope.get("mouth_shade", spec.mouth_shade)))  # fmt: skip


def build_avatar(body, st: TrainSettings, init: InitParams, data: FrameData, stage: int, device,
                 scope: dict | None = None) -> HybridAvatar:  # fmt: skip
    """The avatar of a stage; ``scope`` (capture, frozen_joints and optionally the exterior's layers, none
    when not given) as resolved earlier, else resolved here."""
    scope = scope or resolve_scope(body, st, init, data)
    spec = scoped(st.avatar, scope)
    if not wants_exterior(st, data):
        spec = dataclasses.replace(spec, nerf=None)
    if stage == 2 and spec.nerf is not None:
        spec = dataclasses.replace(spec, deformation=st.deformation)
    bg = torch.tensor(st.background, dtype=torch.float32)
    torch.manual_seed(st.seed)  # network initialisation
    avatar = HybridAvatar(body, spec, init, data.skin_color, bg, data.resolution,
                          frame_times(data.frame_ids, data.train, data.split), scope.get("framed")).to(device)  # fmt: skip
    if avatar.nerf is not None:
        log.info("the exterior's colour: finest cell %.1f mm (nerf.color_cell %s)", 1000 * avatar.nerf.color_cell(),
                 f"{1000 * spec.nerf.color_cell:g} mm" if spec.nerf.color_cell else "unset")  # fmt: skip
    return avatar


def semantic_loss(st: TrainSettings, weights_dir: str | None, device):
    if st.semantic == "none" or st.weights.semantic == 0:
        return None
    from delta.perceptual.idmrf import SemanticLoss

    return SemanticLoss(kind=st.semantic, cache_dir=weights_dir).to(device)


def stage_frames(record, st: TrainSettings, size: int | None = None) -> FrameData:
    """A record's frames as a stage with settings ``st`` trains on them: at ``size`` (default the training
    resolution), on the settings' background and box margin, with the hair mask where the exterior is
    split into layers."""
    return load_frames(record, size or st.resolution, st.background, st.box_margin, hair=st.layers == "split")


def fine_frames(record, st: TrainSettings, stage: int) -> FrameData | None:
    """The frames a coarse-to-fine stage switches to (its ``fine_resolution``, or the record's own
    size), or None when the stage has no switch."""
    cfg = st.stage1 if stage == 1 else st.stage2
    if cfg.fine_step() >= cfg.iterations:
        return None
    size = cfg.fine_resolution
    if not size:
        with FrameRecord(record) as rec:
            size = rec.size
    log.info("stage %d: rays from %d x %d frames from step %d (of %d)", stage, size, size, cfg.fine_step() + 1,
             cfg.iterations)  # fmt: skip
    return stage_frames(record, st, size)


def stage_settings(preset: str, overrides: list[dict], scene: str | None = None, user_set=()) -> TrainSettings:
    """A stage's settings as the workflow resolves them: the preset, the config's ``overrides`` over it, and
    the scene's decisions (``scene.json``) for the keys the config does not set itself (``user_set``)."""
    st = resolve(preset, *overrides)
    if scene:
        decided = scene_settings(scene, st.raw, list(user_set))
        if decided:
            log.info("from the scene analysis (%s): %s", scene, json.dumps(decided, sort_keys=True))
            st = resolve(preset, *overrides, decided)
    return st


def run_stage(stage: int, record: str, body_path: str, start: str, out_dir: str, preset: str,
              overrides: list[dict], device: str = "cpu", perceptual_dir: str | None = None,
              scene: str | None = None, user_set: list[str] = ()) -> dict:  # fmt: skip
    """Train one stage; ``start`` is init/params.npz (stage 1) or stage 1's model.pt (stage 2).

    ``scene``: the subject's scene.json; its decisions apply to the keys not in ``user_set`` (the keys
    the config sets itself)."""
    st = stage_settings(preset, overrides, scene, user_set)
    dev = pick_device(device)
    data = stage_frames(record, st)
    body = load_body_model(body_path)  # on the CPU: the avatar's .to(dev) moves it
    if stage == 1:
        init = load_init(start, data)
        model = build_avatar(body, st, init, data, 1, dev)
    else:
        prev = migrate_model(load_state(start, map_location=dev), start)
        init = load_init_from_state(prev["model"], data)
        model = build_avatar(body, st, init, data, 2, dev, _scope(prev, start, body.num_vertices))
        missing, unexpected = model.load_state_dict(prev["model"], strict=False)
        if unexpected or any(not k.startswith("deformation.") for k in missing):
            raise DeltaError(f"{start}: does not match this preset's stage-2 model "
                             f"(missing {missing[:3]}, unexpected {unexpected[:3]})")  # fmt: skip
    out = Path(out_dir)
    save_json(out / "settings.json", {"preset": preset, "stage": stage, "settings": st.raw,
                                      "nerf": model.nerf is not None, "device": str(dev)})  # fmt: skip
    sem = semantic_loss(st, perceptual_dir, dev) if stage == 2 else None
    fine = fine_frames(record, st, stage)
    t0 = time.time()
    # a checkpoint belongs to what the stage starts from (the init fit, or stage 1's model) and the frames'
    # record: a refitted body or re-prepared frames under unchanged settings is another run, not this one resumed
    origin = f"{file_digest(start)}-{file_digest(record)}"
    res = train_stage(stage, model, data, st, out, sem, origin=origin, fine=fine)
    (ids, values), model.exterior_mirror, evidence = unseen_parts(
        model, data.train, st.unseen_albedo != "field", st.unseen_exterior == "mirror", st.unseen_albedo == "outside"
    )
    model.fill_albedo(ids, values)
    filled, mirrored = len(ids), evidence.get("exterior", {}).get("mirrored", 0)
    if evidence:
        log.info("where no training frame looked: the albedo filled from what they saw, the exterior read at its "
                 "mirror through the body: %s", json.dumps(evidence))  # fmt: skip
    save_model(out / "model.pt", model, stage, preset, st, res.steps)
    last = res.losses.tail(max(1, len(res.losses) // 20)).mean(numeric_only=True)
    summary = {"stage": stage, "steps": res.steps, "seconds": round(time.time() - t0, 1),
               "train_psnr_last5pct": round(float(last.get("psnr", float("nan"))), 2), "albedo_filled": filled,
               "exterior_cells_mirrored": mirrored}  # fmt: skip
    seen = {n: round(float(last[f"seen_{n}"]), 3) for n in getattr(model.nerf, "names", ()) if f"seen_{n}" in last}
    if seen:
        summary["layers_seen"] = seen
        for name in dead_layers(seen):
            log.warning("stage %d: the %s layer's opacity on its own mask's rays is %.2f over the last steps: the "
                        "layer has died and another draws its region (weights.layer_shares > 0 keeps a layer "
                        "alive: docs/method.md)", stage, name, seen[name])  # fmt: skip
    if model.deformation is not None:
        units = summary["deformation_units_active"] = deformation_units(model, data.train)
        width = model.deformation.head.hidden[0].out_features
        if min(units) < width // 4:
            log.warning("F_e's head has few units left active (%s of %d a hidden layer, over its box and the "
                        "training times): its deformation is nearly constant", units, width)  # fmt: skip
    log.info("stage %d done: %s", stage, json.dumps(summary))
    return summary


#: A layer whose mean opacity on its own mask's rays is under this at a stage's end has died.
DEAD_LAYER = 0.1


def dead_layers(seen: dict[str, float], floor: float = DEAD_LAYER) -> list[str]:
    """The layers of ``seen`` (each layer's mean opacity on its own mask's rays, NaN: never met) under
    ``floor``."""
    return [name for name, value in seen.items() if not math.isnan(value) and value < floor]


def deformation_units(model, train) -> list[int]:
    """Units of F_e's head active somewhere in its box at the training frames' times, per hidden layer."""
    times = None
    if model.spec.time_freqs:  # at most 16 of the training times, evenly spread
        frames = torch.as_tensor(train, device=model.frame_time.device)[:: max(1, len(train) // 16)]
        times = time_features(model.frame_time[frames], model.spec.time_freqs)
    return model.deformation.active_units(times)


#: The layout of ``model.pt`` this code writes; :func:`migrate_model` brings older files up to it.
MODEL_FORMAT = 3


def save_model(path: str | Path, model: HybridAvatar, stage: int, preset: str, st: TrainSettings, steps: int) -> None:
    """A stage's output (``model.pt``): the weights and what :func:`load_trained` rebuilds the avatar from."""
    final = {"format": MODEL_FORMAT, "model": model.state_dict(), "stage": stage, "preset": preset, "settings": st.raw,
             "nerf": model.nerf is not None, "deformation": model.deformation is not None,
             "pinhole": model.pinhole, "steps": steps, "capture": model.spec.capture,
             "frozen_joints": list(model.spec.frozen_joints),
             "layers": list(model.spec.layers), "clothing_off_head": model.spec.clothing_off_head,
             "framed": model.framed.cpu().clone(),
             "albedo_fill": {"ids": model.fill_ids.cpu().clone(), "values": model.fill_values.cpu().clone()},
             "exterior_mirror": mirror_state(model.exterior_mirror)}  # fmt: skip
    with atomic_path(path) as tmp:
        torch.save(final, tmp)


def migrate_model(state: dict, path: str | Path) -> dict:
    """A ``model.pt``'s contents in the layout of :data:`MODEL_FORMAT`, whatever format wrote them.

    Format 1 (no ``format`` key) predates the dynamics settings, the capture scope and, in its
    oldest files, the occupancy grid: such a model was trained without time input to F_e, without
    a pose trajectory, on the full body, with every joint free and no occupancy grid. Formats 1 and 2
    predate the mouth's prior: their mouth's inside started at the skin colour (``mouth_shade`` 1).
    """
    version = state.get("format", 1)
    if not isinstance(version, int) or not 1 <= version <= MODEL_FORMAT:
        raise DeltaError(f"{path}: model format {version!r}; this code reads formats 1 to {MODEL_FORMAT} "
                         "(a newer delta wrote it?)")  # fmt: skip
    for key in ("model", "stage", "preset", "settings"):
        if key not in state:
            raise DeltaError(f"{path}: missing '{key}'; not a model.pt written by 'delta train'")
    if version == 1:
        state = dict(state, format=MODEL_FORMAT)
        written = state["settings"].get("dynamics", {})
        settings = deep_merge(
            state["settings"], {"dynamics": {k: 0 for k in ("time_freqs", "pose_knots") if k not in written}}
        )
        if not any(k.startswith("occupancy.") for k in state["model"]):
            settings = deep_merge(settings, {"render": {"occupancy": dataclasses.asdict(OccupancySettings())}})
        state["settings"] = settings
        state.setdefault("capture", "full")
        state.setdefault("frozen_joints", [])
    if version < 3:
        state = dict(state, format=MODEL_FORMAT)
        state["settings"] = dict(state["settings"], mouth_shade=state["settings"].get("mouth_shade", 1.0))
    return state


def _scope(state: dict, path: str | Path = "model.pt", num_vertices: int | None = None) -> dict:
    """The capture, frozen joints, exterior layers, framed vertices and mouth shade a (migrated) model.pt was
    trained with; a file written before the framed vertices were kept has its boxes as they were trained (the
    vertex fields' around the whole template, the exterior's around every modelled vertex).
    ``num_vertices``: the body model's, which the framed vertices must match."""
    framed = state.get("framed")
    if framed is not None:
        if not torch.is_tensor(framed) or framed.dim() != 1:
            raise DeltaError(f"{path}: 'framed' is not a per-vertex mask (a model.pt written by 'delta train'?)")
        if num_vertices is not None and len(framed) != num_vertices:
            raise DeltaError(f"{path}: trained on a body model of {len(framed)} vertices, the body model given has "
                             f"{num_vertices}")  # fmt: skip
        framed = framed.cpu().bool()
    return {"capture": state["capture"], "frozen_joints": list(state["frozen_joints"]),
            "layers": list(state.get("layers", [])),
            "clothing_off_head": bool(state.get("clothing_off_head", False)), "framed": framed,
            "mouth_shade": shade_value(state.get("settings", {}).get("mouth_shade", 1.0), f"{path}: mouth_shade")}  # fmt: skip


def load_init_from_state(state: dict, data: FrameData) -> InitParams:
    """Per-frame parameters as stage 1 left them (stage 2 starts from the refined ones)."""
    camera = data.camera
    if "ortho_scale" in state:
        camera = OrthographicCamera(state["ortho_scale"].cpu(), state["ortho_trans"].cpu(),
                                    data.resolution, data.resolution)  # fmt: skip
    expression = state["expression"].cpu() if "expression" in state else None
    return InitParams(state["betas"].cpu(), state["poses"].cpu(), state["transl"].cpu(), camera, expression)


@dataclasses.dataclass
class Trained:
    """A trained avatar loaded back with the frames and settings it was trained with."""

    model: HybridAvatar
    data: FrameData
    settings: TrainSettings
    stage: int
    preset: str


def load_trained(model_path: str | Path, record: str | Path, body_path: str | Path, device: str = "cpu") -> Trained:
    """Rebuild a stage's avatar from its model.pt (the settings it was trained with travel inside).

    The frames are loaded at the training resolution; other images of a frame (the capture's whole
    frame for scoring and exports) are :class:`delta.models.image.View` s of it.
    """
    dev = pick_device(device)
    state = migrate_model(load_state(model_path, map_location=dev), model_path)
    st = resolve(state["preset"], state["settings"])
    data = stage_frames(record, st)
    spec = st.avatar if state.get("nerf", True) else dataclasses.replace(st.avatar, nerf=None)
    body = load_body_model(body_path)  # on the CPU: the avatar's .to(dev) moves it
    scope = _scope(state, model_path, body.num_vertices)
    spec = scoped(spec, scope)
    if state.get("deformation"):
        spec = dataclasses.replace(spec, deformation=st.deformation)
    bg = torch.tensor(st.background, dtype=torch.float32)
    init = load_init_from_state(state["model"], data)
    frames, expected = len(data.frame_ids), int(init.poses.shape[0])
    if frames != expected:
        raise DeltaError(f"{model_path}: trained on {expected} frames but {record} has {frames}; "
                         "not the record this model was trained on")  # fmt: skip
    model = HybridAvatar(body, spec, init, data.skin_color, bg, data.resolution,
                         frame_times(data.frame_ids, data.train, data.split), scope["framed"]).to(dev)  # fmt: skip
    try:
        model.load_state_dict(state["model"])
        fill = state.get("albedo_fill")  # a file written before the fill has none
        if fill is not None:
            model.fill_albedo(fill["ids"], fill["values"])
        model.exterior_mirror = mirror_from_state(state.get("exterior_mirror"))
    except (RuntimeError, ValueError, KeyError, TypeError) as e:
        raise DeltaError(f"{model_path}: does not match {body_path} or {record}: {str(e)[:300]}") from None
    model.eval()
    return Trained(model, data, st, int(state["stage"]), str(state["preset"]))
