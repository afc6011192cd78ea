"""A subject's scene analysis: what its capture requires modelled, with the evidence for each decision.

From the frame record (person, clothing and hair masks) and the init fit, before training:

- ``exterior``: whether there is clothing or hair to model at all (a NeRF), from the share of the
  person's pixels the parsing calls clothing or hair;
- ``capture``: the framing, ``full`` or ``upper`` (head and shoulders), from how much of the fitted
  lower body is ever inside the image (:mod:`delta.scene.framing`);
- ``render.max_dist``: the room the exterior gets around the body, from how far the person's
  silhouette reaches beyond the fitted body per body region (:mod:`delta.scene.reach`), with a margin;
  never less than the preset's own;
- ``render.shell``: for a head-and-shoulders capture, the soft shell at the measured reach × (1 + MARGIN):
  the room has the preset's floor (10 cm) where the silhouette shows the exterior 1-2 cm from the body,
  and no frame of a frontal video tells how deep along a ray the hair or a collar lies; the shell puts
  it nearest the body the frames allow (the short-haired talker's held-out expressions and turns +2.0
  dB, its views +0.1 dB: docs/heads.md). Full bodies get none: not yet measured there;
- ``render.samples``: the samples a ray needs to cross that room at the preset's sample spacing, and
  at least one per :data:`SAMPLE_PIXELS` of a training pixel's footprint at the body (a pixel of 512²
  frames is 3.9 mm on a full body, 1.6 mm on a head and shoulders);
- ``stage1.rays``: stage 1's rays a step, where the preset allows more than its own (``stage1.max_rays``):
  the scene's samples a ray leave room in the step the preset's costliest scene makes (its rays at
  :data:`MAX_SAMPLE_FACTOR` times its samples), and at the capture's size rays buy more than samples do
  (tight at 512²: twice the rays +0.3 dB on held-out views, twice the samples +0.1 dB);
- ``resolution``: the training frames' size, the capture's crop (a step's cost does not depend on it,
  the figures are scored at the capture's size, and trained at 512² rather than 128² the held-out views
  of tight, loose and upper gained perceptual detail, ST-LPIPS 13-41 % lower, their PSNR moving -0.8 to
  +0.6 dB), unless the frames would not fit :data:`FRAME_BUDGET` bytes;
- ``stage2.length_factor``: stage 2's length as a multiple of the configured one, the room over the
  preset's: stage 2 learns the exterior's motion about the body (F_e), and a garment hanging farther
  from the body sways farther (on the loose dress, 300 -> 600 stage-2 steps lifted held-out views
  25.5 -> 26.3 dB; a T-shirt's stage 2 keeps the configured length);
- ``nerf.color_cell``: the exterior's colour cells, :data:`~delta.scene.pattern.CELL_PIXELS` training
  pixels' footprint at the body where a colour grid of the preset's cells draws the exterior's pattern
  (its clothing or its hair, in the capture's frames) no better than :data:`~delta.scene.pattern.PATTERN_DB`
  (:mod:`delta.scene.pattern`): dots, checks and prints get cells as fine as the frames resolve, a plain
  garment keeps the preset's;
- ``weights`` and ``semantic``: for a tracked face (the init fit tracked its expressions: a talking head),
  the paper's head weights where they differ from its body weights (:data:`HEAD_WEIGHTS`: the stage-2
  semantic term 30 times the body's, the hidden skin's pull to the visible skin colour a tenth) and the
  semantic loss that weight belongs to (:data:`HEAD_SEMANTIC`: the perceptual loss, not the body's ID-MRF);
- ``mouth_shade``: for a tracked face whose training frames open the mouth, the colour inside their inner
  lips against the skin's, a shade a channel (:mod:`delta.scene.mouth`): the mouth's inside starts at
  the capture's own colour, not the preset's shadow.

Written to ``results/{dataset}/{subject}/scene.json`` and read by both training stages: a decision
applies where the user's config does not set that key itself (``training.overrides`` or
``training.subjects.{name}``); an ``auto`` ``exterior`` or ``capture`` takes the decision.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import torch

from delta import DeltaError
from delta.body.lbs import lbs
from delta.body.model import REGION_NAMES, load_body_model
from delta.cameras.models import metres_per_pixel
from delta.data.frames import BYTES_PER_PIXEL, load_frames
from delta.data.record import FrameRecord
from delta.geometry.raymesh import ray_mesh_hits
from delta.io import save_json
from delta.models.image import pixel_grid
from delta.models.avatar import canonical_vertices, exterior_box, modelled_vertices
from delta.models.init import load_init
from delta.scene.framing import MAX_LOWER_IN_VIEW, frame_camera, framed_vertices, lower_body_in_view
from delta.scene.mouth import mouth_shade
from delta.scene.pattern import CELL_PIXELS, PATTERN_DB, colour_cell, colour_why, exterior_ceilings
from delta.scene.reach import Beyond, beyond_body, region_reach
from delta.scene.settings import FRAME_BUDGET, HEAD_SEMANTIC, HEAD_WEIGHTS

log = logging.getLogger(__name__)

#: Image size (pixels a side) the analysis measures at, and how many training frames it looks at.
SIZE, FRAMES = 256, 16
#: The percentile of a region's beyond-the-body distances taken as its reach, and the smallest share
#: of all beyond pixels a region must hold to count.
PERCENTILE, MIN_REGION_SHARE = 98.0, 0.02
#: The room given is the measured reach × (1 + MARGIN) + PAD (a silhouette shows the reach sideways
#: only: the margin covers what faces the camera), at most MAX_ROOM metres.
MARGIN, PAD, MAX_ROOM = 0.25, 0.02, 0.6
#: Captures whose exterior gets the soft shell (``render.shell``) at the reach × (1 + MARGIN).
SHELL_CAPTURES = ("upper",)
#: At most this many times the preset's samples a ray.
MAX_SAMPLE_FACTOR = 4
#: A ray's samples lie at most this many training pixels' footprint apart (at the body's depth). Trained
#: at the capture's 512² (``benchmarks/samples_at_capture.csv``, stage 1, 2 cores): tight (3.9-mm pixels)
#: 27.66 dB with fast's 16 samples (6.3 mm apart), 28.34 with 24 and 28.49 with 32, in the same time;
#: upper (1.6-mm pixels) 21.53 with 16, 22.53 with 32 (+13 % time) and 22.78 with 64 (+55 %).
SAMPLE_PIXELS = 1.0
#: At most this many times the preset's stage-2 steps.
MAX_STAGE2_FACTOR = 3
#: Below this share of exterior pixels (of the person, over the analysed frames) there is no NeRF.
MIN_EXTERIOR_FRACTION = 0.01


@torch.no_grad()
def body_view(body, init, frame: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fitted body of a frame ray-cast into an n×n image: silhouette (bool), region per pixel,
    metres per pixel at the body's depth (pinhole: depth / focal length; orthographic: constant)."""
    out = lbs(body, init.betas[None].float(), init.poses[frame : frame + 1].float(),
              transl=init.transl[frame : frame + 1].float())  # fmt: skip
    verts = out.vertices[0]
    cam = frame_camera(init.camera, frame, n)
    pixels = pixel_grid(n)
    origins, dirs = cam.rays(pixels)
    hits = ray_mesh_hits(verts, body.faces, origins.float(), dirs.float())
    regions = body.regions[body.faces[hits.face.clamp_min(0), 0]]
    mpp = metres_per_pixel(cam, (origins + hits.t[:, None].clamp_min(0) * dirs).double()).float()
    shape = (n, n)
    return hits.hit.reshape(shape).numpy(), regions.reshape(shape).numpy(), mpp.reshape(shape).numpy()


