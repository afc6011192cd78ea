"""A synthetic subject's specification, validated before anything is rendered."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from delta import DeltaError

GARMENTS = ("tshirt", "longsleeve", "trousers", "shorts", "skirt", "dress")
PATTERNS = ("stripes", "checker", "dots", "plaid", "plain")
HAIR = ("none", "short", "long")
CAMERAS = ("pinhole", "orthographic")
FRAMINGS = ("full", "upper", "head")
MOTIONS = ("turn", "face")
EXPRESSIONS = ("none", "talk")
CODECS = ("ffv1", "mp4v")
#: garments that cover the upper / lower body; at most one of each, and a dress covers both
_UPPER, _LOWER = {"tshirt", "longsleeve", "dress"}, {"trousers", "shorts", "skirt", "dress"}


@dataclasses.dataclass(frozen=True)
class GarmentSpec:
    kind: str
    pattern: str = "stripes"
    colors: tuple[tuple[float, float, float], ...] = ((0.15, 0.3, 0.7), (0.9, 0.9, 0.85))
    thickness: float = 0.012
    """Offset of a tight garment from the skin (m)."""


@dataclasses.dataclass(frozen=True)
class DrivenSpec:
    """A subject's frame driven by another subject's face: the generated truth of a reenactment."""

    by: "SubjectSpec"
    """The driving subject: its expressions and its head motion, frame by frame."""
    anchor: int
    """The driven subject's own frame (its body, pose, place) that the driver's face moves."""
    reference: int
    """The driver's frame whose head pose means "no turn"."""


@dataclasses.dataclass(frozen=True)
class SubjectSpec:
    name: str
    seed: int = 0
    phenotype: dict[str, float] = dataclasses.field(default_factory=dict)
    """Anny phenotype values in [0, 1] (gender, age, muscle, weight, height, proportions)."""
    skin_color: tuple[float, float, float] = (0.80, 0.62, 0.52)
    garments: tuple[GarmentSpec, ...] = ()
    hair: str = "none"
    hair_color: tuple[float, float, float] = (0.18, 0.11, 0.07)
    camera: str = "pinhole"
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    camera_pitch: float = 0.0
    """Degrees the (pinhole) camera looks down on the subject from above (negative: up from below), as a
    phone held high does; the subject stays framed."""
    camera_roll: float = 0.0
    """Degrees the (pinhole) camera is rolled about its optical axis (positive: the subject appears
    turned clockwise in the image), as a hand-held phone is."""
    framing: str = "full"
    """``full``: the whole standing body in view; ``upper``: head, shoulders and chest (the top
    ``UPPER_FRAMING`` of the height), hips and legs out of view: a capture that needs no legs;
    ``head``: head and shoulders (the top ``HEAD_FRAMING``), a talking-head video's framing."""
    motion: str = "turn"
    """``turn``: the subject turns in place (``turns`` times), People Snapshot's motion; ``face``: the
    subject faces the camera and turns, nods and tilts the head, a talking-head video's motion."""
    expressions: str = "none"
    """``none``: a still, neutral face; ``talk``: the face talks, blinks and smiles (Anny's facial
    actions), and the held-out segment shows expressions the training frames never do."""
    resolution: int = 512
    turn_frames: int = 100
    novel_frames: int = 30
    turns: float = 1.0
    test_view_every: int = 5
    background: tuple[float, float, float] = (0.92, 0.93, 0.95)
    sway: float = 1.0
    """Amplitude of the non-rigid garment and hair motion (0 = rigidly skinned)."""
    codec: str = "ffv1"
    supersample: int = 2
    """Sub-samples per axis at edge pixels (2 -> 4 rays)."""
    fps: int = 30
    driven: DrivenSpec | None = None
    """Instead of its own motion, one frame per frame of another subject: the ``anchor`` frame with that
    subject's expressions and, on the neck, head and eyes, its head motion relative to its ``reference``
    frame (the truth of ``delta reenact``; its splits are the driver's)."""

    @property
    def num_frames(self) -> int:
        if self.driven is not None:
            return self.driven.by.num_frames
        return self.turn_frames + self.novel_frames


def _color(value: Any, key: str) -> tuple[float, float, float]:
    if not (isinstance(value, (list, tuple)) and len(value) == 3 and all(isinstance(c, (int, float)) for c in value)):
        raise DeltaError(f"{key}: a colour is three numbers in [0, 1], got {value!r}")
    if not all(0.0 <= c <= 1.0 for c in value):
        raise DeltaError(f"{key}: colour components must lie in [0, 1], got {value!r}")
    return tuple(float(c) for c in value)


