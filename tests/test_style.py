"""The code's form is checked as its behaviour is: ruff lints and formats the package, the tests and
the benchmarks (pyproject.toml's [tool.ruff]), snakefmt formats the workflow, and Snakemake's own
linter finds nothing (tests/test_workflow.py). Fix with `ruff format . && ruff check --fix . && snakefmt Snakefile rules`."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CODE = ["delta", "tests", "benchmarks"]


def run(*cmd: str) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)


def tool(name: str) -> str:
    path = shutil.which(name) or str(Path(sys.executable).parent / name)
    if not Path(path).exists():
        pytest.fail(f"{name} is not installed: pip install -e '.[test]'")
    return path


def test_ruff_lint_is_clean():
    res = run(tool("ruff"), "check", *CODE)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]


def test_ruff_format_is_applied():
    res = run(tool("ruff"), "format", "--check", *CODE)
    assert res.returncode == 0, "run `ruff format delta tests benchmarks`:\n" + res.stdout[-4000:] + res.stderr[-2000:]


def test_snakefmt_is_applied():
    res = run(tool("snakefmt"), "--check", "Snakefile", "rules")
    assert res.returncode == 0, "run `snakefmt Snakefile rules`:\n" + res.stdout[-3000:] + res.stderr[-3000:]
