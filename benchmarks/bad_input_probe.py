"""How the workflow treats bad input: every case is a user mistake or an attack, run as a new user runs
the workflow (``delta <subcommand>`` in a subprocess, ``delta validate-config``, or ``python -m snakemake
--cores 2`` in a fresh copy of the workflow), and its outcome is classified:

- ``clear_error``: non-zero exit, a one-line message naming the file, key or frame, no Python traceback in
  what the user sees (the command's output; for Snakemake also the failed job's log);
- ``traceback``: non-zero exit with the traceback of an exception other than DeltaError;
- ``unclear_error``: non-zero exit, no traceback, but no message naming what is wrong (or a DeltaError shown
  with its traceback);
- ``silent_wrong``: exit 0 although the input cannot give a valid result (or a NaN in an output, or a
  control whose output misses what it must show);
- ``code_execution``: a marker file that a payload creates exists afterwards;
- ``ok``: a valid input (a control) that succeeded.

``leftover`` says whether the case's output, or a half-written temporary file beside it (``.{stem}.*.part*``),
exists after a failure. One row per case goes to the CSV (case, category, command, expected, exit_code,
outcome, message: the first error line, 200 characters at most, leftover, seconds); the last line printed
is the summary of counts. A crafted or broken model.pt is refused before the record and body are read;
they are real all the same (a 6-frame person clip prepared at 32 px, the small Anny body). Every input is generated
(tiny videos of 64 x 48 pixels, the tests' approach in tests/test_bad_inputs.py); the body model is the
shipped Anny, converted small (8 shape components) from the Anny build cache in ``$DELTA_ANNY_CACHE``, else
``resources/anny_cache`` (built there the first time: ~3 min on 2 cores). The issue's criterion: 0
silent_wrong, 0 code_execution, 0 traceback. Run from the repository root::

    PYTHONPATH=$PWD python3 benchmarks/bad_input_probe.py                  # every case, ~6.5 min on 2 cores
    PYTHONPATH=$PWD python3 benchmarks/bad_input_probe.py --only input_nan_in_K       # one case
    PYTHONPATH=$PWD python3 benchmarks/bad_input_probe.py --only 'config_*' --csv /tmp/probe.csv --keep
"""

from __future__ import annotations

import argparse
import copy
import csv
import dataclasses
import fnmatch
import json
import math
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])}
ANNY_CACHE = Path(os.environ.get("DELTA_ANNY_CACHE", REPO / "resources" / "anny_cache"))
MARKER = "PWNED"  # what every payload creates (in the case's folder)
TRACEBACK = "Traceback (most recent call last)"
#: stage-1 training of a few steps at 32²: the code path, not the quality
TINY_TRAIN = {"resolution": 32, "render": {"samples": 8},
              "stage1": {"iterations": 2, "rays": 64, "checkpoint_every": 1, "preview_every": 0, "log_every": 1}}  # fmt: skip
TINY_FIT = {"iterations": [5, 5, 5], "sil_size": 16, "facing_starts": 2}


def delta_cmd() -> list[str]:
    """The ``delta`` command a user runs (the installed entry point; PYTHONPATH makes it this checkout's)."""
    exe = shutil.which("delta")
    return [exe] if exe else [sys.executable, "-m", "delta.cli"]


# ---------------------------------------------------------------------------------------------- runs
@dataclasses.dataclass
class Run:
    """What a case's setup returns: the command, where it runs, and what to look at afterwards."""

    argv: list[str]
    cwd: Path
    names: str  # regex the error message must match to name the file / key / frame
    leftovers: list[str] = dataclasses.field(default_factory=list)  # globs (relative to cwd) of outputs
    check: Callable[[str], str] | None = None  # for a success, given the output: "" when right, else what is wrong
    timeout: int = 300
    short: str = ""  # the command as the CSV shows it
    logs: list[str] = dataclasses.field(default_factory=list)  # globs of job logs the user would read


@dataclasses.dataclass
class Case:
    name: str
    category: str
    setup: Callable[[Path], Run]
    expect: str = "clear_error"  # or "ok"


