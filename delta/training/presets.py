"""Speed/accuracy presets of the training stages, and their overrides.

A preset is a nested dict; the config's ``training`` section and a subject's own
``training`` key are deep-merged over it (later wins), then turned into typed settings.
``paper`` follows the SCARF/DELTA settings (512², 4096 rays, 96 samples, PE(10) 8×256 NeRF).
"""

from __future__ import annotations

import copy
import dataclasses
import math

import numpy as np

from delta import DeltaError
from delta.fields.spec import FieldSpec
from delta.loss_weights import LossWeights
from delta.models.spec import AvatarSpec, shade_value
from delta.render.settings import RenderSettings
from delta.render.settings import OccupancySettings
from delta.scene.settings import NOT_READ_BY_STAGE

_GRID_NERF = {"encoding": "grid", "levels": 5, "features": 2, "base_res": 12, "max_res": 96, "depth": 2, "width": 64}
_GRID_OFFSETS = {"encoding": "grid", "levels": 3, "features": 2, "base_res": 8, "max_res": 32, "depth": 1, "width": 32}
_GRID_ALBEDO = {"encoding": "grid", "levels": 5, "features": 2, "base_res": 12, "max_res": 96, "depth": 1, "width": 64}
_PE_DEFORM = {"encoding": "pe", "num_freqs": 6, "depth": 3, "width": 64}
# stage 2 goes on from stage 1's fields at the rates a grid preset's stage 1 ends at (the default rates
# times its lr_final 0.1: a fresh Adam at the full rates shook the trained grids, tight's held-out views
# lost 0.45 dB in stage 2: benchmarks/stage2_rates.csv); its new F_e learns at 1e-3: at the full NeRF rate
# its ReLU head died (gen2: 1 of 64 last-layer units left after 800 steps, none after 3000) and it never
# learned a garment's motion (benchmarks/deformation_rate.csv, docs/method.md)
_STAGE2_LR = {"nerf": 1e-3, "fields": 5e-4, "deformation": 1e-3}

PRESETS: dict[str, dict] = {
    "fast": {
        "resolution": 128,
        "nerf": _GRID_NERF,
        "offsets": _GRID_OFFSETS,
        "albedo": _GRID_ALBEDO,
        "deformation": _PE_DEFORM,
        # the grid in use from step 20 where the room is wide, the body's 5-cm shell kept until step 100 (loose
        # at 512²: stage 1 -25 % time, the same held-out PSNR; not on tight's or the dancer's narrower rooms,
        # where it saved nothing: benchmarks/held_out_front_capture.csv)
        "render": {"samples": 16, "sil_sigma": 0.5, "max_dist": 0.1, "occupancy": {"enabled": True, "early": 20}},
        "freeze_rest": 1e-6,
        # stage 1 stops once its training-ray PSNR has flattened (benchmarks/plateau_stop.csv, at 512²:
        # upper 580 steps, +0.1 dB and -20 %; loose 680, -0.1 dB and -8 %; tight never flattened)
        # up to twice the rays where the scene's samples leave room (tight at 512²: held-out views +0.34 dB,
        # poses +0.49 dB refined, stage 1 +20 % time; benchmarks/scene_rays.csv)
        "stage1": {"iterations": 800, "rays": 4096, "max_rays": 8192, "lr_final": 0.1, "plateau_window": 100},
        # stage 2 too (benchmarks/plateau_stop_stage2.csv, at 512²: gen4 900 -> 290 steps, gen2 666 -> 267,
        # loose 873 -> 388; held-out views and poses within 0.04 dB, stage 2's time -57 to -69 %)
        "stage2": {
            "iterations": 300,
            "rays": 2048,
            "patch": 32,
            "lr_final": 0.1,
            "lr": _STAGE2_LR,
            "plateau_window": 100,
        },
        "dynamics": {"time_freqs": 6},
    },
    "balanced": {
        "resolution": 256,
        "nerf": {**_GRID_NERF, "levels": 6, "max_res": 192},
        "offsets": _GRID_OFFSETS,
        "albedo": {**_GRID_ALBEDO, "levels": 6, "max_res": 192},
        "deformation": _PE_DEFORM,
        # the occupancy grid: both stages 29 % sooner for the same image (tight at 512², 877 s against
        # 1241 s, 29.61 against 29.54 dB on held-out views: benchmarks/tradeoff_tight_512.csv)
        "render": {"samples": 32, "sil_sigma": 1.0, "max_dist": 0.1, "occupancy": {"enabled": True}},
        "stage1": {"iterations": 2500, "rays": 4096, "lr_final": 0.1},
        "stage2": {
            "iterations": 800,
            "rays": 2048,
            "patch": 48,
            "lr_final": 0.1,
            "lr": _STAGE2_LR,
        },
        "dynamics": {"time_freqs": 6},
    },
    "paper": {
        "resolution": 512,
        # SCARF's density: ReLU of raw plus noise (std 1 decaying to 0 over 5000 steps) while training
        "nerf": {
            "encoding": "pe",
            "num_freqs": 10,
            "depth": 8,
            "width": 256,
            "skip": 4,
            "density_activation": "relu",
            "density_noise": 1.0,
            "density_noise_steps": 5000,
        },
        "offsets": {"encoding": "pe", "num_freqs": 6, "depth": 4, "width": 128},
        "albedo": {"encoding": "pe", "num_freqs": 10, "depth": 6, "width": 256, "skip": 3},
        "deformation": {"encoding": "pe", "num_freqs": 6, "depth": 6, "width": 128},
        "render": {"samples": 96, "sil_sigma": 2.0, "box_margin": 0.3, "max_dist": 10.0},
        # SCARF trains its NeRF alone on the whole person first (its stage 0 at 5e-4, 400 precrop
        # steps), then the hybrid at a NeRF rate of 1e-4: a fresh PE NeRF meeting the hybrid
        # objective's clothing mask collapses to σ = 0 in ~25 steps, and so does one carried into
        # it at 5e-4 (benchmarks/density_collapse.py, docs/tradeoff.md)
        "stage1": {
            "iterations": 50000,
            "rays": 4096,
            "lr": {"nerf": 1e-4, "nerf_warmup": 5e-4, "fields": 5e-4},
            "nerf_warmup": 400,
        },  # fmt: skip
        "stage2": {"iterations": 20000, "rays": 4096, "patch": 48, "lr": {"nerf": 1e-4, "fields": 5e-4}},
    },
}

