"""Validate the workflow configuration against its JSON schema before any job runs."""

from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Any

import jsonschema
import yaml

from delta import DeltaError


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


def validate_config(config: dict, schema_path: str | os.PathLike, base_dir: str | os.PathLike = ".") -> dict:
    """Return a validated copy of ``config`` with defaults filled in.

    Every schema violation is reported in one DeltaError naming the offending key;
    files the configuration requires (the SMPL-X model when selected) must exist.
    """
    schema = yaml.safe_load(Path(schema_path).read_text())
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
        for key in ("kind", "root"):
            if key not in dataset:
                raise DeltaError(f"config key 'datasets.{name}.{key}' is required for a dataset other than 'synthetic'")
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


def load_config(path: str | os.PathLike, schema_path: str | os.PathLike) -> dict:
    """Read a YAML config file and validate it; errors name the file."""
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise DeltaError(f"{path}: cannot read configuration ({exc})") from exc
    if not isinstance(raw, dict):
        raise DeltaError(f"{path}: the configuration must be a mapping of keys")
    try:
        return validate_config(raw, schema_path, base_dir=path.parent.parent)
    except DeltaError as exc:
        raise DeltaError(f"{path}: {exc}") from exc