def _garment(raw: Any, key: str) -> GarmentSpec:
    if isinstance(raw, str):
        raw = {"kind": raw}
    if not isinstance(raw, dict) or "kind" not in raw:
        raise DeltaError(f"{key}: a garment is a name or a mapping with 'kind'")
    unknown = set(raw) - {f.name for f in dataclasses.fields(GarmentSpec)}
    if unknown:
        raise DeltaError(f"{key}: unknown garment key(s) {sorted(unknown)}")
    if raw["kind"] not in GARMENTS:
        raise DeltaError(f"{key}: unknown garment '{raw['kind']}'; known: {list(GARMENTS)}")
    pattern = raw.get("pattern", "stripes")
    if pattern not in PATTERNS:
        raise DeltaError(f"{key}.pattern: unknown pattern '{pattern}'; known: {list(PATTERNS)}")
    colors = tuple(_color(c, f"{key}.colors[{i}]") for i, c in enumerate(raw.get("colors", GarmentSpec.colors)))
    if len(colors) != 2:
        raise DeltaError(f"{key}.colors: give two colours")
    thickness = float(raw.get("thickness", 0.012))
    if not 0.002 <= thickness <= 0.05:
        raise DeltaError(f"{key}.thickness: {thickness} m is outside [0.002, 0.05]")
    return GarmentSpec(kind=raw["kind"], pattern=pattern, colors=colors, thickness=thickness)


def parse_subject(name: str, raw: dict) -> SubjectSpec:
    """Validate one subject's config mapping; every error names ``name`` and the key."""
    key = f"datasets.synthetic.subjects.{name}"
    if not isinstance(raw, dict):
        raise DeltaError(f"{key}: expected a mapping")
    fields = {f.name for f in dataclasses.fields(SubjectSpec)} - {"name"}
    unknown = set(raw) - fields
    if unknown:
        raise DeltaError(f"{key}: unknown key(s) {sorted(unknown)}; allowed: {sorted(fields)}")
    kw: dict[str, Any] = dict(raw)
    for int_key, low, high in (("resolution", 32, 4096), ("turn_frames", 1, 100000), ("novel_frames", 0, 100000),
                               ("test_view_every", 2, 1000), ("seed", 0, 2**31 - 1), ("supersample", 1, 4),
                               ("fps", 1, 240)):  # fmt: skip
        if int_key in kw:
            value = kw[int_key]
            if not isinstance(value, int) or isinstance(value, bool):
                raise DeltaError(f"{key}.{int_key}: expected an integer, got {value!r}")
            if not low <= value <= high:
                raise DeltaError(f"{key}.{int_key}: {value} is outside [{low}, {high}]")
    if kw.get("turn_frames", 1) + kw.get("novel_frames", 30) < 1:
        raise DeltaError(f"{key}: zero frames")
    if "garments" in kw:
        if not isinstance(kw["garments"], list):
            raise DeltaError(f"{key}.garments: expected a list")
        kw["garments"] = tuple(_garment(g, f"{key}.garments[{i}]") for i, g in enumerate(kw["garments"]))
        kinds = [g.kind for g in kw["garments"]]
        if sum(k in _UPPER for k in kinds) > 1 or sum(k in _LOWER for k in kinds) > 1:
            raise DeltaError(f"{key}.garments: {kinds} overlap (one upper and one lower garment, or one dress)")
    for choice_key, options in (("hair", HAIR), ("camera", CAMERAS), ("codec", CODECS), ("framing", FRAMINGS),
                                ("motion", MOTIONS), ("expressions", EXPRESSIONS)):  # fmt: skip
        if choice_key in kw and kw[choice_key] not in options:
            raise DeltaError(f"{key}.{choice_key}: unknown value '{kw[choice_key]}'; known: {list(options)}")
    for color_key in ("skin_color", "hair_color", "background"):
        if color_key in kw:
            kw[color_key] = _color(kw[color_key], f"{key}.{color_key}")
    if "distortion" in kw:
        d = kw["distortion"]
        if not (isinstance(d, list) and len(d) == 5 and all(isinstance(c, (int, float)) for c in d)):
            raise DeltaError(f"{key}.distortion: five numbers (k1, k2, p1, p2, k3)")
        if max(abs(c) for c in d) > 1.0:
            raise DeltaError(f"{key}.distortion: coefficients beyond ±1 are not a lens")
        kw["distortion"] = tuple(float(c) for c in d)
    if "phenotype" in kw:
        ph = kw["phenotype"]
        labels = {"gender", "age", "muscle", "weight", "height", "proportions"}
        if not isinstance(ph, dict) or set(ph) - labels:
            raise DeltaError(f"{key}.phenotype: a mapping over {sorted(labels)}")
        if not all(isinstance(v, (int, float)) and 0.0 <= v <= 1.0 for v in ph.values()):
            raise DeltaError(f"{key}.phenotype: values must lie in [0, 1]")
    for float_key, low, high in (("turns", 0.1, 10.0), ("sway", 0.0, 5.0), ("camera_pitch", -60.0, 60.0),
                                 ("camera_roll", -90.0, 90.0)):  # fmt: skip
        if float_key in kw and not (isinstance(kw[float_key], (int, float)) and low <= kw[float_key] <= high):
            raise DeltaError(f"{key}.{float_key}: expected a number in [{low}, {high}]")
    if kw.get("camera") == "orthographic" and any(kw.get("distortion", ())):
        raise DeltaError(f"{key}.distortion: an orthographic camera has no lens distortion")
    if kw.get("camera") == "orthographic" and (kw.get("camera_pitch") or kw.get("camera_roll")):
        raise DeltaError(
            f"{key}: camera_pitch and camera_roll need the pinhole camera (the orthographic one looks along -z)"
        )
    if "driven" in kw:
        kw["driven"] = _driven(name, kw["driven"], kw, f"{key}.driven")
    return SubjectSpec(name=name, **kw)