_STAGE_DEFAULTS = {
    "iterations": 1000, "rays": 1024, "patch": 0, "checkpoint_every": 100, "preview_every": 400, "log_every": 10,
    "lr": {"fields": 5e-3, "nerf": 1e-2, "pose": 5e-4, "camera": 5e-4, "shape": 2e-3, "trajectory": 2e-3},
    "lr_final": 1.0,
}  # fmt: skip
_COMMON = {
    "seed": 0, "background": [1.0, 1.0, 1.0], "box_margin": 0.1, "offset_scale": 0.04, "nerf_margin": 0.3,
    "mouth_shade": 0.3, "semantic": "idmrf", "exterior": "auto", "weights": {}, "render": {}, "stage1": {}, "stage2": {},
    "capture": "auto", "layers": "one", "clothing_on_head": "yes", "unseen_albedo": "outside", "unseen_exterior": "mirror", "freeze": [], "freeze_rest": -1.0, "dynamics": {"time_freqs": 0, "dropout": 0.2, "pose_knots": 0},
}  # fmt: skip


@dataclasses.dataclass
class StageSettings:
    iterations: int
    rays: int
    """Rays a step (inside the person's box)."""
    patch: int
    """Side of the patch rendered for the semantic loss (0: none)."""
    checkpoint_every: int
    preview_every: int
    log_every: int
    lr: dict
    """Learning rates by group: ``fields`` (offsets, albedo), ``nerf``, ``deformation`` (F_e; default: ``nerf``'s),
    ``pose``, ``camera``, ``shape``, ``trajectory``, ``nerf_warmup``."""
    max_rays: int = 0
    """Stage 1: the most rays a step the scene analysis may give it (0: ``rays``, which it then keeps).
    Where the scene's samples a ray are fewer than the most it gives, more rays fit in the step the
    preset's costliest scene makes (:func:`delta.scene.analysis.step_rays`)."""
    lr_final: float = 1.0
    """Every learning rate decays exponentially to this fraction of itself at the last step (1: constant)."""
    nerf_warmup: int = 0
    """Stage 1 only: its first steps train the NeRF alone on the whole person (rays through the mesh,
    opacity against the person mask; SCARF's NeRF-only stage 0) before the hybrid objective, the
    NeRF at the rate ``lr["nerf_warmup"]`` (default: ``lr["nerf"]``)."""
    nerf_warmup_crop: float = 0.5
    """Rays of those steps come from this central fraction of the person box's sides (NeRF's precrop)."""
    edge_rays: float = 0.0
    """This share of a step's rays is drawn from the person's outline (two pixels either side of the
    mask's edge; :func:`delta.data.frames.sample_rays`), the rest from the person's box as usual. Off in
    every preset: on tight a quarter raised held-out PSNR by 0.3-0.6 dB and worsened ST-LPIPS from 0.027
    to 0.036 (docs/tradeoff.md, "Rays from the person's outline")."""
    plateau_window: int = 0
    """Training length from convergence (0: off, every one of ``iterations``): every this many steps the
    mean training-ray PSNR of the last window is set against the window's before; once it gains less
    than ``plateau_gain`` dB the stage has converged at its learning rate, and anneals: the rates decay to
    ``lr_final`` over ``anneal`` × ``iterations`` more steps, and it stops (never past ``iterations``)."""
    plateau_gain: float = 0.05
    """dB a window must gain over the one before for training to go on at full length."""
    anneal: float = 0.1
    """The steps after a plateau, as a fraction of ``iterations``."""
    fine_from: float = 1.0
    """Coarse to fine: from this fraction of ``iterations`` on, the rays come from the frames at
    ``fine_resolution`` (1: never). The model keeps its resolution's pixel units; a fine pixel is a
    smaller square of it."""
    fine_resolution: int = 0
    """The frames' size for the steps from ``fine_from`` (0: the frame record's own size)."""

    def fine_step(self) -> int:
        """The first step whose rays come from the fine frames (``iterations`` or more: none)."""
        return math.ceil(self.fine_from * self.iterations - 1e-9) if self.fine_from < 1 else self.iterations

    def lr_factor(self, step: int, plateau: int | None = None) -> float:
        """The learning rates' multiplier at a step (a function of the step and the plateau, which the
        loss rows give again on a resume: resumes stay exact): exponential decay to ``lr_final`` at the
        last step; after a plateau, from where it stood to ``lr_final`` at :meth:`end`."""
        base = self.lr_final ** (step / max(self.iterations - 1, 1))
        if plateau is None or step < plateau:
            return base
        f0, end = self.lr_final ** (plateau / max(self.iterations - 1, 1)), self.end(plateau)
        return f0 * (self.lr_final / f0) ** ((step - plateau) / max(end - 1 - plateau, 1))

    def end(self, plateau: int | None = None) -> int:
        """The stage's step count: ``iterations``, or the plateau's step plus the annealing steps."""
        if plateau is None:
            return self.iterations
        return min(self.iterations, plateau + math.ceil(self.anneal * self.iterations))