def error_message(text: str) -> str:
    """The first error line a user sees, with the indented lines of a multi-line message after it."""
    lines = text.splitlines()
    for i, line in enumerate(lines):  # Snakemake: "DeltaError in file ..., line N:", the message, then "  File ..."
        if re.match(r"^\w*Error in file ", line):
            out = [line.strip()]
            for nxt in lines[i + 1 : i + 6]:
                if nxt.startswith("  File ") or not nxt.strip():
                    break
                out.append(nxt.strip())
            return " | ".join(out)
    patterns = [r"^delta [\w-]+: error: ", r"^Error in rule ", r"^(\w+\.)*\w*(Error|Exception)\b",
                r"error", r"Error"]  # fmt: skip
    for pat in patterns:
        for i, line in enumerate(lines):
            if re.search(pat, line):
                out = [line.strip()]
                for nxt in lines[i + 1 : i + 4]:
                    if nxt.startswith((" ", "\t")) and nxt.strip() and not nxt.strip().startswith("File "):
                        out.append(nxt.strip())
                    else:
                        break
                return " | ".join(out)
    return lines[-1].strip() if lines else ""


def exception_of(text: str) -> str:
    """The exception a traceback ends with ("" when there is no traceback)."""
    if TRACEBACK not in text:
        return ""
    tail = text[text.rindex(TRACEBACK) :].splitlines()
    for line in tail[1:]:
        m = re.match(r"^([A-Za-z_][\w.]*(Error|Exception|Interrupt|Exit))\b", line)
        if m:
            return m.group(1)
    return "unknown"


def classify(case: Case, run: Run, rc: int, seen: str) -> tuple[str, str]:
    cwd = run.cwd
    if list(cwd.rglob(MARKER)) or (cwd.parent / MARKER).exists():
        return "code_execution", f"marker {MARKER} created"
    if rc == 0:
        if case.expect == "ok":
            wrong = run.check(seen) if run.check else ""
            return ("silent_wrong", wrong) if wrong else ("ok", "")
        return "silent_wrong", "exit 0 on input that cannot give a valid result"
    exc = exception_of(seen)
    if exc and not exc.endswith("DeltaError"):
        return "traceback", f"{exc}: {error_message(seen[seen.rindex(TRACEBACK) :])}"
    msg = error_message(seen)
    if exc:
        return "unclear_error", f"DeltaError shown with a traceback: {msg}"
    if re.search(run.names, msg):
        return "clear_error", msg
    return "unclear_error", msg


def execute(case: Case, root: Path) -> dict:
    work = root / case.name
    work.mkdir(parents=True)
    t0 = time.perf_counter()
    try:
        run = case.setup(work)
    except Exception as exc:  # noqa: BLE001  (the probe's own setup failed: say so, not the workflow's)
        return {"case": case.name, "category": case.category, "command": "(setup)", "expected": case.expect,
                "exit_code": "", "outcome": "setup_failed", "message": f"{type(exc).__name__}: {exc}"[:200],
                "leftover": "", "seconds": round(time.perf_counter() - t0, 1)}  # fmt: skip
    try:
        res = subprocess.run(
            run.argv, cwd=run.cwd, env=ENV, capture_output=True, text=True, timeout=run.timeout, check=False
        )
        rc, seen = res.returncode, res.stdout + "\n" + res.stderr
    except subprocess.TimeoutExpired as exc:
        rc = 124
        seen = f"timed out after {run.timeout} s\n" + (exc.stdout or b"").decode(errors="replace")
    if rc != 0:  # a failed Snakemake job: its log is what the user reads next
        for pattern in run.logs:
            for log in sorted(run.cwd.glob(pattern)):
                seen += "\n" + log.read_text(errors="replace")
    outcome, message = classify(case, run, rc, seen)
    message = message.replace(str(work) + "/", "").replace(str(root) + "/", "")  # the temporary folder adds nothing
    left = sorted(str(p.relative_to(run.cwd)) for g in run.leftovers for p in run.cwd.glob(g))
    return {"case": case.name, "category": case.category, "command": run.short or shlex.join(run.argv)[:200],
            "expected": case.expect, "exit_code": rc, "outcome": outcome, "message": message[:200].replace("\n", " "),
            "leftover": ("yes: " + " ".join(left))[:200] if left and rc != 0 else ("no" if rc != 0 else ""),
            "seconds": round(time.perf_counter() - t0, 1)}  # fmt: skip