def _driven(name: str, raw: Any, own: dict, key: str) -> DrivenSpec:
    if not isinstance(raw, dict) or set(raw) != {"by", "anchor", "reference"}:
        raise DeltaError(f"{key}: a mapping with 'by' (the driving subject), 'anchor' and 'reference' (frames)")
    by = parse_subject(f"{name}.driven.by", raw["by"])
    if by.driven is not None:
        raise DeltaError(f"{key}.by: a driving subject has its own motion (it is not driven itself)")
    if own.get("expressions", "none") != "talk" or by.expressions != "talk":
        raise DeltaError(f"{key}: both subjects need talking faces (expressions: talk)")
    own_frames = own.get("turn_frames", SubjectSpec.turn_frames) + own.get("novel_frames", SubjectSpec.novel_frames)
    for field, count in (("anchor", own_frames), ("reference", by.num_frames)):
        value = raw[field]
        if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < count:
            raise DeltaError(f"{key}.{field}: a frame in [0, {count}), got {value!r}")
    return DrivenSpec(by=by, anchor=raw["anchor"], reference=raw["reference"])


#: The keys of a subject that make its exterior (what an exterior transfer carries).
EXTERIOR_KEYS = ("garments", "hair", "hair_color")


#: The word between a subject and an application's name in the name of its generated truth.
TRUTH_WORDS = {"dress": "wears", "reshape": "shape", "reenact": "follows"}


def truth_name(application: str, subject: str, name: str) -> str:
    """The generated truth's subject name of an application job: ``tight.wears.loose-dress``,
    ``tight.shape.heavier``, ``talker.follows.short-face`` (with a '.', which no configured subject name
    has)."""
    return f"{subject}.{TRUTH_WORDS[application]}.{name}"


#: The subject keys of each exterior layer.
LAYER_KEYS = {"clothing": ("garments",), "hair": ("hair", "hair_color")}


def dressed_raw(body: dict, wearer: dict, layers: list[str] | tuple[str, ...] = ()) -> dict:
    """The subject ``body`` (its shape, skin, motion, camera: its seed) wearing ``wearer``'s garments and hair
    (``layers``: only those, ``clothing`` = its garments, ``hair`` = its hair; the body keeps its own
    other ones): the generated truth of putting the wearer's exterior on the body's avatar."""
    moved = [k for layer in layers for k in LAYER_KEYS[layer]] if layers else EXTERIOR_KEYS
    return {k: v for k, v in body.items() if k not in moved} | {k: wearer[k] for k in moved if k in wearer}


def edit_amount(key: str, value) -> tuple[bool, float]:
    """(relative, amount) of one shape-edit value: a number sets the label (or coefficient) to it, a string
    with a sign ("+0.3", "-0.2") changes it by that much; errors name the key."""
    relative = isinstance(value, str)
    text = value.strip() if relative else value
    if relative and not (text[:1] in "+-" and len(text) > 1):
        raise DeltaError(f"shape edit '{key}': {value!r} is neither a number nor a signed change such as '+0.3'")
    try:
        amount = float(text)
    except (TypeError, ValueError):
        raise DeltaError(
            f"shape edit '{key}': {value!r} is neither a number nor a signed change such as '+0.3'"
        ) from None
    if not math.isfinite(amount):
        raise DeltaError(f"shape edit '{key}': {value!r} is not a finite number")
    return relative, amount


#: The phenotype value a subject has for a label it does not set (Anny's default).
DEFAULT_PHENOTYPE = 0.5


def reshaped_raw(raw: dict, edit: dict) -> dict:
    """The subject ``raw`` with its phenotype labels set, or changed (a signed string), by ``edit`` (the rest
    unchanged, changes clamped to [0, 1]): the generated truth of a phenotype edit."""
    phenotype = dict(raw.get("phenotype", {}))
    for key, value in edit.items():
        relative, amount = edit_amount(key, value)
        base = phenotype.get(key, DEFAULT_PHENOTYPE) if relative else 0.0
        phenotype[key] = min(max(base + amount, 0.0), 1.0)
    return {**raw, "phenotype": phenotype}


def reenacted_raw(raw: dict, driver: dict, anchor: int = 0, reference: int = 0) -> dict:
    """The subject ``raw``'s frame ``anchor`` driven by the subject ``driver``'s face relative to its frame
    ``reference`` (:class:`DrivenSpec`): the generated truth of a reenactment."""
    return {**raw, "driven": {"by": driver, "anchor": anchor, "reference": reference}}