def find_plateau(psnr, window: int, gain: float, first: int = 0) -> int | None:
    """The first step count s (a multiple of ``window``, s ≥ first + 2·window) at which the mean of
    ``psnr[s-window:s]`` beats the mean of the window before by less than ``gain``; None when there is
    none (yet). ``psnr[i]`` is the training-ray PSNR of step i + 1; ``first`` steps are not counted
    (stage 1's NeRF-only warmup)."""
    if window <= 0:
        return None
    x = np.asarray(psnr, dtype=np.float64)
    start = first + 2 * window
    for s in range(start + (-start) % window, len(x) + 1, window):
        if x[s - window : s].mean() - x[s - 2 * window : s - window].mean() < gain:
            return s
    return None


@dataclasses.dataclass
class TrainSettings:
    preset: str
    resolution: int
    seed: int
    background: list
    box_margin: float
    """Rays are drawn inside the person's box grown by this fraction."""
    exterior: str
    """``auto`` (a NeRF only when the capture shows clothing or hair), ``yes``, ``no``."""
    semantic: str
    """Stage-2 semantic loss: ``idmrf`` (body), ``perceptual`` (head) or ``none``."""
    capture: str
    """``auto`` (``upper`` when the lower body is never in view), ``full`` or ``upper`` (no legs modelled)."""
    freeze: list
    """Joint groups (``fingers``, ``toes``, ``eyes``, ``jaw``) or joint names whose pose is not optimised."""
    freeze_rest: float
    """Also freeze joints the init leaves at rest: |pose| ≤ this (rad) in every training frame (< 0: off)."""
    avatar: AvatarSpec
    """Stage-1 architecture (no F_e)."""
    deformation: FieldSpec
    """F_e, added in stage 2."""
    weights: LossWeights
    stage1: StageSettings
    stage2: StageSettings
    raw: dict
    """The merged dict these settings came from (written beside checkpoints)."""
    time_dropout: float = 0.0
    """Stage 2 with a time-reading F_e: the share of steps rendered without the frame's time
    (teaches the time-free deformation novel poses get)."""
    layers: str = "one"
    """``one`` NeRF for the whole exterior, or ``split``: clothing and hair each their own NeRF, told
    apart by the parsing masks, where the capture shows both (else one)."""
    clothing_on_head: str = "yes"
    """With a clothing layer: ``yes`` it may hold density about the head (a hat, a hood), ``no`` none at the points
    the head's vertices carry (backward skinning's nearest vertex: a collar under a chin that tilts back
    does not rise with it), ``auto`` no where the capture's clothing covers at most
    :data:`delta.scene.framing.MAX_CLOTHING_ON_HEAD` of the fitted head's projected vertices. ``yes`` in every
    preset: on the short-haired talker ``auto`` mended the collar and raised the head region of six held-out
    frames by 0.9 dB, and lowered their whole image by 0.4 dB where the head tilted down (docs/heads.md)."""
    unseen_albedo: str = "outside"
    """The body's albedo where no training frame looked (the back of a head that never turns): ``outside`` takes
    the harmonic fill of the seen surface as it looks from outside (the exterior over its albedo: the scalp under
    short hair lends the back of the head the hair's colour), ``fill`` of the seen albedo alone
    (``delta.models.unseen``), ``field`` keeps what the albedo field extrapolates there."""
    unseen_exterior: str = "mirror"
    """The exterior's canonical space where no training frame looked (the back of a shirt that never turned away
    from the camera): ``mirror`` reads it at its mirror image through the body along the canonical front axis
    where a frame saw that and the exterior is there (``delta.models.unseen.exterior_mirror``), ``field`` keeps
    what the NeRF extrapolates."""


