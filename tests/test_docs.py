"""The documentation: the configuration reference is generated from the schema, the README stays a
short guide, and nothing tracked narrates the history of the work (that is what git log is for)."""

import re
import subprocess
from pathlib import Path

import pytest

from delta.config import load_schema
from delta.config_reference import COMMAND, INTRO, main, schema_markdown

REPO = Path(__file__).resolve().parents[1]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"
WORK_LOG = re.compile(
    r"\bsessions? [0-9]|\bin session\b|\blast session\b|\bround [0-9]|\brounds? of work\b|\bsince last time\b"
    r"|\bthese replace\b",
    re.IGNORECASE,
)


def test_configuration_reference_is_current():
    generated = schema_markdown(load_schema(SCHEMA), intro=INTRO)
    path = REPO / "docs" / "configuration.md"
    assert path.is_file(), f"docs/configuration.md is missing: run `{COMMAND}`"
    assert path.read_text() == generated, f"docs/configuration.md is stale: run `{COMMAND}`"


def test_check_flag(tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)
    assert main(["--check", "docs/configuration.md"]) == 0
    stale = tmp_path / "configuration.md"
    stale.write_text("# old\n")
    assert main(["--check", str(stale)]) == 1


def test_schema_markdown_rows():
    schema = {
        "description": "a tiny config",
        "type": "object",
        "properties": {
            "mode": {"description": "how it runs", "enum": ["a", "b"], "default": "a"},
            "body": {
                "type": "object",
                "description": "the body",
                "default": {},
                "properties": {
                    "level": {"type": "integer", "minimum": 0, "maximum": 2, "default": 1},
                    "path": {"type": "string", "default": "", "description": "a | b <file>"},
                    "parts": {"type": "array", "items": {"enum": ["x", "y"]}, "default": ["x"]},
                    "scale": {"type": "number", "exclusiveMinimum": 0},
                },
            },
            "datasets": {
                "type": "object",
                "additionalProperties": {
                    "type": "object",
                    "required": ["subjects"],
                    "properties": {"subjects": {"type": "object", "minProperties": 1}},
                },
            },
        },
    }
    text = schema_markdown(schema, source="s.yaml")
    lines = text.splitlines()
    assert lines[0] == "# Configuration reference"
    assert "a tiny config" in lines
    header = "| key | type | default | allowed | description |"
    assert lines.count(header) == 3  # top-level keys, body, datasets
    assert lines.index("## Top-level keys") < lines.index("## `body`") < lines.index("## `datasets`")
    assert "the body" in lines
    rows = [line for line in lines if line.startswith("| `")]
    assert rows == [
        "| `mode` | string | `a` | `a`, `b` | how it runs |",
        "| `body.level` | integer | `1` | 0 – 2 |  |",
        '| `body.path` | string | `""` |  | a \\| b &lt;file> |',
        "| `body.parts` | array of string | `[x]` | `x`, `y` |  |",
        "| `body.scale` | number |  | > 0 |  |",
        "| `datasets.<dataset>` | object |  | requires `subjects` |  |",
        "| `datasets.<dataset>.subjects` | object |  | at least 1 entry |  |",
    ]


def test_readme_is_short():
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= 300, f"README.md has {len(lines)} lines (at most 300): move detail into docs/"


def _tracked_text_files() -> list[Path]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    files = []
    for name in filter(None, out.decode().split("\0")):
        path = REPO / name
        if name.endswith(".csv") or not path.is_file():
            continue
        data = path.read_bytes()
        if b"\0" in data[:8192]:  # binary
            continue
        files.append(path)
    return files


def test_no_work_log_wording():
    hits = []
    for path in _tracked_text_files():
        text = path.read_text(errors="replace")
        for number, line in enumerate(text.splitlines(), 1):
            if WORK_LOG.search(line):
                hits.append(f"{path.relative_to(REPO)}:{number}: {line.strip()[:120]}")
    assert not hits, "work-log wording (history belongs in git log):\n" + "\n".join(hits)