# ------------------------------------------------------------------------------------ shared inputs
class Shared:
    """Inputs several cases read, made once: the small Anny body, a person capture's record, its init fit."""

    def __init__(self, root: Path):
        self.root = root / "_shared"
        self.root.mkdir(parents=True, exist_ok=True)
        self._done: dict[str, object] = {}

    def _once(self, key, make):
        if key not in self._done:
            self._done[key] = make()
        return self._done[key]

    def body(self) -> str:
        def make():
            base, sub = self.root / "anny.npz", self.root / "anny_sub1.npz"
            if not ANNY_CACHE.is_dir():
                print(f"  (building the Anny cache in {ANNY_CACHE}: ~3 min, once)", flush=True)
            cli("convert-anny", "--out", base, "--num-shape", 8, "--num-samples", 64, "--merge", "fingers", "toes",
                "--cache-dir", ANNY_CACHE, "--threads", 2)  # fmt: skip
            cli("upsample", "--src", base, "--out", sub, "--level", 1)
            return str(sub)

        return self._once("body", make)

    def record(self) -> str:
        """A 6-frame person clip prepared as the workflow prepares a video (train 0-3, test 4-5), with the
        parse step's clothing masks (0/1; the shirt and trousers: the person below the neck)."""

        def make():
            import h5py

            steps = capture(self.root / "person", "pppppp")
            with h5py.File(steps["matte"]) as f:
                clothing = (f["person"][:] > 127).astype("uint8")
            clothing[:, :12] = 0
            with h5py.File(self.root / "person" / "parsing.h5", "w") as f:
                f["clothing"] = clothing
                f.attrs["model"] = "default:probe"
            out = self.root / "frames.h5"
            cli(*prepare_argv(self.root / "person", out, [*steps.values(), self.root / "person" / "parsing.h5"],
                              config={"train": [0, 3, 1], "test": [4, 5, 1]}))  # fmt: skip
            return str(out)

        return self._once("record", make)

    def init(self) -> str:
        def make():
            cli("fit-init", "--record", self.record(), "--body", self.body(), "--out", self.root / "init",
                "--settings", json.dumps(TINY_FIT), "--threads", 2)  # fmt: skip
            return str(self.root / "init" / "params.npz")

        return self._once("init", make)


SHARED: Shared | None = None


def cli(*args) -> None:
    """A setup step through the CLI; it must succeed."""
    res = subprocess.run(
        [*delta_cmd(), *map(str, args)], env=ENV, capture_output=True, text=True, timeout=600, check=False
    )
    if res.returncode != 0:
        raise RuntimeError(f"delta {args[0]} failed: {(res.stderr or res.stdout)[-300:]}")


# ------------------------------------------------------------------------------------ tiny captures
def capture(root: Path, frames: str) -> dict:
    """``root/clip.mp4`` (64 x 48) of person / grey / noise frames with its matting and keypoint files."""
    from tests.test_bad_inputs import capture as make

    return make(root, frames)


def prepare_argv(root: Path, out: Path, steps: list | None = None, kind: str = "video", config: dict | None = None):
    steps = [root / "matte.h5", root / "keypoints.h5"] if steps is None else steps
    argv = ["prepare", "--kind", kind, "--root", str(root), "--subject", "clip", "--resolution", "32",
            "--out", str(out), "--summary", str(out.with_suffix(".json"))]  # fmt: skip
    if config is not None:
        argv += ["--settings", json.dumps({"frames": config})]
    return argv + (["--steps", *map(str, steps)] if steps else [])


def delta_run(work: Path, argv: list, names: str, leftovers=(), check=None, timeout=300) -> Run:
    argv = [str(a) for a in argv]
    short = "delta " + " ".join(shlex.quote(a if len(a) < 60 else a[:57] + "...") for a in argv)
    short = short.replace(str(work) + "/", "").replace(str(work), ".")
    return Run([*delta_cmd(), *argv], work, names, list(leftovers), check, timeout, short[:200])


def prepare_case(frames: str = "pppppp", camera: str | None = None, masks=None, expect_summary=None,
                 names: str = r"clip") -> Callable[[Path], Run]:  # fmt: skip
    """``delta prepare`` of a generated clip; ``camera`` the text of clip.camera.json, ``masks`` a function
    of the good masks giving the matting file's."""

    def setup(work: Path) -> Run:
        from tests.test_bad_inputs import read, write_steps

        steps = capture(work / "in", frames)
        if camera is not None:
            (work / "in" / "clip.camera.json").write_text(camera)
        if masks is not None:
            write_steps(work / "in", masks(read(steps["matte"], "person")), read(steps["keypoints"], "keypoints"))
        out = work / "out" / "frames.h5"
        out.parent.mkdir()

        def check(seen: str) -> str:
            if not out.is_file():
                return "exit 0 but no frames.h5"
            summary = json.loads(out.with_suffix(".json").read_text())
            if expect_summary:
                return expect_summary(summary)
            return ""

        return delta_run(work, prepare_argv(work / "in", out), names,
                         ["out/frames.h5", "out/frames.json", "out/.frames.*"], check)  # fmt: skip

    return setup