def stage_view(raw: dict, stage: int) -> dict:
    """The merged settings stage ``stage`` reads: ``raw`` less the other stage's own keys.

    The training rule of a stage passes this view (so Snakemake reruns a stage only when what it
    reads changes), and the stage's checkpoint fingerprint hashes it. ``resolve(preset, view)``
    gives the same settings for everything the stage reads.
    """
    if stage not in NOT_READ_BY_STAGE:
        raise DeltaError(f"stage: {stage} (expected 1 or 2)")
    return {k: copy.deepcopy(v) for k, v in raw.items() if k not in NOT_READ_BY_STAGE[stage]}


def deep_merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in (over or {}).items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


def _fields(d: dict, key: str) -> FieldSpec:
    try:
        return FieldSpec(**d[key])
    except (TypeError, ValueError) as err:
        raise DeltaError(f"training.{key}: {err}") from None


_INT, _NUM = True, False
_FIELD_RANGES = {"num_freqs": (0, 32, _INT), "levels": (1, 32, _INT), "features": (1, 64, _INT), "base_res": (1, 4096, _INT),
                 "max_res": (1, 4096, _INT), "depth": (0, 64, _INT), "width": (1, 4096, _INT), "skip": (-1, 64, _INT),
                 "color_max_res": (0, 4096, _INT), "color_levels": (0, 32, _INT), "color_cell": (0, 1, _NUM)}  # fmt: skip
#: (low, high, integer) of every number a training setting holds (high None: unbounded); keys with ``*``
#: stand for every name at that level.
RANGES = {
    "resolution": (16, 4096, _INT), "seed": (0, None, _INT), "box_margin": (0, 10, _NUM), "offset_scale": (0, 1, _NUM),
    "mouth_shade": (0, 1, _NUM), "nerf_margin": (0, 10, _NUM), "freeze_rest": (None, None, _NUM),
    "render.samples": (1, 1024, _INT), "render.k": (1, 64, _INT), "render.contact_cell": (0, 1, _NUM), "render.sigma": (1e-6, None, _NUM),
    "render.max_dist": (1e-6, None, _NUM), "render.shell": (0, None, _NUM), "render.sil_sigma": (1e-6, None, _NUM), "render.sil_k": (1, 256, _INT),
    "render.probe": (1, 4096, _INT), "render.probe_cell": (1e-5, 1, _NUM), "render.box_margin": (0, 10, _NUM),
    "render.occupancy.resolution": (4, 512, _INT), "render.occupancy.update_every": (1, None, _INT),
    "render.occupancy.threshold": (0, None, _NUM), "render.occupancy.decay": (0, 1, _NUM),
    "render.occupancy.warmup": (0, None, _INT), "render.occupancy.early": (0, None, _INT),
    "render.occupancy.early_shell": (0, None, _NUM),
    "stage*.iterations": (1, 10_000_000, _INT), "stage*.rays": (1, 1_000_000, _INT),
    "stage*.max_rays": (0, 1_000_000, _INT), "stage*.patch": (0, 512, _INT),
    "stage*.checkpoint_every": (1, None, _INT), "stage*.preview_every": (0, None, _INT), "stage*.log_every": (1, None, _INT),
    "stage*.lr.*": (1e-12, 10, _NUM), "weights.*": (0, None, _NUM), "stage*.plateau_window": (0, None, _INT),
    "stage*.plateau_gain": (None, None, _NUM), "stage*.anneal": (1e-6, 1, _NUM),
    "stage*.fine_from": (0, 1, _NUM), "stage*.fine_resolution": (0, 4096, _INT), "stage*.edge_rays": (0, 1, _NUM),
    **{f"{f}.{k}": v for f in ("nerf", "offsets", "albedo", "deformation") for k, v in _FIELD_RANGES.items()},
}  # fmt: skip


