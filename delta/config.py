"""The workflow configuration's one validation, run before any job starts (``rules/common.smk``)
and by ``delta validate-config`` alike: the JSON schema, finite numbers everywhere, safe dataset and
subject names, every subject's synthetic spec, fit and training settings, the trade-off variants,
frame ranges against the videos they index, and the device."""

from __future__ import annotations

import copy
import math
import os
import re
from pathlib import Path
from typing import Any

import jsonschema
import yaml

from delta import DeltaError
from delta.fields import LAYERS


def _key(path) -> str:
    return ".".join(str(p) for p in path) or "<top level>"


def _fill_defaults(schema: dict, instance: Any) -> Any:
    """Insert the schema's ``default`` values for missing keys, recursively."""
    if not isinstance(instance, dict) or schema.get("type") != "object":
        return instance
    for name, sub in schema.get("properties", {}).items():
        if name not in instance and "default" in sub:
            instance[name] = copy.deepcopy(sub["default"])
        if name in instance:
            _fill_defaults(sub, instance[name])
    extra = schema.get("additionalProperties")
    if isinstance(extra, dict):
        for name, value in instance.items():
            if name not in schema.get("properties", {}):
                _fill_defaults(extra, value)
    return instance


def _describe(error: jsonschema.ValidationError) -> str:
    key = _key(error.absolute_path)
    if error.validator == "additionalProperties":
        allowed = sorted(error.schema.get("properties", {}))
        extra = sorted(set(error.instance) - set(allowed))
        hint = f"; allowed keys: {allowed}" if allowed else ""
        return f"config key '{key}': unknown key(s) {extra}{hint}"
    return f"config key '{key}': {error.message}"


def _inject(node: Any) -> Any:
    """Replace each ``{$settings: module.Class}`` of a schema by that dataclass's generated schema
    (``defaults: false`` leaves the defaults out: a section that overrides another)."""
    if isinstance(node, dict) and "$settings" in node:
        import importlib

        from delta.settings import section_schema

        module, name = node["$settings"].rsplit(".", 1)
        out = section_schema(getattr(importlib.import_module(module), name), defaults=node.get("defaults", True))
        if "description" in node:
            out["description"] = node["description"]
        return out
    if isinstance(node, dict):
        return {k: _inject(v) for k, v in node.items()}
    return node


def load_schema(path: str | os.PathLike) -> dict:
    """The workflow's config schema: the YAML file with its typed sections generated from their dataclasses."""
    return _inject(yaml.safe_load(Path(path).read_text()))


def validate_config(config: dict, schema_path: str | os.PathLike, base_dir: str | os.PathLike = ".") -> dict:
    """Return a validated copy of ``config`` with defaults filled in.

    Every schema violation is reported in one DeltaError naming the offending key;
    files the configuration requires (the SMPL-X model when selected) must exist.
    """
    schema = load_schema(schema_path)
    config = _fill_defaults(schema, copy.deepcopy(dict(config)))
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(config), key=lambda e: list(map(str, e.absolute_path)))
    if errors:
        lines = "\n  ".join(_describe(e) for e in errors)
        raise DeltaError(f"invalid configuration ({len(errors)} problem(s)):\n  {lines}")
    _check_files(config, Path(base_dir))
    return config


def _check_files(config: dict, base: Path) -> None:
    for name, dataset in config["datasets"].items():
        if name == "synthetic":
            continue
        if "kind" not in dataset:
            raise DeltaError(f"config key 'datasets.{name}.kind' is required for a dataset other than 'synthetic'")
        if dataset["kind"] == "video" and not dataset.get("root"):
            raise DeltaError(
                f"config key 'datasets.{name}.root' is required for a video dataset (the folder of its videos)"
            )
    for step in ("matting", "parsing"):
        cfg = config["preprocess"][step]
        if cfg["model"] not in ("none", "mediapipe", "default") and not (base / cfg["path"]).is_file():
            raise DeltaError(f"config key 'preprocess.{step}.path': ONNX model not found: {base / cfg['path']}. "
                             f"Download the {cfg['model']} export and give its path, or set model: none")  # fmt: skip
    body = config["body_model"]
    if body["name"] == "smplx":
        path = base / body["smplx_path"]
        if not path.is_file():
            from delta.body.smplx_loader import MISSING_HELP

            raise DeltaError(f"config key 'body_model.smplx_path': file not found: {path}. {MISSING_HELP}")


