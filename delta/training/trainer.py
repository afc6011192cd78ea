"""One training stage: the loop, the loss recipe, checkpoints that resume exactly, previews.

Resume contract: a checkpoint holds the model, the optimiser, the step, the sampling
generator's state and the loss rows so far; a stage rerun after an interruption
continues from it and reaches the same parameters as an uninterrupted run.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import Callable, Optional

import cv2
import numpy as np
import pandas as pd
import torch

from delta import DeltaError
from delta import losses as L
from delta.body.face_points import FacePoints
from delta.data.frames import FrameData, RayBatch, sample_rays
from delta.data.tracks import Tracks, frame_tracks
from delta.io import atomic_path, load_state
from delta.models.avatar import HybridAvatar
from delta.models.image import render_image
from delta.optim import Adam
from delta.progress import Progress
from delta.render.settings import RenderSettings
from delta.training.presets import StageSettings, TrainSettings, find_plateau, stage_view

log = logging.getLogger(__name__)
CHECKPOINT = "checkpoint.pt"
PREVIOUS_CHECKPOINT = "checkpoint.prev.pt"


@dataclasses.dataclass
class StageResult:
    steps: int
    seconds: float
    losses: pd.DataFrame


def loss_terms(model: HybridAvatar, batch: RayBatch, st: TrainSettings, skin_color: torch.Tensor,
               semantic: Optional[Callable] = None, generator=None, timeless: bool = False,
               face: Optional[tuple[FacePoints, torch.Tensor]] = None) -> tuple[dict, object]:  # fmt: skip
    """Render a ray batch and evaluate every term of the objective (unweighted); ``face``: the record's face
    points on the mesh and the (K, 3) detections of the batch's frame (u, v, confidence), for their term."""
    mesh, offsets, out = model.posed_mesh(batch.frame)
    r = model.render(batch.frame, batch.pixels, generator, mesh, timeless)
    d = st.weights.huber_delta
    terms = {
        "pixel": L.pixel(r.rgb, batch.rgb, d),
        "silhouette": L.silhouette(r.silhouette, batch.person, d),
        "interior_mask": L.interior_mask(r.silhouette, batch.interior, d),
        "skin": L.skin(r.mesh_rgb, batch.rgb, batch.interior, d),
        "inside": L.inside(r.silhouette, batch.person, d),
        "skin_inside": L.skin_inside(r.mesh_rgb, skin_color, batch.exterior, d),
        "edge": L.edge(offsets, model.edges),  # the mesh with its offsets against the one without
        "offset": L.offset(offsets, model.body.regions, st.weights.offset_region_weights),
    }
    details = [f.detail for f in (model.offset_field, model.albedo_field) if f.detail is not None]
    if details:
        terms["vertex_detail"] = L.vertex_detail(details)
    if face is not None:
        posed = face[0](out.vertices)[0]
        uv, _ = model.camera(batch.frame).project(posed)
        terms["face_points"] = L.face_points(uv, face[1][:, :2], face[1][:, 2], model.resolution)
    if model.nerf is not None:
        terms["exterior"] = L.exterior(r.nerf_mask, batch.exterior)
        if st.weights.empty_background > 0:
            terms["empty_background"] = L.empty_background(r.optical_depth, batch.person)
        if st.weights.shell > 0 and r.shell_depth is not None:
            terms["shell"] = L.shell(r.shell_depth)
        if st.weights.distortion > 0 and r.distortion is not None:
            terms["distortion"] = L.distortion(r.distortion)
    if r.layer_masks is not None:
        terms["exterior_layers"] = L.exterior_layers(r.layer_masks, model.nerf.names, batch.exterior, batch.hair)
        if st.weights.layer_shares > 0 and r.layer_log_shares is not None:
            terms["layer_shares"] = L.layer_shares(r.layer_log_shares, r.sample_weights, model.nerf.names,
                                                   batch.exterior, batch.hair)  # fmt: skip
    if semantic is not None and batch.patch:
        p = batch.patch
        img = lambda x: x[: p * p].T.reshape(1, 3, p, p)  # noqa: E731
        terms["semantic"] = semantic(img(r.rgb), img(batch.rgb))
    return terms, r