def _match(pattern: str, key: str) -> bool:
    a, b = pattern.split("."), key.split(".")
    return len(a) == len(b) and all(
        p == "*" or p == k or (p.endswith("*") and k.startswith(p[:-1])) for p, k in zip(a, b)
    )


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def check_numbers(d: dict) -> None:
    """Every number of the merged settings is finite, of the right kind and in its range (:data:`RANGES`)."""
    for key, value in _flat(d).items():
        if isinstance(value, float) and not math.isfinite(value):
            raise DeltaError(f"training.{key}: {value} is not a finite number")
        rule = next((r for pattern, r in RANGES.items() if _match(pattern, key)), None)
        if rule is None:
            continue
        for k, v in enumerate(value) if isinstance(value, (list, tuple)) else ((None, value),):  # each of a list
            _check_number(key if k is None else f"{key}[{k}]", v, rule)


def _check_number(key: str, value, rule: tuple) -> None:
    low, high, integer = rule
    if isinstance(value, bool) or not isinstance(value, int if integer else (int, float)):
        raise DeltaError(f"training.{key}: {value!r} is not {'a whole number' if integer else 'a number'}")
    if isinstance(value, float) and not math.isfinite(value):
        raise DeltaError(f"training.{key}: {value} is not a finite number")
    if (low is not None and value < low) or (high is not None and value > high):
        bounds = f">= {low}" if high is None else f"<= {high}" if low is None else f"in [{low}, {high}]"
        raise DeltaError(f"training.{key}: {value} (expected {bounds})")


#: the sections of the settings that are a dataclass's fields
_SECTIONS = {"stage1": StageSettings, "stage2": StageSettings, "render": RenderSettings, "weights": LossWeights,
             "render.occupancy": OccupancySettings,
             **{f: FieldSpec for f in ("nerf", "offsets", "albedo", "deformation")}}  # fmt: skip


def _names(cls) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def check_switches(d: dict) -> None:
    """Every on/off setting (a ``bool`` field of the render, stage and occupancy settings) is true or false:
    ``round_trip: 3`` or ``"no"`` is named, not read as on."""
    for key, value in _flat(d).items():
        section, _, name = key.rpartition(".")
        cls = _SECTIONS.get(section)
        field = next((f for f in dataclasses.fields(cls) if f.name == name), None) if cls else None
        if field is not None and field.type in ("bool", bool) and not isinstance(value, bool):
            raise DeltaError(f"training.{key}: {value!r} is not true or false")


def _check_keys(d: dict) -> None:
    """Every key of the merged settings is one the settings read; an unknown one is named with its section
    and the keys allowed there."""
    sections = {"": set(_COMMON) | {k for p in PRESETS.values() for k in p},
                "dynamics": {"time_freqs", "dropout", "pose_knots"}, **{k: _names(c) for k, c in _SECTIONS.items()}}  # fmt: skip
    for section, allowed in sections.items():
        node = d
        for part in filter(None, section.split(".")):
            node = node.get(part, {}) if isinstance(node, dict) else {}
        if not isinstance(node, dict):
            raise DeltaError(f"training.{section}: expected a mapping of keys, got {node!r}")
        unknown = sorted(set(node) - allowed)
        if unknown:
            where = f"training.{section}" if section else "training"
            raise DeltaError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(allowed)}")