#: Where the workflow writes its People Snapshot stand-in (rules/common.smk's ``syn_ps_dir``).
SYNTHETIC_PEOPLESNAPSHOT_ROOT = "data/synthetic_ps"
#: Dataset and subject names become folder names and wildcards: letters, digits, '_' and '-'.
SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]*$")
#: The schema beside the package's checkout (an editable install or a clone).
DEFAULT_SCHEMA = Path(__file__).resolve().parents[1] / "workflow" / "schemas" / "config.schema.yaml"


def _non_finite(value: Any, path: tuple = ()) -> list[str]:
    """Keys whose value is a NaN or an infinity, anywhere in the tree."""
    if isinstance(value, float) and not math.isfinite(value):
        return [_key(path)]
    if isinstance(value, dict):
        return [k for name, v in value.items() for k in _non_finite(v, path + (name,))]
    if isinstance(value, list):
        return [k for i, v in enumerate(value) for k in _non_finite(v, path + (i,))]
    return []


def _check_names(config: dict) -> list[str]:
    out = []
    for dataset, spec in config["datasets"].items():
        for what, name, key in [("dataset", dataset, f"datasets.{dataset}")] + [
            ("subject", s, f"datasets.{dataset}.subjects.{s}") for s in spec["subjects"]
        ]:
            if not SAFE_NAME.match(str(name)):
                out.append(f"config key '{key}': {what} name {name!r} is not allowed (it names folders: letters, "
                           "digits, '_' and '-', starting with a letter or digit)")  # fmt: skip
    return out


def check_device(name: str) -> None:
    """``cuda`` needs a CUDA device that torch can see here."""
    if name == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise DeltaError("config key 'device': cuda is configured but torch sees no CUDA device on this machine "
                             "(set device: auto or cpu; a cluster run checks on its GPU nodes)")  # fmt: skip


def _video_frames(path: Path) -> int | None:
    """The frame count of a video file, None when it is absent."""
    if not path.is_file():
        return None
    from delta.data.video import probe_video

    return probe_video(path).frames


def _check_frame_ranges(config: dict, base: Path, generated: set[str]) -> list[str]:
    """Every non-synthetic subject has a ``train`` and a ``test`` range within its video."""
    from delta.data import STANDARD_SPLITS
    from delta.data.video import FRAMINGS

    out = []
    for dataset, spec in config["datasets"].items():
        kind = "synthetic" if dataset == "synthetic" else spec.get("kind")
        if kind in ("synthetic", None):
            continue
        for subject, cfg in spec["subjects"].items():
            key = f"datasets.{dataset}.subjects.{subject}"
            ranges = {**(STANDARD_SPLITS.get(subject, {}) if kind == "peoplesnapshot" else {}), **(cfg or {})}
            allowed = {"train", "test", "framing"} if kind == "video" else {"train", "test"}
            unknown = sorted(set(ranges) - allowed)
            if unknown:
                out.append(f"config key '{key}': unknown key(s) {unknown}; allowed: {sorted(allowed)}")
            if ranges.get("framing", "full") not in FRAMINGS:
                out.append(f"config key '{key}.framing': '{ranges['framing']}'; expected one of {list(FRAMINGS)} "
                           "(head: a head-and-shoulders close-up, its face tracked)")  # fmt: skip
            missing = [s for s in ("train", "test") if s not in ranges]
            if missing:
                out.append(f"config key '{key}': no {' and no '.join(repr(m) for m in missing)} frame range "
                           "[start, end, step] (inclusive end): evaluation scores the test frames")  # fmt: skip
                continue
            root = Path(spec["root"]) if Path(spec["root"]).is_absolute() else base / spec["root"]
            video = (root / subject if kind == "peoplesnapshot" else root) / f"{subject}.mp4"
            if kind == "peoplesnapshot" and spec["root"] not in generated:
                files = [f"{subject}.mp4", "masks.hdf5", "camera.pkl", "keypoints.hdf5"]
                missing = [f for f in files if not (root / subject / f).is_file()]
                if missing:
                    out.append(f"config key 'datasets.{dataset}.root': People Snapshot subject '{subject}' lacks "
                               f"{missing} in {root / subject} (copy the subject's folder there, or leave root "
                               "empty for the synthetic stand-in)")  # fmt: skip
                    continue
            n = None if spec["root"] in generated else _video_frames(video)
            for split in ("train", "test"):
                r = ranges[split]
                if not (
                    isinstance(r, list)
                    and len(r) == 3
                    and all(isinstance(v, int) and not isinstance(v, bool) for v in r)
                ):
                    out.append(f"config key '{key}.{split}': expected [start, end, step] (whole numbers), got {r!r}")
                elif r[0] < 0 or r[1] < r[0] or r[2] < 1:
                    out.append(f"config key '{key}.{split}': [start, end, step] = {r} is not a valid range")
                elif n is not None and r[1] >= n:
                    out.append(
                        f"config key '{key}.{split}': ends at frame {r[1]}, but {video} has {n} frames (0 to {n - 1})"
                    )
    return out


