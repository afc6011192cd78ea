"""Every workflow job starts a ``delta`` process, so what a process imports before it works is paid once a
job: the command line is built from settings modules that import no torch, trimesh or scipy (about 3 s a
process on two cores), and each subcommand imports what it needs when it runs."""

import json
import subprocess
import sys
from pathlib import Path

HEAVY = ("torch", "trimesh", "scipy", "cv2", "kornia", "pandas")


def imported_after(code: str) -> list[str]:
    probe = f"import sys, json\n{code}\nprint(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))"
    res = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_the_command_line_is_built_without_the_heavy_libraries():
    assert imported_after("from delta.cli import build_parser; build_parser()") == []


def test_help_of_every_subcommand_needs_no_heavy_library():
    code = (
        "from delta.cli import build_parser\n"
        "p = build_parser()\n"
        "subs = next(a for a in p._actions if a.__class__.__name__ == '_SubParsersAction')\n"
        "[s.format_help() for s in subs.choices.values()]"
    )
    assert imported_after(code) == []


def test_a_subcommand_still_finds_its_settings():
    """The settings moved out of the modules that use them are the same classes there."""
    from delta.eval import evaluate, settings
    from delta.preprocess import settings as prepare_settings
    from delta.preprocess.frames import prepare

    assert evaluate.EvalSettings is settings.EvalSettings
    assert prepare.__module__ == "delta.preprocess.frames" and prepare_settings.PrepareSettings().kind == "video"


def test_the_workflow_builds_its_dag_without_torch(tmp_path):
    """Snakemake's own process validates the config and resolves every subject's training before any job
    starts, and does so on the settings modules alone (a dry run of the default target took 7.5 s with torch
    imported, 3.5 s without)."""
    repo = Path(__file__).resolve().parents[1]
    cmd = [sys.executable, "-X", "importtime", "-m", "snakemake", "--cores", "1", "-n", "results/synthetic/metrics.csv"]
    res = subprocess.run(cmd, cwd=repo, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    imported = {line.rsplit("|", 1)[-1].strip() for line in res.stderr.splitlines() if line.startswith("import time:")}
    assert "delta.config" in imported, "the probe saw the workflow's imports"
    assert not imported & {"torch", "trimesh", "scipy", "kornia"}, sorted(imported & {"torch", "trimesh", "scipy"})


def test_the_working_modules_import_neither_kornia_nor_the_compiler():
    """``import kornia`` loads its whole package (~0.5 s) and ``torch._dynamo`` ~2 s: the rotations and the
    optimiser are the project's own, and the deterministic flag is set without the compiler's config."""
    code = (
        "import sys, torch\n"
        "import delta.training.trainer, delta.eval.evaluate, delta.fitting.fit, delta.export.animated\n"
        "import delta.export.video, delta.applications.animate, delta.applications.reenact\n"
        "from delta.training.trainer import reproducible\n"
        "with reproducible(torch.device('cpu')):\n"
        "    inside = torch.are_deterministic_algorithms_enabled()\n"
        "after = torch.are_deterministic_algorithms_enabled()\n"
        "print(inside, after, 'kornia' in sys.modules, 'torch._dynamo' in sys.modules)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.split() == ["True", "False", "False", "False"]