def resolve(preset: str, *overrides: dict, where: str = "") -> TrainSettings:
    """The preset's settings with overrides deep-merged in order; ``where`` prefixes every error (the
    subject or variant they belong to)."""
    try:
        return _resolve(preset, *overrides)
    except DeltaError as exc:
        if where:
            raise DeltaError(f"{where}: {exc}") from None
        raise


def _resolve(preset: str, *overrides: dict) -> TrainSettings:
    if preset not in PRESETS:
        raise DeltaError(f"unknown preset '{preset}'; choose one of {sorted(PRESETS)}")
    d = deep_merge(_COMMON, PRESETS[preset])
    for o in overrides:
        if not isinstance(o or {}, dict):
            raise DeltaError(f"training settings: expected a mapping of keys, got {o!r}")
        d = deep_merge(d, o or {})
    check_numbers(d)
    check_switches(d)
    _check_keys(d)
    stages = {s: deep_merge(_STAGE_DEFAULTS, d[s]) for s in ("stage1", "stage2")}
    try:
        render = dict(d["render"])
        occupancy = OccupancySettings(**render.pop("occupancy", {}))
        render = RenderSettings(**render, occupancy=occupancy)
        weights = LossWeights(**d["weights"])
        stage = {s: StageSettings(**v) for s, v in stages.items()}
        for name, cfg in stage.items():
            if not 0 < cfg.lr_final <= 1:
                raise DeltaError(f"training.{name}.lr_final: {cfg.lr_final} (expected a fraction in (0, 1])")
            if not 0 < cfg.nerf_warmup_crop <= 1:
                raise DeltaError(
                    f"training.{name}.nerf_warmup_crop: {cfg.nerf_warmup_crop} (expected a fraction in (0, 1])"
                )
            if cfg.nerf_warmup < 0 or (name == "stage2" and cfg.nerf_warmup):
                raise DeltaError(f"training.{name}.nerf_warmup: {cfg.nerf_warmup} (steps >= 0, stage 1 only: "
                                 "stage 2 starts from stage 1's NeRF)")  # fmt: skip
        dyn = dict(d["dynamics"])
        knots = int(dyn["pose_knots"])
        if (set(dyn) - {"time_freqs", "dropout", "pose_knots"} or not 0 <= float(dyn["dropout"]) < 1
                or int(dyn["time_freqs"]) < 0 or knots < 0 or knots == 1):  # fmt: skip
            raise DeltaError(f"training.dynamics: {dyn} (keys time_freqs >= 0, dropout in [0, 1), "
                             "pose_knots 0 (off) or >= 2)")  # fmt: skip
    except TypeError as err:
        raise DeltaError(f"training settings: {err}") from None
    avatar = AvatarSpec(nerf=_fields(d, "nerf"), offsets=_fields(d, "offsets"), albedo=_fields(d, "albedo"),
                        deformation=None, offset_scale=d["offset_scale"], mouth_shade=shade_value(d["mouth_shade"]),
                        nerf_margin=d["nerf_margin"],
                        render=render, time_freqs=int(dyn["time_freqs"]), pose_knots=knots)  # fmt: skip
    if d["capture"] not in ("auto", "full", "upper"):
        raise DeltaError(f"training.capture: '{d['capture']}' (expected auto, full or upper)")
    if d["layers"] not in ("one", "split"):
        raise DeltaError(f"training.layers: '{d['layers']}' (expected one or split)")
    if d["clothing_on_head"] not in ("auto", "yes", "no"):
        raise DeltaError(f"training.clothing_on_head: {d['clothing_on_head']!r} (expected auto, yes or no)")
    if d["unseen_albedo"] not in ("outside", "fill", "field"):
        raise DeltaError(f"training.unseen_albedo: {d['unseen_albedo']!r} (expected outside, fill or field)")
    if d["unseen_exterior"] not in ("mirror", "field"):
        raise DeltaError(f"training.unseen_exterior: {d['unseen_exterior']!r} (expected mirror or field)")
    return TrainSettings(preset, d["resolution"], d["seed"], d["background"], d["box_margin"], d["exterior"],
                         d["semantic"], d["capture"], list(d["freeze"]), float(d["freeze_rest"]), avatar,
                         _fields(d, "deformation"), weights, stage["stage1"], stage["stage2"], d,
                         float(dyn["dropout"]), d["layers"], d["clothing_on_head"], d["unseen_albedo"],
                         d["unseen_exterior"])  # fmt: skip