def _check_settings(config: dict) -> list[str]:
    """Each subject's synthetic spec, fit and training settings, and every trade-off variant, resolved."""
    from delta.fitting.settings import fit_config
    from delta.synthetic.spec import parse_subject
    from delta.training.presets import resolve

    out = []

    def attempt(fn, *args, **kw):
        try:
            fn(*args, **kw)
        except DeltaError as exc:
            out.append(str(exc))

    for name, raw in {**config["datasets"].get("synthetic", {}).get("subjects", {}), **config["standins"]}.items():
        attempt(parse_subject, name, raw)
    subjects = {s for spec in config["datasets"].values() for s in spec["subjects"]}
    fit, train, trade = config["fitting"], config["training"], config.get("tradeoff", {"variants": {}, "subjects": []})
    for section, named in (("fitting", fit["subjects"]), ("training", train["subjects"])):
        for s in sorted(set(named) - subjects):
            out.append(f"config key '{section}.subjects.{s}': not a configured subject ({sorted(subjects)})")
    # the sections every subject shares, once; then each subject's own keys
    before = len(out)
    attempt(fit_config, fit["settings"], where="fitting.settings")
    attempt(resolve, config["preset"], train["overrides"], where="training.overrides")
    shared_ok = len(out) == before
    for s in sorted(subjects) if shared_ok else []:
        attempt(fit_config, fit["settings"], fit["subjects"].get(s, {}), where=f"fitting (subject '{s}')")
        preset, overrides = subject_training(config, s)
        attempt(resolve, preset, *overrides, where=f"training (subject '{s}')")
    for v in sorted(set(trade.get("only") or []) - set(trade["variants"])):
        out.append(
            f"config key 'tradeoff.only': '{v}' is not a variant of tradeoff.variants ({sorted(trade['variants'])})"
        )
    for v, spec in trade["variants"].items():
        if not isinstance(spec.get("inherit_training", True), bool):
            out.append(
                f"config key 'tradeoff.variants.{v}.inherit_training': {spec['inherit_training']!r} is not true or false"
            )
        unknown = sorted(set(spec.get("subjects") or []) - subjects)
        if unknown:
            out.append(f"config key 'tradeoff.variants.{v}.subjects': {unknown} are not configured subjects")
        for s in sorted(set(trade["subjects"] or subjects) & subjects):
            preset, overrides = variant_training(config, s, v)
            attempt(resolve, preset, *overrides, where=f"tradeoff.variants.{v} (subject '{s}')")
    return out


def subject_training(config: dict, subject: str) -> tuple[str, list[dict]]:
    """(preset, [overrides...]) of a subject: the config's preset and overrides, then the subject's own."""
    own = dict(config["training"]["subjects"].get(subject, {}))
    return own.pop("preset", config["preset"]), [config["training"]["overrides"], own]