# ------------------------------------------------------------------------------------------ configs
def repo_config() -> dict:
    return yaml.safe_load((REPO / "config" / "config.yaml").read_text())


def tiny_config() -> dict:
    return yaml.safe_load((REPO / ".test" / "config" / "config.yaml").read_text())


def put(cfg: dict, key: str, value) -> dict:
    """Set ``a.b.c`` in a copy of ``cfg`` (creating mappings on the way)."""
    cfg = copy.deepcopy(cfg)
    *path, last = key.split(".")
    node = cfg
    for k in path:
        node = node.setdefault(k, {})
    node[last] = value
    return cfg


def write_video(path: Path, frames: int) -> None:
    import cv2
    import numpy as np

    path.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, (64, 48))
    for i in range(frames):
        writer.write(np.full((48, 64, 3), 20 * i % 255, np.uint8))
    writer.release()


def video_dataset(work: Path, ranges: dict, frames: int = 10, root: str = "data/vid") -> dict:
    write_video(work / root / "clip.mp4", frames)
    return {"kind": "video", "root": root, "subjects": {"clip": ranges}}


def validate_case(change: Callable[[Path], dict], names: str, cwd_outside: bool = False,
                  extra: tuple = (), text: str | None = None) -> Callable[[Path], Run]:  # fmt: skip
    """``delta validate-config config/config.yaml`` of the repository's config changed by ``change(work)``."""

    def setup(work: Path) -> Run:
        path = work / "config" / "config.yaml"
        path.parent.mkdir()
        path.write_text(text if text is not None else yaml.safe_dump(change(work), sort_keys=False))
        if cwd_outside:  # the file given by its absolute path, from an unrelated folder
            (work / "elsewhere").mkdir()
            run = delta_run(work / "elsewhere", ["validate-config", path, *extra], names)
            run.short = f"(cwd elsewhere/) delta validate-config {path.relative_to(work)}"
            return run
        return delta_run(work, ["validate-config", "config/config.yaml", *extra], names)

    return setup


def workflow_copy(work: Path) -> Path:
    """The workflow's files in a fresh folder, as a user's clone has them."""
    for name in ("Snakefile", "rules", "workflow", "config", ".test"):
        src = REPO / name
        (shutil.copytree if src.is_dir() else shutil.copy)(src, work / name)
    return work


def snakemake_case(change: Callable[[Path], dict], names: str, args: tuple = ("-n",), leftovers=("logs", "resources"),
                   check=None, timeout: int = 240, before: Callable[[Path], None] | None = None):  # fmt: skip
    """Snakemake in a copy of the workflow with ``.test/config/probe.yaml`` = the tiny config changed by ``change``."""

    def setup(work: Path) -> Run:
        workflow_copy(work)
        (work / ".test" / "config" / "probe.yaml").write_text(yaml.safe_dump(change(work), sort_keys=False))
        if before:
            before(work)
        argv = [sys.executable, "-m", "snakemake", "--cores", "2", "--configfile", ".test/config/probe.yaml", *args]
        chk = (lambda seen: check(work, seen)) if check else None
        return Run(argv, work, names, list(leftovers), chk, timeout,
                   "snakemake --cores 2 --configfile probe.yaml " + " ".join(args), logs=["logs/**/*.log"])  # fmt: skip

    return setup


# ------------------------------------------------------------------------------------------- paths
#: a dataset root a user (or an attacker handing over a config) could name: a space, a quote, a command
EVIL_ROOT = f"data/o'neil $(touch {MARKER}) `touch {MARKER}` x"


