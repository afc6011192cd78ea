"""Typed settings sections: one dataclass a section is the one place a knob is written.

From a section's dataclass come its JSON schema (the workflow's config schema embeds it, and the
configuration reference is generated from that), its command-line options (one per field, help
from the field's docstring) and its validation. A rule passes a job its resolved section once, as
JSON (``--settings``); the command reads it with :func:`from_mapping`.

A field declares what the schema needs in its ``metadata``: ``minimum`` / ``maximum`` (inclusive),
``exclusive_minimum``, ``choices`` (for strings, or the items of a tuple of strings), ``min_items``, and
``config: False`` for a field that the workflow fills in itself (a path), not the user.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import json
import math
import textwrap
import types
import typing
from typing import Any

from delta import DeltaError


def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of a dataclass, as one line."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body
    docs = {}
    for node, nxt in zip(body, body[1:]):
        if isinstance(node, ast.AnnAssign) and isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant):
            docs[node.target.id] = " ".join(str(nxt.value.value).split())
    return docs


def _type_schema(tp: Any, meta: dict) -> dict:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):  # Optional[X]: null means "not given"
        inner = [a for a in args if a is not type(None)]
        return _type_schema(inner[0], meta)
    if tp is bool:
        return {"type": "boolean"}
    if tp is dict or origin is dict:
        return {"type": "object"}
    if tp is int:
        out: dict = {"type": "integer"}
    elif tp is float:
        out = {"type": "number"}
    elif tp is str:
        return {"enum": list(meta["choices"])} if "choices" in meta else {"type": "string"}
    elif origin in (tuple, list):
        item = args[0] if args else str
        items = _type_schema(item, meta)
        out = {"type": "array", "items": items}
        if origin is tuple and args and args[-1] is not Ellipsis:
            out |= {"minItems": len(args), "maxItems": len(args)}
        elif "choices" in meta:
            out["uniqueItems"] = True
        if "min_items" in meta:
            out["minItems"] = meta["min_items"]
        return out
    else:
        raise TypeError(f"no schema for the type {tp!r}")
    for key, name in (("minimum", "minimum"), ("maximum", "maximum"), ("exclusive_minimum", "exclusiveMinimum")):
        if key in meta:
            out[name] = meta[key]
    return out


def _json_default(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


def section_schema(cls: type, defaults: bool = True) -> dict:
    """The JSON schema of a settings dataclass: one property per user-set field, no other key.

    ``defaults`` puts each field's default in the schema (the config validation fills it in); a
    section that overrides another (a subject's own fit settings) takes none.
    """
    hints, docs = typing.get_type_hints(cls), field_docs(cls)
    props = {}
    for f in dataclasses.fields(cls):
        if not f.metadata.get("config", True):
            continue
        prop = _type_schema(hints[f.name], f.metadata)
        if f.name in docs:
            prop["description"] = docs[f.name]
        if defaults and f.default is not dataclasses.MISSING and f.default is not None:
            prop["default"] = _json_default(f.default)
        props[f.name] = prop
    out = {"type": "object", "additionalProperties": False, "properties": props}
    if cls.__doc__:
        out["description"] = " ".join(cls.__doc__.split("\n\n")[0].split())
    if defaults:
        out["default"] = {}
    return out


def check(obj: Any, where: str) -> None:
    """Every number of a settings object finite and within its field's bounds; a DeltaError names the key."""
    for f in dataclasses.fields(obj):
        value, meta = getattr(obj, f.name), f.metadata
        values = value if isinstance(value, (tuple, list)) else [value]
        for v in values:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                if isinstance(v, str) and "choices" in meta and v not in meta["choices"]:
                    raise DeltaError(f"{where}.{f.name}: {v!r} (expected one of {list(meta['choices'])})")
                continue
            if not math.isfinite(v):
                raise DeltaError(f"{where}.{f.name}: {v} is not a finite number")
            low, high, above = meta.get("minimum"), meta.get("maximum"), meta.get("exclusive_minimum")
            if (low is not None and v < low) or (high is not None and v > high) or (above is not None and v <= above):
                bounds = ", ".join(
                    s for s in (f">= {low}" if low is not None else "", f"<= {high}" if high is not None else "",
                                f"> {above}" if above is not None else "") if s)  # fmt: skip
                raise DeltaError(f"{where}.{f.name}: {v} (expected {bounds})")


def from_mapping(cls: type, data: dict | None, where: str) -> Any:
    """A settings object from a mapping of its fields (JSON or YAML), checked against its schema.

    Unknown keys, values of the wrong type and numbers out of bounds raise a DeltaError naming
    ``where`` and the key. Tuples come from lists; a field left out, or given as null, keeps its default.
    """
    import jsonschema

    data = {k: v for k, v in (data or {}).items() if v is not None}
    schema = section_schema(cls, defaults=False)
    internal = {f.name for f in dataclasses.fields(cls)} - set(schema["properties"])
    schema["properties"] |= {name: {} for name in internal}
    errors = sorted(jsonschema.Draft202012Validator(schema).iter_errors(data), key=lambda e: list(map(str, e.path)))
    if errors:
        e = errors[0]
        key = ".".join([where, *map(str, e.absolute_path)])
        raise DeltaError(f"{key}: {e.message}")
    hints = typing.get_type_hints(cls)
    kw = {k: tuple(v) if isinstance(v, list) and _is_tuple(hints[k]) else v for k, v in data.items()}
    obj = cls(**kw)
    check(obj, where)
    return obj


def _is_tuple(tp: Any) -> bool:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return any(_is_tuple(a) for a in typing.get_args(tp))
    return typing.get_origin(tp) is tuple


def to_mapping(obj: Any, config_only: bool = True) -> dict:
    """A settings object as JSON-ready values (``config_only``: the fields a user sets; None: not given)."""
    return {f.name: _json_default(getattr(obj, f.name)) for f in dataclasses.fields(obj)
            if (not config_only or f.metadata.get("config", True)) and getattr(obj, f.name) is not None}  # fmt: skip


def add_arguments(parser: Any, cls: type) -> None:
    """``--settings JSON`` plus one option a field (``max_frames`` -> ``--max-frames``), help from its docstring.

    An option given on the command line wins over the same key in ``--settings``.
    """
    parser.add_argument("--settings", default="{}", help=f"JSON object of {cls.__name__} fields (what a rule passes)")
    hints, docs = typing.get_type_hints(cls), field_docs(cls)
    for f in dataclasses.fields(cls):
        if not f.metadata.get("config", True):
            continue
        flag = "--" + f.name.replace("_", "-")
        tp = hints[f.name]
        if tp is dict or typing.get_origin(tp) is dict:
            continue  # a mapping comes through --settings only
        help_ = docs.get(f.name, "").replace("%", "%%")  # argparse formats help with %
        if tp is bool:
            parser.add_argument(flag, dest=f.name, type=_boolean, default=None, metavar="true|false", help=help_)
        elif _is_tuple(tp) or typing.get_origin(tp) is list:
            parser.add_argument(flag, dest=f.name, nargs="+", default=None, type=_scalar(tp), help=help_)
        else:
            parser.add_argument(flag, dest=f.name, type=_scalar(tp), default=None, help=help_)


def _boolean(text: str) -> bool:
    if text.lower() not in ("true", "false", "1", "0", "yes", "no"):
        raise ValueError(text)
    return text.lower() in ("true", "1", "yes")


def _scalar(tp: Any):
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        tp = next(a for a in typing.get_args(tp) if a is not type(None))
    if typing.get_origin(tp) in (tuple, list):
        tp = typing.get_args(tp)[0] if typing.get_args(tp) else str
    return tp if tp in (int, float) else str


def from_arguments(cls: type, args: Any, section: str, **internal: Any) -> Any:
    """A settings object from ``--settings`` and the per-field options (the options win)."""
    text = args.settings
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise DeltaError(f"--settings: not valid JSON ({err})") from None
    if not isinstance(data, dict):
        raise DeltaError(f"--settings: expected a JSON object of {cls.__name__} fields, got {text[:80]}")
    for f in dataclasses.fields(cls):
        given = getattr(args, f.name, None)
        if given is not None:
            data[f.name] = list(given) if isinstance(given, (list, tuple)) else given
    return dataclasses.replace(from_mapping(cls, data, section), **internal)