def variant_training(config: dict, subject: str, variant: str) -> tuple[str, list[dict]]:
    """(preset, overrides) of a trade-off variant on a subject: the subject's settings with the variant's
    on top; a variant with ``inherit_training: false`` (the paper reference) takes its preset and its
    own keys alone, on every subject alike."""
    spec = dict(config["tradeoff"]["variants"][variant])
    own_preset = spec.pop("preset", None)
    for k in ("subjects", "inherit_training", "stages"):
        spec.pop(k, None)
    if not config["tradeoff"]["variants"][variant].get("inherit_training", True):
        return own_preset or config["preset"], [spec]
    preset, overrides = subject_training(config, subject)
    return own_preset or preset, overrides + [spec]


#: What ``expand_standins`` tells the user once, with the line to change.
STANDIN_NOTE = (
    "datasets.{dataset}.root is empty: {dataset} runs on a synthetic stand-in in People Snapshot's layout "
    "(subjects {subjects}, scored against their ground truth), not on People Snapshot. To use your copy, set "
    "datasets.{dataset}.root to the folder holding {real}/."
)


def expand_standins(config: dict) -> dict:
    """A People Snapshot dataset without a root becomes its synthetic stand-in.

    Its subjects become ``standin-<name>`` with the stand-in's frame ranges, its root the folder the
    workflow writes their People Snapshot layout to; their synthetic specs go to ``config["standins"]``
    and the note to ``config["standin_notes"]``. Runs on the validated config (defaults filled in).
    """
    from delta.synthetic.standin import standin

    config = dict(config, standins={}, standin_notes=[])
    datasets = dict(config["datasets"])
    for name, spec in datasets.items():
        if spec.get("kind") != "peoplesnapshot" or spec.get("root"):
            continue
        subjects = {}
        for real in spec["subjects"]:
            sname, syn, ranges = standin(real, **spec.get("standin", {}))
            config["standins"][sname] = syn
            subjects[sname] = ranges
        datasets[name] = {**spec, "root": SYNTHETIC_PEOPLESNAPSHOT_ROOT, "subjects": subjects, "standin_of": dict(
            zip(subjects, spec["subjects"]))}  # fmt: skip
        config["standin_notes"].append(STANDIN_NOTE.format(dataset=name, subjects=", ".join(subjects),
                                                           real="/, ".join(spec["subjects"])))  # fmt: skip
    config["datasets"] = datasets
    return config


def subject_ref(config: dict, ref: str) -> tuple[str, str] | None:
    """(dataset, subject) that ``"dataset/subject"`` names, as the workflow knows them (a People Snapshot
    subject run on its stand-in is ``standin-<name>``); None when it names no configured subject."""
    dataset, _, subject = str(ref).partition("/")
    spec = config["datasets"].get(dataset)
    if spec is None or not subject:
        return None
    if subject in spec["subjects"]:
        return dataset, subject
    renamed = {real: name for name, real in spec.get("standin_of", {}).items()}
    return (dataset, renamed[subject]) if subject in renamed else None


def tracks_face(config: dict, dataset: str, subject: str) -> bool:
    """A subject whose face is tracked and modelled with expressions: a video's head close-up (``framing:
    head``) or a synthetic talking face (``expressions`` other than ``none``)."""
    spec = config["datasets"][dataset]["subjects"].get(subject) or {}
    if dataset == "synthetic":
        return spec.get("expressions", "none") != "none"
    return config["datasets"][dataset].get("kind") == "video" and spec.get("framing") == "head"


def motion_source(config: dict, name: str) -> tuple[str, str] | str:
    """Where the configured motion ``name`` comes from: (dataset, subject) of a subject whose fitted motion
    it is, or the path of a motion file."""
    source = config["applications"]["motions"][name]
    return subject_ref(config, source) or source


def _exterior_parts(source: str) -> tuple[str, list[str]]:
    """``"dataset/subject"`` or ``"dataset/subject:hair"`` -> (the avatar, the layers named after the colon)."""
    avatar, _, layers = str(source).partition(":")
    return avatar, [x for x in layers.split("+") if x] if layers else []


