"""The configuration reference (docs/configuration.md), generated from the config's JSON schema.

    python -m delta.config_reference > docs/configuration.md          # regenerate
    python -m delta.config_reference --check docs/configuration.md    # exit 1 if it is stale

``schema_markdown`` is pure: it walks the schema (nested ``properties``, ``additionalProperties``
that hold a schema, ``description``, ``type``, ``default``, ``enum``, bounds) and returns markdown,
one table per top-level section, one row per key path.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any


SCHEMA = Path("workflow/schemas/config.schema.yaml")
COMMAND = "python -m delta.config_reference > docs/configuration.md"
HEADER = ("key", "type", "default", "allowed", "description")
INTRO = (
    "Free-form keys are documented where they are read: a dataset subject's keys in "
    "[preprocessing](preprocessing.md) (synthetic subjects: `SubjectSpec` in `delta/synthetic/spec.py`), "
    "`fitting.settings` and `fitting.subjects.<subject>` are `FitConfig`'s fields (`delta/fitting/settings.py`, "
    "[fitting](fitting.md)), `training.overrides`, `training.subjects.<subject>` and "
    "`tradeoff.variants.<variant>` are the presets' keys (`delta/training/presets.py`)."
)


def _scalar(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null"
    if isinstance(value, str):
        plain = value and re.fullmatch(r"[A-Za-z0-9_./\-]+", value) and value not in ("true", "false", "null")
        return value if plain else json.dumps(value, ensure_ascii=False)
    return repr(value)


def _flow(value: Any) -> str:
    """A value in YAML flow style, as it would be written in config/config.yaml."""
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_scalar(k)}: {_flow(v)}" for k, v in value.items()) + "}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_flow(v) for v in value) + "]"
    return _scalar(value)


def _code(text: str) -> str:
    return f"`{text}`" if text else ""


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _prose(text: str) -> str:
    """Free text in a markdown table or paragraph: ``<name>`` would be read as an HTML tag."""
    return _cell(text).replace("<", "&lt;")


def _type(node: dict) -> str:
    t = node.get("type")
    if isinstance(t, list):
        name = " or ".join(t)
    elif t:
        name = t
    elif "enum" in node:
        kinds = sorted({type(v).__name__ for v in node["enum"]})
        name = {"str": "string", "int": "integer", "float": "number", "bool": "boolean"}.get(kinds[0], kinds[0]) \
            if len(kinds) == 1 else "any"  # fmt: skip
    else:
        name = ""
    items = node.get("items")
    if name == "array" and isinstance(items, dict) and _type(items):
        name = f"array of {_type(items)}"
    return name


def _allowed(node: dict) -> str:
    parts = []
    enum = node.get("enum")
    items = node.get("items") if isinstance(node.get("items"), dict) else {}
    if enum is None and "enum" in items:
        enum = items["enum"]
    if enum is not None:
        parts.append(", ".join(_code(_scalar(v)) for v in enum))
    lo, hi = node.get("minimum"), node.get("maximum")
    if lo is not None and hi is not None:
        parts.append(f"{_scalar(lo)} – {_scalar(hi)}")
    elif lo is not None:
        parts.append(f"≥ {_scalar(lo)}")
    elif hi is not None:
        parts.append(f"≤ {_scalar(hi)}")
    if node.get("exclusiveMinimum") is not None:
        parts.append(f"> {_scalar(node['exclusiveMinimum'])}")
    if node.get("exclusiveMaximum") is not None:
        parts.append(f"< {_scalar(node['exclusiveMaximum'])}")
    if node.get("minItems") is not None:
        parts.append(f"at least {node['minItems']} item{'s' if node['minItems'] != 1 else ''}")
    if node.get("maxItems") is not None:
        parts.append(f"at most {node['maxItems']} item{'s' if node['maxItems'] != 1 else ''}")
    if node.get("minProperties") is not None:
        parts.append(f"at least {node['minProperties']} entr{'ies' if node['minProperties'] != 1 else 'y'}")
    if node.get("pattern"):
        parts.append(f"matches {_code(node['pattern'])}")
    if node.get("required"):
        parts.append("requires " + ", ".join(_code(k) for k in node["required"]))
    return "; ".join(parts)


def _placeholder(key: str) -> str:
    """``<dataset>`` under ``datasets``: the name a free-form key stands for."""
    return f"<{key[:-1]}>" if key.endswith("s") and len(key) > 1 else "<name>"


def _row(path: str, node: dict) -> str:
    default = _code(_flow(node["default"])) if "default" in node else ""
    cells = (
        _cell(_code(path)),
        _type(node),
        _cell(default),
        _cell(_allowed(node)),
        _prose(node.get("description", "")),
    )
    return "| " + " | ".join(cells) + " |"


def _rows(path: str, node: dict) -> list[str]:
    """The rows of everything below ``node`` at ``path``."""
    rows = []
    for name, child in node.get("properties", {}).items():
        rows += [_row(f"{path}.{name}", child), *_rows(f"{path}.{name}", child)]
    extra = node.get("additionalProperties")
    if isinstance(extra, dict):
        child = f"{path}.{_placeholder(path.rsplit('.', 1)[-1])}"
        rows += [_row(child, extra), *_rows(child, extra)]
    return rows


def _table(rows: list[str]) -> list[str]:
    return ["| " + " | ".join(HEADER) + " |", "|" + " --- |" * len(HEADER), *rows]


def _is_section(node: dict) -> bool:
    return node.get("type") == "object" or "properties" in node or isinstance(node.get("additionalProperties"), dict)


def schema_markdown(schema: dict, source: str = str(SCHEMA), intro: str = "") -> str:
    """Markdown reference of a configuration schema: top-level scalar keys in one table, then
    one section per top-level object with a row per key path (``<name>`` for free-form keys).
    ``intro`` (markdown) goes after the schema's own description."""
    out = ["# Configuration reference", "",
           f"Generated from `{source}` by `{COMMAND}`; do not edit by hand.", ""]  # fmt: skip
    if schema.get("description"):
        out += [_prose(schema["description"]), ""]
    if intro:
        out += [intro, ""]
    props = schema.get("properties", {})
    scalars = [(k, v) for k, v in props.items() if not _is_section(v)]
    sections = [(k, v) for k, v in props.items() if _is_section(v)]
    if scalars:
        out += ["## Top-level keys", "", *_table([_row(k, v) for k, v in scalars]), ""]
    for name, node in sections:
        out += [f"## `{name}`", ""]
        if node.get("description"):
            out += [_prose(node["description"]), ""]
        out += [*_table(_rows(name, node)), ""]
    return "\n".join(out).rstrip("\n") + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m delta.config_reference", description=__doc__.split("\n")[0])
    parser.add_argument("--schema", default=str(SCHEMA), help="the config schema (default: %(default)s)")
    parser.add_argument("--check", metavar="FILE", help="exit 1 if FILE differs from the generated reference")
    args = parser.parse_args(argv)
    from delta.config import load_schema

    text = schema_markdown(load_schema(args.schema), source=args.schema, intro=INTRO)
    if args.check:
        path = Path(args.check)
        if not path.is_file() or path.read_text() != text:
            print(f"{path} is stale: run `{COMMAND}`", file=sys.stderr)
            return 1
        return 0
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
