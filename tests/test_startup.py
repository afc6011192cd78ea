"""Every workflow job starts a ``delta`` process, so what a process imports before it works is paid once a
job: the command line is built from settings modules that import no torch, trimesh or scipy (about 3 s a
process on two cores), and each subcommand imports what it needs when it runs."""

import json
import subprocess
import sys

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