def layers_seen(layer_masks: torch.Tensor, names, exterior_mask: torch.Tensor,
                hair_mask: Optional[torch.Tensor]) -> dict[str, torch.Tensor]:  # fmt: skip
    """``{"seen_{layer}": mean opacity of the layer (``layer_masks`` (R, L), in ``names`` order) on the rays
    its own mask holds (over half)}``, NaN where the batch has none of its rays: a readout, not a term (a
    layer near 0 here has died: another layer draws its region)."""
    if hair_mask is None:
        return {}
    with torch.no_grad():
        mine = L.stacked_targets(exterior_mask, hair_mask, names) > 0.5  # (R, L)
        seen = (layer_masks * mine).sum(0) / mine.sum(0)  # 0 / 0: NaN where no ray is the layer's
    return {f"seen_{n}": seen[k] for k, n in enumerate(names)}


def nerf_only_terms(model: HybridAvatar, batch: RayBatch, st: TrainSettings, generator=None) -> tuple[dict, object]:
    """The NeRF-only warm-up's objective (SCARF's stage 0): rays pass through the mesh and the NeRF alone
    learns the whole person — its colour against the image, its opacity against the person mask.

    A fresh PE MLP is one constant over space, and Adam moves that constant by whole learning-rate
    steps in every layer at once: when a batch's rays mostly ask for less density (skin and
    background under the hybrid objective's clothing mask; background under the person mask of a
    whole-box batch) its density runs to 0 everywhere within ~25 steps and never recovers
    (``benchmarks/density_collapse.py``). Drawn from the person box's centre (``nerf_warmup_crop``),
    these rays mostly ask for more, and the NeRF takes the person's shape before the hybrid
    objective carves the body out of it.
    """
    r = model.render(batch.frame, batch.pixels, generator, through_mesh=True)
    terms = {
        "pixel": L.pixel(r.rgb, batch.rgb, st.weights.huber_delta),
        "exterior": L.exterior(r.nerf_mask, batch.person),
    }
    return terms, r


def _psnr_of(mse: float) -> float:
    return float(10 * np.log10(1.0 / max(mse, 1e-10)))


def _read_back(*scalars: torch.Tensor) -> list[float]:
    """The values of 0-d tensors as floats, read from the device at once (on a GPU one wait, not one each);
    each exactly as ``float(t)`` gives it."""
    return torch.stack([t.detach().reshape(()).to(torch.float64) for t in scalars]).tolist()


def fingerprint(stage: int, st: TrainSettings, data: FrameData, origin: str = "", model=None) -> str:
    """What a checkpoint must have been trained with to be resumed: the stage, the settings it reads
    (:func:`stage_view`), the frames, ``origin`` (the workflow's: digests of what the stage starts from, the
    init fit or the stage-1 model, and of the frames' record) and, given the ``model``, the shapes of its
    state (the same settings build other grids where the fields' boxes differ: a checkpoint of another
    version's boxes is not resumed, not half loaded)."""
    shapes = {} if model is None else {k: list(v.shape) for k, v in model.state_dict().items()}
    key = json.dumps({"stage": stage, "settings": stage_view(st.raw, stage), "frames": np.asarray(data.frame_ids).tolist(),
                      "resolution": data.resolution, "origin": origin, **({"shapes": shapes} if shapes else {})},
                     sort_keys=True, default=str)  # fmt: skip
    return hashlib.sha256(key.encode()).hexdigest()[:16]