def exterior_source(config: dict, name: str) -> tuple[str, str]:
    """(dataset, subject) of the avatar whose exterior the configured exterior ``name`` is."""
    return subject_ref(config, _exterior_parts(config["applications"]["exteriors"][name])[0])


def exterior_layers(config: dict, name: str) -> list[str]:
    """The layers of the avatar's exterior the configured exterior ``name`` is (``"dataset/subject:hair"``),
    [] for the whole exterior."""
    return _exterior_parts(config["applications"]["exteriors"][name])[1]


#: Each application: the config key of the names its avatars take (motions, exteriors).
APPLICATIONS = {"animate": "motions", "dress": "exteriors", "reshape": "shapes", "tryon": "exteriors",
                "reenact": "drivers"}  # fmt: skip


def application_jobs(config: dict, application: str) -> list[tuple[str, str, str]]:
    """(dataset, subject, name) of every configured job of ``application`` ("animate": name is a motion,
    "dress" and "tryon": an exterior, "reshape": a shape edit)."""
    out = []
    for avatar, names in config["applications"][application]["avatars"].items():
        dataset, subject = subject_ref(config, avatar)
        out += [(dataset, subject, m) for m in names]
    return out


def _check_applications(config: dict, base: Path) -> list[str]:
    apps, out = config["applications"], []
    for name, source in apps["motions"].items():
        key = f"config key 'applications.motions.{name}'"
        if not SAFE_NAME.match(name):
            out.append(f"{key}: motion name {name!r} is not allowed (it names a folder: letters, digits, '_' and '-')")
        elif subject_ref(config, source) is None and not (base / source).is_file():
            out.append(f"{key}: {source!r} is neither a configured 'dataset/subject' nor a motion file (npz)")
    for name, source in apps["exteriors"].items():
        key = f"config key 'applications.exteriors.{name}'"
        if not SAFE_NAME.match(name):
            out.append(
                f"{key}: exterior name {name!r} is not allowed (it names a folder: letters, digits, '_' and '-')"
            )
        elif subject_ref(config, _exterior_parts(source)[0]) is None:
            out.append(f"{key}: {source!r} names no configured subject (expected 'dataset/subject', "
                       "optionally ':clothing' or ':hair')")  # fmt: skip
        else:
            out += _check_exterior_layers(config, key, source)
    for name, source in apps["drivers"].items():
        key = f"config key 'applications.drivers.{name}'"
        if not SAFE_NAME.match(name):
            out.append(f"{key}: driver name {name!r} is not allowed (it names a folder: letters, digits, '_' and '-')")
        elif subject_ref(config, source) is None:
            out.append(f"{key}: {source!r} names no configured subject (expected 'dataset/subject')")
        elif not tracks_face(config, *subject_ref(config, source)):
            out.append(f"{key}: {source!r} is not a tracked face (framing: head, or a synthetic talking face)")
    for avatar in apps["reenact"]["avatars"]:
        ref = subject_ref(config, avatar)
        if ref is not None and not tracks_face(config, *ref):
            out.append(f"config key 'applications.reenact.avatars.{avatar}': {avatar!r} is not a tracked face "
                       "(framing: head, or a synthetic talking face): only such an avatar has expressions to drive")  # fmt: skip
    for name in apps["shapes"]:
        if not SAFE_NAME.match(name):
            out.append(f"config key 'applications.shapes.{name}': shape name {name!r} is not allowed (it names a "
                       "folder: letters, digits, '_' and '-')")  # fmt: skip
    for app, names_key in APPLICATIONS.items():
        for avatar, names in apps[app]["avatars"].items():
            key = f"config key 'applications.{app}.avatars.{avatar}'"
            if subject_ref(config, avatar) is None:
                out.append(f"{key}: {avatar!r} names no configured subject (expected 'dataset/subject')")
            unknown = [m for m in names if m not in apps[names_key]]
            if unknown:
                out.append(
                    f"{key}: {names_key} {unknown} are not in applications.{names_key} ({sorted(apps[names_key])})"
                )
    return out