def exterior_shares(record: str | Path, frames: list[int]) -> dict[str, float]:
    """Share of the person's pixels the record's clothing and hair masks cover, over ``frames``."""
    with FrameRecord(record) as rec:
        person = sum(float((rec.h5["person"][f] > 127).sum()) for f in frames)
        return {m: round(sum(float(((rec.h5[m][f] > 0) & (rec.h5["person"][f] > 127)).sum()) for f in frames)
                         / max(person, 1.0), 4)
                for m in ("clothing", "hair") if m in rec.h5}  # fmt: skip


def room_and_samples(reach: float, preset_room: float, preset_samples: int,
                     footprint: float = 0.0) -> tuple[float, int]:  # fmt: skip
    """The exterior's room (m) for a measured reach, never below the preset's, and the samples a ray
    needs to cross it: at the preset's spacing (preset samples per preset room), and no sparser than
    :data:`SAMPLE_PIXELS` training pixels' footprint (``footprint`` m a pixel at the body; 0: not known)."""
    room = min(max(reach * (1 + MARGIN) + PAD, preset_room), MAX_ROOM)
    samples = math.ceil(preset_samples * room / preset_room - 1e-9)
    if footprint > 0:
        samples = max(samples, math.ceil(room / (SAMPLE_PIXELS * footprint) - 1e-9))
    return round(room, 3), int(min(max(samples, preset_samples), MAX_SAMPLE_FACTOR * preset_samples))