def file_digest(path: str | Path) -> str:
    """A digest of a file's bytes (a checkpoint belongs to the init fit or stage-1 model it started from)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def load_checkpoint(out_dir: Path, key: str, stage: int, device) -> Optional[dict]:
    """The newest readable checkpoint of the run ``key`` in ``out_dir``, else None (train from the start).

    A checkpoint that cannot be read (truncated, corrupt, or holding objects that could run code) is
    set aside as ``<name>.corrupt`` with a warning, and the one before it (``checkpoint.prev.pt``) is
    tried; one written with other settings, frames or start (init fit, stage-1 model) is stale and not resumed.
    """
    for name in (CHECKPOINT, PREVIOUS_CHECKPOINT):
        path = out_dir / name
        if not path.is_file():
            continue
        try:
            state = load_state(path, map_location=device)
            for field in ("model", "optimizer", "step", "generator", "rows"):
                if field not in state:
                    raise DeltaError(f"{path}: missing '{field}'")
        except DeltaError as exc:
            aside = path.with_name(path.name + ".corrupt")
            os.replace(path, aside)
            log.warning("stage %d: %s; set aside as %s, trying the checkpoint before it", stage, exc, aside.name)
            continue
        if state.get("fingerprint") != key:
            log.warning("stage %d: not resuming from %s: it was written with other settings, frames or start (init "
                        "fit, stage-1 model); training from the start", stage, path)  # fmt: skip
            return None
        return state
    return None


def save_checkpoint(path: Path, model, optimizer, step: int, generator: torch.Generator, rows: list,
                    fingerprint: str = "") -> None:  # fmt: skip
    """Write a checkpoint atomically; the one it replaces is kept as ``checkpoint.prev.pt``."""
    state = {"model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": step,
             "generator": generator.get_state(), "rows": rows, "fingerprint": fingerprint}  # fmt: skip
    path = Path(path)
    if path.is_file():
        os.replace(path, path.with_name(PREVIOUS_CHECKPOINT))
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


@contextlib.contextmanager
def reproducible(device: torch.device):
    """On the CPU, torch's deterministic kernels for the duration (the previous mode is restored).

    With 2 threads the backward of a gather with repeated indices (``vertices[faces]``, a feature
    table indexed per sample) adds into the same rows from both threads in any order: two runs of the
    same stage parted from step ~40 (tight, ``fast``; reruns of the three subjects ended 0.05-0.07 dB
    apart held-out). The deterministic path made them bit-identical at no measurable cost (80 steps:
    36-38 s against 40 s). On CUDA the mode stays as it is: there it needs cuBLAS configured before
    the first call, and ops without a deterministic CUDA kernel would raise.
    """
    if device.type != "cpu":
        yield
        return
    before, warn = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    _deterministic(True)
    try:
        yield
    finally:
        _deterministic(before, warn_only=warn)


def _deterministic(mode: bool, warn_only: bool = False) -> None:
    """``torch.use_deterministic_algorithms``, without importing the compiler it also configures (~2 s a
    process, for a flag that matters only to compiled code) unless something has imported it already."""
    if "torch._inductor.config" in sys.modules:
        torch.use_deterministic_algorithms(mode, warn_only=warn_only)
    else:
        torch._C._set_deterministic_algorithms(mode, warn_only=warn_only)


def train_stage(stage: int, model: HybridAvatar, data: FrameData, st: TrainSettings, out_dir: Path,
                semantic: Optional[Callable] = None, max_steps: Optional[int] = None, origin: str = "",
                fine: Optional[FrameData] = None) -> StageResult:  # fmt: skip
    """Run (or resume) a stage; ``max_steps`` stops early (tests use it to simulate an interruption).
    ``fine``: the frames at the stage's ``fine_resolution``, which its rays come from after the switch
    (:meth:`StageSettings.fine_step`; the step decides, so a resume across the switch stays exact).

    A checkpoint of the same run at the stage's last step is finished work: the model is loaded from
    it and written out, not trained again (delete the stage's folder to train from scratch).
    ``origin`` identifies what the stage starts from (stage 2: the stage-1 model's digest).
    On the CPU a stage is bit-reproducible for a given thread count (:func:`reproducible`)."""
    with reproducible(model.background.device):
        return _train_stage(stage, model, data, st, out_dir, semantic, max_steps, origin, fine)


def face_targets(data: FrameData, st: TrainSettings, device) -> Optional[tuple[FacePoints, torch.Tensor]]:
    """The record's face points on the mesh and every frame's (F, K, 3) detections, on ``device``, where
    the term that holds the face to them is on (``weights.face_points`` > 0) and the record tracks a face."""
    if st.weights.face_points <= 0 or data.face is None:
        return None
    points = FacePoints(data.face.vertex_ids.to(device), data.face.bary.to(device))
    return points, data.face_points.to(device)


#: tracked points a step reads (each two rays, one a frame), and how many a pair of frames must share
TRACK_POINTS = 512
TRACK_LEAST = 32


def stage_tracks(model: HybridAvatar, data: FrameData, st: TrainSettings, stage: int) -> Optional[Tracks]:
    """The points of the exterior followed through the training frames, where the track term is on
    (``weights.track`` > 0) and the stage has F_e to move (stage 2); else None."""
    if st.weights.track <= 0 or model.deformation is None:  # stage 1, or no exterior: nothing for it to move
        return None
    tracks = frame_tracks(data.images, data.exterior, data.frame_ids, data.train)
    lengths = (~tracks.pixels[..., 0].isnan()).sum(1).float()
    log.info("stage %d: %d points of the exterior followed through the training frames (%.1f frames each on "
             "average, %d at most)", stage, tracks.count, float(lengths.mean()) if len(lengths) else 0.0,
             int(lengths.max()) if len(lengths) else 0)  # fmt: skip
    return tracks


def track_term(model: HybridAvatar, tracks: Tracks, frame: int, partners: torch.Tensor, generator: torch.Generator,
               num: int = TRACK_POINTS) -> torch.Tensor:  # fmt: skip
    """The track term (``delta.losses.track``) between ``frame`` and one of its ``partners`` (frames sharing
    tracks with it, drawn with ``generator``) on up to ``num`` of their shared tracks, each end read in its
    own frame at its own time."""
    b = int(partners[torch.randint(len(partners), (1,), generator=generator)])
    start, end = tracks.between(frame, b)
    pick = torch.randperm(len(start), generator=generator)[:num]
    device = model.background.device
    pa, ua, oa = model.canonical_points(frame, start[pick].to(device), generator)
    pb, ub, ob = model.canonical_points(b, end[pick].to(device), generator)
    return L.track(pa, pb, ua, ub, oa, ob)


def rays_at(data: FrameData, fine: Optional[FrameData], frame: int, num: int, generator: torch.Generator,
            patch: int = 0, crop: float = 1.0, edge: float = 0.0) -> RayBatch:  # fmt: skip
    """A step's rays: from ``data``, or from the ``fine`` frames with their pixels in ``data``'s units
    (the model's). The same draws from the generator either way."""
    if fine is None:
        return sample_rays(data, frame, num, generator, patch, crop=crop, edge=edge)
    batch = sample_rays(fine, frame, num, generator, patch, crop=crop, edge=edge)
    return dataclasses.replace(batch, pixels=batch.pixels * (data.resolution / fine.resolution))


def _train_stage(stage: int, model: HybridAvatar, data: FrameData, st: TrainSettings, out_dir: Path,
                 semantic: Optional[Callable], max_steps: Optional[int], origin: str,
                 fine: Optional[FrameData]) -> StageResult:  # fmt: skip
    cfg: StageSettings = st.stage1 if stage == 1 else st.stage2
    if cfg.fine_step() < cfg.iterations and fine is None:
        raise DeltaError(f"stage {stage}: fine_from {cfg.fine_from} asks for fine frames; none were given")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    device = model.background.device
    generator = torch.Generator().manual_seed(st.seed * 1000 + stage)
    optimizer = Adam(model.param_groups(cfg.lr), eps=1e-12)
    base_lr = [g["lr"] for g in optimizer.param_groups]  # before a resume loads the decayed ones
    start, rows = 0, []
    ckpt = out_dir / CHECKPOINT
    key = fingerprint(stage, st, data, origin, model)
    state = load_checkpoint(out_dir, key, stage, device)
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        generator.set_state(state["generator"].cpu())  # map_location moved it
        start, rows = state["step"], state["rows"]
    warmup_end = cfg.nerf_warmup if stage == 1 and model.nerf is not None else 0  # steps before it: NeRF alone
    plateau = find_plateau([r["psnr"] for r in rows[:start]], cfg.plateau_window, cfg.plateau_gain, warmup_end)
    if state is not None:
        if start >= cfg.end(plateau):
            log.info("stage %d: %s holds this run's last step (%d): the stage is finished; writing it out "
                     "without training (delete %s to train from scratch)", stage, ckpt, start, out_dir)  # fmt: skip
        else:
            log.info("stage %d: resuming from %s at step %d", stage, ckpt, start)
    else:
        _start_occupancy(model, st, stage)
    skin_color = data.skin_color.to(device)
    faces = face_targets(data, st, device)
    tracks = stage_tracks(model, data, st, stage)
    if start < warmup_end:
        log.info("stage 1: steps %d-%d train the NeRF alone on the whole person (rays through the mesh, from the "
                 "central %.0f%% of the person box)", start + 1, warmup_end, 100 * cfg.nerf_warmup_crop)  # fmt: skip
    t0, seen = time.time(), 0
    before = rows[-1].get("seconds", 0.0) if rows else 0.0  # wall time of the runs this one resumes
    progress = Progress(f"stage {stage}", cfg.end(plateau), start)
    limit = cfg.iterations if max_steps is None else max_steps
    step = start
    while step < min(cfg.end(plateau), limit):
        end = min(cfg.end(plateau), limit)
        warm = step < warmup_end
        for g, lr in zip(optimizer.param_groups, base_lr):
            if warm and g.get("name") == "nerf":
                lr = cfg.lr.get("nerf_warmup") or lr
            g["lr"] = lr * cfg.lr_factor(step, plateau)
        frame = int(data.train[torch.randint(len(data.train), (1,), generator=generator)])
        crop = cfg.nerf_warmup_crop if warm else 1.0
        source = fine if step >= cfg.fine_step() else None
        batch = _to(
            rays_at(data, source, frame, cfg.rays, generator, cfg.patch if semantic else 0, crop, cfg.edge_rays), device
        )
        _maybe_update_occupancy(model, st, stage, step)
        if model.nerf is not None and model.spec.nerf.density_noise > 0:  # a function of the step: resumes exact
            model.nerf.set_noise(model.spec.nerf.noise_at(step), _step_seed(st, stage, step) + 7)
        timeless = False  # with a time-reading F_e, some steps train its time-free input
        if model.deformation is not None and model.spec.time_freqs and st.time_dropout > 0:
            timeless = bool(torch.rand((), generator=generator) < st.time_dropout)
        if warm:
            terms, r = nerf_only_terms(model, batch, st, generator)
        else:
            face = None if faces is None else (faces[0], faces[1][frame])
            terms, r = loss_terms(model, batch, st, skin_color, semantic, generator, timeless, face)
            partners = tracks.partners(frame, TRACK_LEAST) if tracks is not None and not timeless else None
            if partners is not None and len(partners):
                terms["track"] = track_term(model, tracks, frame, partners, generator)
        loss = L.total(terms, st.weights)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        model.mask_frozen_pose_gradient()
        with frame_locked(model.per_frame_parameters(), frame):
            optimizer.step()
        seen += 1
        seen_layers = {}
        if not warm and r.layer_masks is not None:
            seen_layers = layers_seen(r.layer_masks, model.nerf.names, batch.exterior, batch.hair)
        logged = _read_back(loss, ((r.rgb.detach() - batch.rgb) ** 2).mean(), *terms.values(), *seen_layers.values())
        rows.append({"step": step + 1, "loss": logged[0], "psnr": _psnr_of(logged[1]),
                     "samples": r.samples_evaluated, "seconds": round(before + time.time() - t0, 3),
                     **({"warmup": float(warm)} if warmup_end else {}),
                     **dict(zip([*terms, *seen_layers], logged[2:]))})  # fmt: skip
        if (step + 1) % cfg.log_every == 0 or step + 1 == end:
            row = rows[-1]
            progress.report(
                step + 1, f"loss {row['loss']:.4f} psnr {row['psnr']:.2f} dB {seen / (time.time() - t0):.2f} it/s"
            )
        if (step + 1) % cfg.checkpoint_every == 0 or step + 1 == end:
            save_checkpoint(ckpt, model, optimizer, step + 1, generator, rows, key)
        if cfg.preview_every and ((step + 1) % cfg.preview_every == 0 or step + 1 == cfg.end(plateau)):
            write_preview(model, data, int(data.train[0]), out_dir / "previews" / f"step_{step + 1:06d}.png")
        step += 1
        if plateau is None and cfg.plateau_window and step % cfg.plateau_window == 0:
            plateau = find_plateau([r["psnr"] for r in rows], cfg.plateau_window, cfg.plateau_gain, warmup_end)
            if plateau is not None:
                progress.total = cfg.end(plateau)
                log.info("stage %d: the training-ray PSNR gained less than %g dB over the last %d steps: converged "
                         "at step %d; annealing the learning rates to %g x over %d steps (stops at step %d of %d)",
                         stage, cfg.plateau_gain, cfg.plateau_window, plateau, cfg.lr_final, cfg.end(plateau) - plateau,
                         cfg.end(plateau), cfg.iterations)  # fmt: skip
    if model.nerf is not None:
        model.nerf.set_noise(0.0)  # the trained model renders without noise
    losses = pd.DataFrame(rows)
    with atomic_path(out_dir / "losses.csv") as tmp:
        losses.to_csv(tmp, index=False)
    return StageResult(step, time.time() - t0, losses)


def _step_seed(st: TrainSettings, stage: int, step: int) -> int:
    """A seed of the run, stage and step alone: what a step draws outside the shared generator
    (occupancy jitter, density noise) is the same after a resume."""
    return st.seed * 1_000_003 + stage * 100_003 + step


def _start_occupancy(model: HybridAvatar, st: TrainSettings, stage: int) -> None:
    """A fresh stage 1 starts with every cell occupied; stage 2 from stage 1's grid, grown by F_e's reach."""
    occ = model.occupancy
    if occ is None:
        return
    if stage == 2 and st.avatar.render.occupancy.carry and occ.carry_over():
        log.info("stage 2: starting from stage 1's occupancy grid grown by %d cells, %.1f%% of cells occupied",
                 occ.dilation, 100 * occ.fraction())  # fmt: skip
        return
    occ.reset()
    render = st.avatar.render
    start = occupancy_start(render, stage, occ.shell_reach)
    if start < render.occupancy.warmup:
        log.info("stage %d: the occupancy grid in use from step %d, the body's shell of cells (%.2f m) kept until "
                 "step %d (the room, %.2f m, reaches past twice it)", stage, start, occ.shell_reach,
                 render.occupancy.warmup, render.max_dist)  # fmt: skip


def occupancy_start(render: RenderSettings, stage: int, shell_reach: float) -> int:
    """The step of a stage's first occupancy update: ``early`` where the grid starts young (stage 1, or a
    stage 2 not ``carry``-ing stage 1's grid) and more than half the room (``render.max_dist``, the scene's
    reach) lies beyond ``shell_reach``, how far the body's shell of cells that the early updates keep may
    reach (a narrower room's cells past the shell are the garment's and hair's outer ones, with little empty
    space left to skip); else ``warmup``."""
    occ = render.occupancy
    young = stage == 1 or not occ.carry
    if occ.early and young and render.max_dist > 2 * shell_reach:
        return min(occ.early, occ.warmup)
    return occ.warmup


def _maybe_update_occupancy(model: HybridAvatar, st: TrainSettings, stage: int, step: int) -> None:
    """From :func:`occupancy_start` on, every ``update_every`` steps (a function of the step alone: resumes
    stay exact); before ``warmup`` the body's shell of cells stays occupied."""
    occ = st.avatar.render.occupancy
    if model.occupancy is None:
        return
    start = occupancy_start(st.avatar.render, stage, model.occupancy.shell_reach)
    if step < start or (step - start) % occ.update_every:
        return
    model.update_occupancy(seed=_step_seed(st, stage, step), early=step < occ.warmup)
    if step in (start, occ.warmup) or (step - start) % (occ.update_every * 16) == 0:
        log.info("stage %d step %d: occupancy grid %s, %.1f%% of cells occupied", stage, step,
                 "x".join(map(str, model.occupancy.shape)), 100 * model.occupancy.fraction())  # fmt: skip


@contextlib.contextmanager
def frame_locked(params: list[torch.Tensor], frame: int):
    """Only ``frame``'s slice of per-frame parameters may change in this step.

    Adam's momentum would otherwise keep moving every other frame's pose and camera, with no
    gradient there to correct the drift (frames are visited one at a time).
    """
    saved = [p.detach().clone() for p in params]
    yield
    with torch.no_grad():
        for p, old in zip(params, saved):
            keep = torch.ones(p.shape[0], dtype=torch.bool, device=p.device)
            keep[frame] = False
            p[keep] = old[keep]


def _to(batch: RayBatch, device) -> RayBatch:
    return dataclasses.replace(batch, **{f: getattr(batch, f).to(device) for f in
                                        ("pixels", "rgb", "person", "exterior", "interior", "hair")
                                        if getattr(batch, f) is not None})  # fmt: skip


def write_preview(model: HybridAvatar, data: FrameData, frame: int, path: Path) -> None:
    """[target | composite | mesh only | NeRF only] side by side."""
    img = render_image(model, frame)
    row = torch.cat([data.images[frame], img["rgb"], img["mesh"], img["nerf"]], dim=1)
    bgr = cv2.cvtColor((row.clamp(0, 1).numpy() * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR)
    with atomic_path(path) as tmp:
        cv2.imwrite(str(tmp), bgr)