def _check_exterior_layers(config: dict, key: str, source: str) -> list[str]:
    """An exterior of some layers names known layers of an avatar trained in layers (``layers: split``)."""
    avatar, layers = _exterior_parts(source)
    if not layers:
        return []
    unknown = sorted(set(layers) - set(LAYERS))
    if unknown or len(set(layers)) != len(layers):
        return [f"{key}: {source!r}: the layers after ':' are one or more of {list(LAYERS)} joined by '+'"]
    from delta.training.presets import resolve

    subject = subject_ref(config, avatar)[1]
    preset, overrides = subject_training(config, subject)
    if resolve(preset, *overrides).layers != "split":
        return [f"{key}: {source!r} takes a layer of {avatar}'s exterior, which is trained as one NeRF: set "
                f"training.subjects.{subject}.layers: split (or training.overrides.layers)"]  # fmt: skip
    return []


def data_source(config: dict, dataset: str) -> str:
    """What a dataset's figures were measured on, for the ``source`` column of its metrics."""
    spec = config["datasets"][dataset]
    kind = "synthetic" if dataset == "synthetic" else spec.get("kind")
    if spec.get("standin_of"):
        return "synthetic stand-in of People Snapshot (no copy configured)"
    return {"synthetic": "synthetic (generated, ground truth)", "peoplesnapshot": "People Snapshot",
            "video": "video"}[kind]  # fmt: skip


def validate_workflow_config(config: dict, schema_path: str | os.PathLike = DEFAULT_SCHEMA,
                             base_dir: str | os.PathLike = ".", device: bool = True,
                             generated_roots: tuple[str, ...] = ()) -> dict:  # fmt: skip
    """The whole check of a workflow configuration; returns it with defaults filled in.

    Every problem found is listed in one DeltaError. ``device`` checks that a configured CUDA device
    exists here (off for cluster submission); ``generated_roots`` are dataset roots the workflow writes
    itself (their videos do not exist yet).
    """
    config = expand_standins(validate_config(config, schema_path, base_dir))
    problems = [f"config key '{k}': {v} is not a finite number" for k, v in
                ((k, "NaN or infinity") for k in _non_finite(config))]  # fmt: skip
    problems += _check_names(config)
    if not problems:
        problems += _check_settings(config)
        generated = set(generated_roots) | ({SYNTHETIC_PEOPLESNAPSHOT_ROOT} if config["standins"] else set())
        problems += _check_frame_ranges(config, Path(base_dir), generated)
        problems += _check_applications(config, Path(base_dir))
    if device:
        try:
            check_device(config["device"])
        except DeltaError as exc:
            problems.append(str(exc))
    if problems:
        lines = "\n  ".join(problems)
        raise DeltaError(f"invalid configuration ({len(problems)} problem(s)):\n  {lines}")
    return config


def _read(path: Path) -> dict:
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise DeltaError(f"{path}: cannot read configuration ({exc})") from None
    if not isinstance(raw, dict):
        raise DeltaError(f"{path}: the configuration must be a mapping of keys")
    return raw


def _update(base: dict, over: dict) -> dict:
    """Snakemake's merge of config files given in order: mappings merge, anything else is replaced."""
    out = dict(base)
    for k, v in over.items():
        out[k] = _update(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def load_config(path: str | os.PathLike | list, schema_path: str | os.PathLike = DEFAULT_SCHEMA,
                device: bool = True) -> dict:  # fmt: skip
    """Read one YAML config file, or several merged in order as ``--configfile A B`` merges them, and
    validate the result as the workflow does; errors name the file(s). Relative paths in it are taken
    from the folder above the first file's (a config/ folder in a checkout)."""
    paths = [Path(p) for p in (path if isinstance(path, (list, tuple)) else [path])]
    raw: dict = {}
    for p in paths:
        raw = _update(raw, _read(p))
    base = paths[0].resolve().parent.parent
    try:
        return validate_workflow_config(raw, schema_path, base_dir=base, device=device,
                                        generated_roots=(SYNTHETIC_PEOPLESNAPSHOT_ROOT,))  # fmt: skip
    except DeltaError as exc:
        raise DeltaError(f"{' + '.join(map(str, paths))}: {exc}") from None