def step_budget(preset_rays: int, preset_samples: int) -> int:
    """The samples of the preset's costliest step: its rays at :data:`MAX_SAMPLE_FACTOR` × its samples a ray."""
    return preset_rays * MAX_SAMPLE_FACTOR * preset_samples


def step_rays(samples: int, preset_samples: int, preset_rays: int, max_rays: int) -> int:
    """Stage 1's rays a step for ``samples`` a ray: as many as keep the step within :func:`step_budget`, at
    least the preset's rays and at most ``max_rays`` (one at or below ``preset_rays`` keeps the preset's)."""
    budget = step_budget(preset_rays, preset_samples)
    return int(min(max(budget // max(samples, 1), preset_rays), max(max_rays, preset_rays)))


def stage2_factor(room: float, preset_room: float) -> float:
    """Stage 2's length as a multiple of the configured one for an exterior's room: the room over the
    preset's (at least 1, at most :data:`MAX_STAGE2_FACTOR`)."""
    return round(min(max(room / preset_room, 1.0), MAX_STAGE2_FACTOR), 3)


def shell_start(reach: float, capture: str) -> float:
    """The soft shell's start (m; 0: none) for a measured ``reach`` (m) and ``capture``: the reach × (1 +
    MARGIN) for the :data:`SHELL_CAPTURES`, none for others or where nothing reaches beyond the body."""
    if capture not in SHELL_CAPTURES or reach <= 0:
        return 0.0
    return round(reach * (1 + MARGIN), 3)


def training_resolution(crop: int, frames: int, budget: int = FRAME_BUDGET) -> int:
    """The training frames' size: the capture's crop (``crop`` pixels a side), or, where ``frames`` of it
    would hold more than ``budget`` bytes, the largest multiple of 16 that fits (at least 16)."""
    fits = math.isqrt(budget // (BYTES_PER_PIXEL * max(frames, 1)))
    return crop if crop <= fits else max(16, fits // 16 * 16)


def preset_colour_cell(body, init, frames: list[int], capture: str, room: float, nerf_margin: float,
                       colour_res: int) -> tuple[float, float]:  # fmt: skip
    """(the preset's finest colour cell, the exterior box's longest side), metres: the box the avatar's
    exterior fields get (:func:`delta.models.avatar.exterior_box`: what the capture frames of what it
    models, with the room) over ``colour_res`` nodes along its longest side."""
    framed = framed_vertices(body, init.betas, init.poses, init.transl, init.camera, frames, SIZE)
    region = modelled_vertices(body, capture).cpu()
    region = region & framed if bool((region & framed).any()) else region
    box = exterior_box(canonical_vertices(body).cpu(), region, nerf_margin, room)
    longest = float((box[1] - box[0]).max())
    return longest / max(colour_res - 1, 1), longest


def pattern_evidence(record: str | Path, frames: list[int], parts: list[str], preset_cell: float,
                     footprint: float, record_mpp: float) -> dict:  # fmt: skip
    """Each exterior part's ceilings (dB) at the preset's colour cell and at :data:`CELL_PIXELS` training
    pixels' footprint, measured on ``frames`` of the record at its own size (``record_mpp`` m a pixel)."""
    cells = {"preset": preset_cell / record_mpp, "fine": CELL_PIXELS * footprint / record_mpp}
    out = {}
    with FrameRecord(record) as rec:
        images = [rec.h5["images"][f] for f in frames]
        person = [rec.h5["person"][f] > 127 for f in frames]
        for part in parts:
            masks = [(rec.h5[part][f] > 0) & p for f, p in zip(frames, person)]
            out[part] = exterior_ceilings(images, masks, cells)
    return out


def analyze(record: str | Path, init_path: str | Path, body_path: str | Path, preset_room: float,
            preset_samples: int, size: int = SIZE, frames: int = FRAMES, preset_rays: int = 0,
            max_rays: int = 0, colour_res: int = 0, nerf_margin: float = 0.3) -> dict:  # fmt: skip
    """The scene of one subject: ``{"decisions": {...}, "evidence": {...}}``. Stage 1's rays are decided
    only where ``max_rays`` exceeds ``preset_rays`` (the preset's stage 1); the exterior's colour cell only
    where ``colour_res`` (the preset's finest colour grid, nodes along its box; 0: none) is given."""
    if preset_room <= 0 or preset_samples < 1:
        raise DeltaError(
            f"scene analysis: the preset's max_dist {preset_room} and samples {preset_samples} must be > 0"
        )
    data = load_frames(record, size)
    init = load_init(init_path, data)
    body = load_body_model(body_path)
    train = np.asarray(data.train)
    picked = [int(f) for f in train[np.linspace(0, len(train) - 1, min(frames, len(train))).round().astype(int)]]
    beyond: list[Beyond] = []
    body_mpp = []  # metres a pixel of the analysis' size at the body, per frame that shows it
    for f in picked:
        sil, regions, mpp = body_view(body, init, f, size)
        beyond.append(beyond_body(sil, regions, data.person[f].numpy() > 0.5, mpp))
        if sil.any():
            body_mpp.append(float(np.median(mpp[sil])))
    per_region = region_reach(beyond, dict(enumerate(REGION_NAMES)), PERCENTILE, MIN_REGION_SHARE)
    reach = max((r["reach_m"] for r in per_region.values()), default=0.0)
    with FrameRecord(record) as rec:
        crop, n_frames = rec.size, len(rec)
    resolution = training_resolution(crop, n_frames)
    footprint = float(np.median(body_mpp)) * size / resolution if body_mpp else 0.0
    room, samples = room_and_samples(reach, preset_room, preset_samples, footprint)
    shares = exterior_shares(record, picked)
    exterior = "yes" if sum(shares.values()) >= MIN_EXTERIOR_FRACTION else "no"
    lower = lower_body_in_view(body, init.betas, init.poses, init.transl, init.camera, picked, size)
    capture = "upper" if lower is not None and lower <= MAX_LOWER_IN_VIEW else "full"
    decisions = {"exterior": exterior, "capture": capture, "resolution": resolution,
                 "render": {"max_dist": room, "samples": samples}}  # fmt: skip
    colour = None
    if exterior == "yes" and colour_res > 0 and footprint > 0:
        preset_cell, longest = preset_colour_cell(body, init, [int(f) for f in train], capture, room, nerf_margin,
                                                  colour_res)  # fmt: skip
        parts = [p for p, share in shares.items() if share >= MIN_EXTERIOR_FRACTION]
        record_mpp = float(np.median(body_mpp)) * size / crop
        ceilings = pattern_evidence(record, picked, parts, preset_cell, footprint, record_mpp)
        cell = colour_cell(ceilings, preset_cell, footprint)
        if cell > 0:
            decisions["nerf"] = {"color_cell": cell}
        colour = {"preset_cell_mm": round(1000 * preset_cell, 2), "fine_cell_mm": round(1000 * CELL_PIXELS * footprint, 2),
                  "box_m": round(longest, 3), "preset_nodes": colour_res, "pattern_db": PATTERN_DB, "parts": ceilings,
                  "why": colour_why(ceilings, preset_cell, footprint, cell)}  # fmt: skip
    shell = shell_start(reach, capture) if exterior == "yes" else 0.0
    if shell > 0:
        decisions["render"]["shell"] = shell
    if exterior == "yes":
        decisions["stage2"] = {"length_factor": stage2_factor(room, preset_room)}
    rays = step_rays(samples, preset_samples, preset_rays, max_rays) if max_rays > preset_rays > 0 else None
    if rays is not None:
        decisions["stage1"] = {"rays": rays}
    face = init.expression is not None
    if face:
        decisions["weights"] = dict(HEAD_WEIGHTS)
        decisions["semantic"] = HEAD_SEMANTIC
        shade, mouth = mouth_shade(record, train, data.skin_color.numpy())
        if shade is not None:
            decisions["mouth_shade"] = shade
    evidence = {
        "frames": picked, "size": size,
        "exterior": {"shares": shares, "min_share": MIN_EXTERIOR_FRACTION,
                     "why": f"clothing + hair cover {100 * sum(shares.values()):.1f}% of the person "
                            f"({'at least' if exterior == 'yes' else 'under'} {100 * MIN_EXTERIOR_FRACTION:g}%)"},
        "capture": {"lower_body_in_view": None if lower is None else round(lower, 4), "max_for_upper": MAX_LOWER_IN_VIEW},
        "reach": {"per_region": per_region, "reach_m": reach, "percentile": PERCENTILE,
                  "beyond_pixels": int(sum(len(b.metres) for b in beyond)),
                  "why": f"the silhouette reaches {100 * reach:.1f} cm beyond the fitted body; room "
                         f"{reach:.3f} x {1 + MARGIN:g} + {PAD:g} m, at least the preset's {preset_room:g} m"},
        "resolution": {"crop": crop, "frames": n_frames, "budget_mb": round(FRAME_BUDGET / 2**20),
                       "why": f"the capture's {crop}² crop" + ("" if resolution == crop else
                              f" would not fit {FRAME_BUDGET / 2**30:g} GB for {n_frames} frames: {resolution}²")},
        "samples": {"preset": preset_samples, "preset_max_dist": preset_room,
                    "pixel_footprint_mm": round(1000 * footprint, 2), "max_pixels_apart": SAMPLE_PIXELS,
                    "why": f"{preset_samples} samples per {preset_room:g} m of room, and samples at most "
                           f"{SAMPLE_PIXELS:g} of the {resolution}² training pixels apart ({1000 * footprint:.1f} mm "
                           f"at the body), at most {MAX_SAMPLE_FACTOR}x the preset's"},
    }  # fmt: skip
    if colour is not None:
        evidence["colour"] = colour
    if shell > 0:
        evidence["shell"] = {"start_m": shell, "room_m": room,
                             "why": f"a head-and-shoulders capture ({capture!r}): exterior density farther than "
                                    f"the silhouette's reach x {1 + MARGIN:g} ({100 * shell:.1f} cm) from the body "
                                    f"costs, rising to its full cost at the room's edge ({100 * room:.0f} cm)"}  # fmt: skip
    if rays is not None:
        budget = step_budget(preset_rays, preset_samples)
        evidence["rays"] = {"preset": preset_rays, "max": max_rays, "samples": samples, "step_samples": budget,
                            "why": f"{samples} samples a ray: {rays} rays keep a step within {budget} samples (the "
                                   f"preset's {preset_rays} rays at {MAX_SAMPLE_FACTOR}x its {preset_samples}), "
                                   f"between the preset's {preset_rays} and its most, {max_rays}"}  # fmt: skip
    if face:
        evidence["weights"] = {"expressions": int(init.expression.shape[1]),
                               "why": f"a tracked face ({init.expression.shape[1]} expression coefficients a "
                                      f"frame): the paper's head weights and its head's semantic loss, "
                                      f"{HEAD_SEMANTIC}"}  # fmt: skip
        evidence["mouth_shade"] = mouth
    if "stage2" in decisions:
        evidence["stage2"] = {"room_over_preset": round(room / preset_room, 3), "max_factor": MAX_STAGE2_FACTOR,
                              "why": f"stage 2 learns the exterior's motion about the body, which grows with its "
                                     f"room ({room:g} m against the preset's {preset_room:g} m): the configured "
                                     f"steps x {decisions['stage2']['length_factor']:g}"}  # fmt: skip
    log.info("scene: %s (%s; %s)", json.dumps(decisions), evidence["exterior"]["why"], evidence["reach"]["why"])
    return {"decisions": decisions, "evidence": evidence}


def write_scene(path: str | Path, scene: dict) -> None:
    save_json(path, scene)