def evil_dataset(work: Path, steps: bool) -> dict:
    """A 7-frame person video under EVIL_ROOT; with ``steps``, its matting and keypoint outputs already made
    (and a stand-in for the converted MediaPipe model, older than them): only prepare_frames is left to run."""
    cfg = put(tiny_config(), "datasets.clips", {"kind": "video", "root": EVIL_ROOT,
                                                 "subjects": {"clip": {"train": [0, 4, 1], "test": [5, 6, 1]}}})  # fmt: skip
    cfg = put(cfg, "preprocess.parsing", {"model": "none"})
    made = capture(work / EVIL_ROOT, "ppppppp")
    if steps:
        model = work / "resources" / "models" / "mediapipe" / "pose_landmark_full.onnx"
        model.parent.mkdir(parents=True)
        model.write_bytes(b"stand-in")
        old = time.time() - 3600
        os.utime(model, (old, old))
        os.utime(work / EVIL_ROOT / "clip.mp4", (old, old))
        results = work / "results" / "clips" / "clip"
        results.mkdir(parents=True)
        shutil.copy(made["matte"], results / "matting.h5")
        shutil.copy(made["keypoints"], results / "keypoints.h5")
    return cfg


# ------------------------------------------------------------------------------------- model files
class _Payload:
    """Unpickling this runs ``touch <marker>``: what a crafted avatar file would do."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return os.system, (f"touch '{self.marker}'",)


def crafted(path: Path, marker: Path, **extra) -> Path:
    import torch

    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"format": 2, "model": {}, "stage": 1, "preset": "fast", "settings": {}, "step": 1,
                "payload": _Payload(marker), **extra}, path)  # fmt: skip
    return path


def truncated(path: Path) -> Path:
    import torch

    torch.save({"format": 2, "model": {"w": torch.ones(4000)}, "stage": 1, "preset": "fast", "settings": {}}, path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def model_case(make: Callable[[Path], Path], sub: str) -> Callable[[Path], Run]:
    """``delta export`` / ``delta evaluate`` of a bad model.pt, with a real record and body."""

    def setup(work: Path) -> Run:
        model = make(work)
        common = ["--model", model, "--record", SHARED.record(), "--body", SHARED.body()]
        if sub == "export":
            argv = ["export", *common, "--out", work / "export", "--grid", 24, "--turntable-frames", 2]
            left = ["export"]
        else:
            argv = [
                "evaluate",
                *common,
                "--out",
                work / "eval" / "metrics.csv",
                "--summary",
                work / "eval" / "summary.json",
            ]
            left = ["eval"]
        run = delta_run(work, argv, r"model\.pt", left)
        run.short = run.short.replace(SHARED.root.parent.as_posix() + "/", "")
        return run

    return setup


def train_argv(work: Path, settings: str, out: Path) -> list:
    return ["train", "--stage", 1, "--settings", settings, "--record", SHARED.record(), "--body", SHARED.body(),
            "--start", SHARED.init(), "--out", out, "--threads", 2]  # fmt: skip


def crafted_checkpoint(work: Path) -> Run:
    out = work / "stage1"
    crafted(out / "checkpoint.pt", work / MARKER, optimizer={}, generator=[0], rows=[])

    def check(seen: str) -> str:
        import pandas as pd

        if not (out / "checkpoint.pt.corrupt").is_file() or "set aside as checkpoint.pt.corrupt" not in seen:
            return "the crafted checkpoint.pt was not set aside as checkpoint.pt.corrupt (with a warning)"
        if not (out / "model.pt").is_file():
            return "exit 0 but no model.pt"
        losses = pd.read_csv(out / "losses.csv")
        if len(losses) != TINY_TRAIN["stage1"]["iterations"]:
            return f"losses.csv has {len(losses)} rows, expected {TINY_TRAIN['stage1']['iterations']} (resumed?)"
        bad = [c for c in losses.columns if losses[c].dtype.kind == "f" and not losses[c].map(math.isfinite).all()]
        return f"NaN/inf in losses.csv columns {bad}" if bad else ""

    run = delta_run(work, train_argv(work, json.dumps(TINY_TRAIN), out), r"checkpoint", ["stage1/model.pt"], check,
                    timeout=400)  # fmt: skip
    run.short = run.short.replace(SHARED.root.parent.as_posix() + "/", "")
    return run


def train_settings_case(settings: str, names: str) -> Callable[[Path], Run]:
    def setup(work: Path) -> Run:
        run = delta_run(work, train_argv(work, settings, work / "stage1"), names, ["stage1"])
        run.short = run.short.replace(SHARED.root.parent.as_posix() + "/", "")
        return run

    return setup


# -------------------------------------------------------------------------------------------- cases
def build_cases() -> list[Case]:
    import numpy as np

    base, tiny = repo_config, tiny_config
    tight = lambda: copy.deepcopy(tiny()["datasets"]["synthetic"]["subjects"]["tight"])

    def renamed(name: str, config: Callable[[], dict] = base) -> Callable[[Path], dict]:
        """The tight subject again under another name (set directly: the name is no dotted key)."""

        def change(work: Path) -> dict:
            cfg = config()
            cfg["datasets"]["synthetic"]["subjects"][name] = tight()
            return cfg

        return change

    K = [[50, 0, 32], [0, 50, 24], [0, 0, 1]]
    cases = [
        # --------------------------------------------------------------------------- config
        Case("config_repo_valid", "config", validate_case(lambda w: base(), r"."), "ok"),
        Case(
            "config_tiny_merged_valid",
            "config",
            validate_case(lambda w: base(), r".", extra=(str(REPO / ".test" / "config" / "config.yaml"),)),
            "ok",
        ),
        Case(
            "config_unknown_top_key",
            "config",
            validate_case(lambda w: put(base(), "learning_rate", 0.1), r"learning_rate"),
        ),
        Case(
            "config_typo_stage1_iteratons",
            "config",
            validate_case(lambda w: put(base(), "training.overrides.stage1.iteratons", 10), r"iteratons"),
        ),
        Case(
            "config_typo_fitting_settings",
            "config",
            validate_case(lambda w: put(base(), "fitting.settings.sil_weigth", 300), r"sil_weigth"),
        ),
        Case(
            "config_typo_synthetic_garmnets",
            "config",
            validate_case(lambda w: put(base(), "datasets.synthetic.subjects.tight.garmnets", ["tshirt"]), r"garmnets"),
        ),
        Case(
            "config_preset_fastest",
            "config",
            validate_case(lambda w: put(base(), "training.subjects.tight", {"preset": "fastest"}), r"fastest"),
        ),
        Case(
            "config_fit_iterations_negative",
            "config",
            validate_case(lambda w: put(base(), "fitting.settings.iterations", [-1, 10, 10]), r"iterations"),
        ),
        Case(
            "config_lr_final_nan",
            "config",
            validate_case(lambda w: put(base(), "training.overrides.stage2.lr_final", float("nan")), r"lr_final"),
        ),
        Case(
            "config_crop_margin_nan",
            "config",
            validate_case(lambda w: put(base(), "preprocess.crop_margin", float("nan")), r"crop_margin"),
        ),
        Case(
            "config_stage1_iterations_-5",
            "config",
            validate_case(lambda w: put(base(), "training.overrides.stage1.iterations", -5), r"iterations"),
        ),
        Case(
            "config_stage1_rays_0",
            "config",
            validate_case(lambda w: put(base(), "training.overrides.stage1.rays", 0), r"rays"),
        ),
        Case(
            "config_training_resolution_100000",
            "config",
            validate_case(lambda w: put(base(), "training.overrides.resolution", 100000), r"resolution"),
        ),
        Case(
            "config_evaluation_resolution_100000",
            "config",
            validate_case(
                lambda w: put(base(), "evaluation.resolution", 100000), r"evaluation.*resolution|resolution.*100000"
            ),
        ),
        Case("config_subject_dotdot", "config", validate_case(renamed(".."), r"'\.\.'")),
        Case("config_subject_traversal", "config", validate_case(renamed("../../etc"), r"\.\./\.\./etc")),
        Case("config_subject_space", "config", validate_case(renamed("my subject"), r"my subject")),
        Case("config_subject_accent", "config", validate_case(renamed("sujet-é"), r"sujet-é")),
        Case(
            "config_video_no_test_range",
            "config",
            validate_case(
                lambda w: put(base(), "datasets.vid", video_dataset(w, {"train": [0, 5, 1]})),
                r"datasets\.vid\.subjects\.clip.*test",
            ),
        ),
        Case(
            "config_video_test_past_end",
            "config",
            validate_case(
                lambda w: put(base(), "datasets.vid", video_dataset(w, {"train": [0, 5, 1], "test": [8, 12, 1]})),
                r"datasets\.vid\.subjects\.clip\.test.*12",
            ),
        ),
        Case("config_device_cuda_no_gpu", "config", validate_case(lambda w: put(base(), "device", "cuda"), r"device")),
        Case(
            "config_device_cuda_cluster_flag",
            "config",
            validate_case(lambda w: put(base(), "device", "cuda"), r".", extra=("--cluster",)),
            "ok",
        ),
        Case(
            "config_validate_from_outside_repo", "config", validate_case(lambda w: base(), r".", cwd_outside=True), "ok"
        ),
        Case(
            "config_yaml_syntax_error",
            "config",
            validate_case(
                None, r"config\.yaml.*cannot read", text="preset: fast\ntraining:\n  overrides: {stage1: [\n"
            ),
        ),
        # the same mistakes as Snakemake sees them (dry runs of the tiny config)
        Case("snakemake_tiny_dry_run", "config", snakemake_case(lambda w: tiny(), r"."), "ok"),
        Case(
            "snakemake_unknown_top_key",
            "config",
            snakemake_case(lambda w: put(tiny(), "learning_rate", 0.1), r"learning_rate"),
        ),
        Case(
            "snakemake_typo_stage1_iteratons",
            "config",
            snakemake_case(lambda w: put(tiny(), "training.overrides.stage1.iteratons", 10), r"iteratons"),
        ),
        Case(
            "snakemake_lr_final_nan",
            "config",
            snakemake_case(lambda w: put(tiny(), "training.overrides.stage2.lr_final", float("nan")), r"lr_final"),
        ),
        Case("snakemake_subject_traversal", "config", snakemake_case(renamed("../../etc", tiny), r"\.\./\.\./etc")),
        Case(
            "snakemake_video_no_test_range",
            "config",
            snakemake_case(
                lambda w: put(tiny(), "datasets.vid", video_dataset(w, {"train": [0, 5, 1]})),
                r"datasets\.vid\.subjects\.clip.*test",
            ),
        ),
        Case(
            "snakemake_device_cuda_real_run",
            "config",
            snakemake_case(
                lambda w: put(tiny(), "device", "cuda"),
                r"device|cuda",
                args=(),
                leftovers=("logs", "resources", "results", "data"),
                timeout=180,
            ),
        ),
        # ---------------------------------------------------------------------------- paths
        Case(
            "paths_evil_root_dry_run",
            "paths",
            snakemake_case(
                lambda w: evil_dataset(w, False),
                r".",
                args=("-n", "-p", "-F", "results/clips/clip/frames.h5"),
                check=check_dry_run_quoting,
            ),
            "ok",
        ),
        Case(
            "paths_evil_root_prepare_real_run",
            "paths",
            snakemake_case(
                lambda w: evil_dataset(w, True), r".", args=("-p", "results/clips/clip/frames.h5"), check=check_real_run
            ),
            "ok",
        ),
        # ------------------------------------------------------------------------ model files
        Case(
            "model_crafted_pickle_export",
            "model-file",
            model_case(lambda w: crafted(w / "model.pt", w / MARKER), "export"),
        ),
        Case(
            "model_crafted_pickle_evaluate",
            "model-file",
            model_case(lambda w: crafted(w / "model.pt", w / MARKER), "evaluate"),
        ),
        Case("model_truncated_export", "model-file", model_case(lambda w: truncated(w / "model.pt"), "export")),
        Case("model_truncated_evaluate", "model-file", model_case(lambda w: truncated(w / "model.pt"), "evaluate")),
        Case("model_json_text_export", "model-file", model_case(json_model, "export")),
        Case("checkpoint_crafted_pickle_train", "checkpoint", crafted_checkpoint, "ok"),
        # ----------------------------------------------------------------------------- inputs
        Case("input_person_control", "input", prepare_case("pppppp"), "ok"),
        Case("input_grey_video", "input", prepare_case("gggggg", names=r"clip\.mp4: no person found")),
        Case("input_noise_video", "input", prepare_case("nnnnnn", names=r"clip\.mp4: no person found")),
        Case("input_zero_K", "input", prepare_case(camera=json.dumps({"K": [[0] * 3] * 3}), names=r"camera\.json.*K")),
        Case(
            "input_nan_in_K",
            "input",
            prepare_case(
                camera=json.dumps({"K": [[50, 0, float("nan")], K[1], K[2]]}), names=r"camera\.json.*K.*not finite"
            ),
        ),
        Case(
            "input_nan_in_distortion",
            "input",
            prepare_case(camera=json.dumps({"K": K, "dist": [0.1, float("nan")]}), names=r"camera\.json.*distortion"),
        ),
        Case(
            "input_camera_json_not_json",
            "input",
            prepare_case(camera='{"K": [[50, 0, 32]', names=r"camera\.json.*JSON"),
        ),
        Case(
            "input_camera_json_missing_K",
            "input",
            prepare_case(camera='{"dist": [0, 0, 0, 0, 0]}', names=r"camera\.json.*'K'"),
        ),
        Case(
            "input_masks_extra_channel",
            "input",
            prepare_case(masks=lambda m: np.repeat(m[..., None], 3, -1), names=r"matte\.h5.*shape"),
        ),
        Case("input_masks_wrong_size", "input", prepare_case(masks=lambda m: m[:, :, :-4], names=r"matte\.h5.*shape")),
        Case(
            "input_partly_bad_capture",
            "input",
            prepare_case(
                "pgpnpg",
                expect_summary=lambda s: (
                    ""
                    if (s.get("few_keypoints") == [1, 3, 5] and s.get("frames") == 6)
                    else f"bad frames not listed: {s}"
                ),
            ),
            "ok",
        ),
        # --------------------------------------------------------------------------- training
        Case(
            "train_settings_iterations_-5",
            "training",
            train_settings_case('{"stage1": {"iterations": -5}}', r"iterations"),
        ),
        Case("train_settings_not_json", "training", train_settings_case("not json", r"--settings")),
    ]
    return cases


def json_model(work: Path) -> Path:
    path = work / "model.pt"
    path.write_text(json.dumps({"model": {}, "stage": 1, "preset": "fast"}))
    return path


def check_dry_run_quoting(work: Path, seen: str) -> str:
    """The printed shell commands give the root back whole once the shell parses them."""
    found = {}
    for line in seen.splitlines():
        line = line.strip().removeprefix("Shell command: ")
        if not line.startswith("delta "):
            continue
        words = shlex.split(line)
        for flag in ("--root", "--video"):
            if flag in words:
                found.setdefault(f"{words[1]} {flag}", words[words.index(flag) + 1])
    want = {"prepare --root": EVIL_ROOT, "matte --video": f"{EVIL_ROOT}/clip.mp4",
            "keypoints --video": f"{EVIL_ROOT}/clip.mp4"}  # fmt: skip
    wrong = {k: found.get(k) for k, v in want.items() if found.get(k) != v}
    return f"printed commands do not quote the root: {wrong}" if wrong else ""


def check_real_run(work: Path, seen: str) -> str:
    import h5py

    rec = work / "results" / "clips" / "clip" / "frames.h5"
    if not rec.is_file():
        return "exit 0 but no frames.h5"
    with h5py.File(rec) as f:
        n = len(f["frame_ids"])
    return "" if n == 7 else f"frames.h5 has {n} frames, expected 7"


# -------------------------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    global SHARED
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", nargs="+", help="run only these cases (names, or patterns such as 'config_*')")
    ap.add_argument("--csv", default=str(REPO / "benchmarks" / "bad_input_probe.csv"))
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder (its path is printed)")
    args = ap.parse_args(argv)
    cases = build_cases()
    if args.only:
        unknown = [p for p in args.only if not any(fnmatch.fnmatchcase(c.name, p) for c in cases)]
        if unknown:
            ap.error(f"no case matches {unknown}; known: {[c.name for c in cases]}")
        cases = [c for c in cases if any(fnmatch.fnmatchcase(c.name, p) for p in args.only)]
    root = Path(tempfile.mkdtemp(prefix="delta-bad-input-"))
    SHARED = Shared(root)
    t0 = time.perf_counter()
    rows = []
    try:
        for case in cases:
            row = execute(case, root)
            rows.append(row)
            print(
                f"{row['outcome']:>14}  {row['case']:<36} {row['seconds']:>6.1f}s  {row['message'][:110]}", flush=True
            )
    finally:
        if args.keep:
            print(f"kept {root}")
        else:
            shutil.rmtree(root, ignore_errors=True)
    fields = ["case", "category", "command", "expected", "exit_code", "outcome", "message", "leftover", "seconds"]
    with open(args.csv, "w", newline="") as f:
        w = csv.DictWriter(f, fields)
        w.writeheader()
        w.writerows(rows)
    counts = {k: sum(r["outcome"] == k for r in rows) for k in
              ("clear_error", "ok", "silent_wrong", "code_execution", "traceback", "unclear_error", "setup_failed")}  # fmt: skip
    leftovers = sum(r["leftover"].startswith("yes") for r in rows)
    print(f"{len(rows)} cases in {time.perf_counter() - t0:.0f} s: " + ", ".join(f"{v} {k}" for k, v in counts.items())
          + f"; {leftovers} with leftovers -> {args.csv}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
