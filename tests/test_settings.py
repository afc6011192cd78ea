"""Typed settings sections: the schema, the command-line options and the validation come from one
dataclass (checked on a small hand-written section and on the workflow's own sections)."""

import argparse
import dataclasses
from typing import Optional

import pytest

from delta import DeltaError
from delta.config import load_schema
from delta.eval.settings import EvalSettings
from delta.export.settings import ExportSettings
from delta.settings import add_arguments, from_arguments, from_mapping, section_schema, to_mapping
from tests.test_validation import REPO

_f = dataclasses.field


@dataclasses.dataclass
class Knobs:
    """Knobs of a test section.

    More prose that stays out of the schema."""

    steps: int = _f(default=3, metadata={"minimum": 1, "maximum": 9})
    """How many steps."""
    rate: float = _f(default=0.5, metadata={"exclusive_minimum": 0})
    kinds: tuple[str, ...] = _f(default=("a",), metadata={"choices": ("a", "b"), "min_items": 1})
    """Which kinds."""
    flag: bool = True
    pair: Optional[tuple[str, str]] = None
    where: str = _f(default="", metadata={"config": False})


def test_schema_of_a_section_by_hand():
    assert section_schema(Knobs) == {
        "type": "object", "additionalProperties": False, "default": {}, "description": "Knobs of a test section.",
        "properties": {
            "steps": {"type": "integer", "minimum": 1, "maximum": 9, "description": "How many steps.", "default": 3},
            "rate": {"type": "number", "exclusiveMinimum": 0, "default": 0.5},
            "kinds": {"type": "array", "items": {"enum": ["a", "b"]}, "uniqueItems": True, "minItems": 1,
                      "description": "Which kinds.", "default": ["a"]},
            "flag": {"type": "boolean", "default": True},
            "pair": {"type": "array", "items": {"type": "string"}, "minItems": 2, "maxItems": 2},
        },
    }  # fmt: skip
    assert "default" not in section_schema(Knobs, defaults=False)["properties"]["steps"]


@pytest.mark.parametrize("data,message", [
    ({"stpes": 2}, "knobs: Additional properties are not allowed ('stpes' was unexpected)"),
    ({"steps": 10}, "knobs.steps: 10 is greater than the maximum of 9"),
    ({"steps": 2.5}, "knobs.steps: 2.5 is not of type 'integer'"),
    ({"rate": 0}, "knobs.rate: 0 is less than or equal to the minimum of 0"),
    ({"rate": float("nan")}, "knobs.rate: nan is not a finite number"),
    ({"kinds": ["c"]}, "knobs.kinds.0: 'c' is not one of ['a', 'b']"),
    ({"pair": ["x"]}, "knobs.pair: ['x'] is too short"),
    ({"where": "/tmp"}, None),  # internal fields pass through a mapping (the workflow's own paths)
])  # fmt: skip
def test_from_mapping_names_the_key(data, message):
    if message is None:
        assert from_mapping(Knobs, data, "knobs").where == "/tmp"
        return
    with pytest.raises(DeltaError) as err:
        from_mapping(Knobs, data, "knobs")
    assert str(err.value) == message


def test_options_come_from_the_fields_and_win_over_settings():
    parser = argparse.ArgumentParser()
    add_arguments(parser, Knobs)
    assert "--where" not in parser.format_help() and "How many steps." in parser.format_help()
    args = parser.parse_args(["--settings", '{"steps": 4, "rate": 2.0}', "--steps", "5", "--kinds", "a", "b",
                              "--flag", "false", "--pair", "p", "q"])  # fmt: skip
    k = from_arguments(Knobs, args, "knobs", where="here")
    assert k == Knobs(steps=5, rate=2.0, kinds=("a", "b"), flag=False, pair=("p", "q"), where="here")
    assert to_mapping(k) == {"steps": 5, "rate": 2.0, "kinds": ["a", "b"], "flag": False, "pair": ["p", "q"]}
    with pytest.raises(DeltaError, match="--settings: not valid JSON"):
        from_arguments(Knobs, parser.parse_args(["--settings", "{steps"]), "knobs")


def test_the_workflow_schema_embeds_the_sections():
    schema = load_schema(REPO / "workflow" / "schemas" / "config.schema.yaml")
    assert schema["properties"]["evaluation"] == section_schema(EvalSettings)
    assert schema["properties"]["export"] == section_schema(ExportSettings)
    study = schema["properties"]["tradeoff"]["properties"]["evaluation"]
    assert study["properties"] == section_schema(EvalSettings, defaults=False)["properties"] and "default" not in study


@pytest.mark.parametrize("cls", [EvalSettings, ExportSettings])
def test_a_section_round_trips_through_its_mapping(cls):
    default = cls()
    assert from_mapping(cls, to_mapping(default), "x") == default
