"""The Snakemake workflow end to end on the tiny .test configuration."""

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import h5py
import pandas as pd
import pytest
import yaml

from delta.body.model import load_body_model
from delta.eval.runtime import evaluation_minutes, read_job, videos_minutes
from delta.eval.settings import EvalSettings
from delta.export.settings import ExportSettings
from delta.settings import from_mapping
from delta.training.presets import PRESETS
from tests.conftest import ANNY_CACHE, MODELS_DIR

REPO = Path(__file__).resolve().parents[1]
STANDIN = "standin-male-3-casual"
pytestmark = pytest.mark.workflow


def workflow_copy(tmp_path: Path) -> Path:
    """The workflow's files in a fresh directory, as a user's clone has them."""
    for name in ("Snakefile", "rules", "workflow", "config", ".test"):
        src = REPO / name
        (shutil.copytree if src.is_dir() else shutil.copy)(src, tmp_path / name)
    return tmp_path


def snakemake(workdir: Path, *args: str) -> subprocess.CompletedProcess:
    """Snakemake on two cores, a job one thread: the tiny jobs gain nothing from a second, and beside the
    other pytest worker a two-thread job's OpenMP threads spin waiting for each other (a tiny training job
    took 36 CPU-s in the suite against 13 alone)."""
    cmd = [sys.executable, "-m", "snakemake", "--cores", "2", "--max-threads", "1", *args]
    return subprocess.run(cmd, cwd=workdir, capture_output=True, text=True, timeout=900)


def test_lint_is_clean():
    res = snakemake(REPO, "--lint")
    assert res.returncode == 0, res.stdout + res.stderr
    assert "Congratulations" in res.stdout + res.stderr


def tiny_workflow(work: Path, applications: dict) -> tuple[dict, dict]:
    """The end-to-end run's configuration written into ``work``: one synthetic subject (orthographic, a dress)
    and one People Snapshot subject (its stand-in: pinhole with lens distortion, the dataset's adapter and the
    ONNX steps), with ``applications``; configs merge: the main config lists them all, and the other
    synthetic captures have tests of their own. Returns (main config, CI config)."""
    main = yaml.safe_load((work / "config/config.yaml").read_text())
    main["datasets"]["peoplesnapshot"]["subjects"] = {"male-3-casual": {}}
    for name in ("upper", "tight"):
        del main["datasets"]["synthetic"]["subjects"][name]
    main["applications"] = applications
    (work / "config/config.yaml").write_text(yaml.safe_dump(main))
    cfg = yaml.safe_load((work / ".test/config/config.yaml").read_text())
    for name in ("upper", "tight"):
        del cfg["datasets"]["synthetic"]["subjects"][name]
    cfg["body_model"]["anny"]["cache_dir"] = str(ANNY_CACHE)  # reuse the session's Anny build
    cfg["preprocess"]["models_dir"] = str(MODELS_DIR)  # and its converted models
    (work / ".test/config/ci.yaml").write_text(yaml.safe_dump(cfg))
    return main, cfg


#: every application, across datasets by the real name: the stand-in's avatar in the synthetic subject's
#: fitted motion, wearing its dress (worn, and tried on a photo); the synthetic avatar made heavier
ALL_APPLICATIONS = {"motions": {"loose-motion": "synthetic/loose"},
                    "animate": {"avatars": {"peoplesnapshot/male-3-casual": ["loose-motion"]},
                                "settings": {"max_frames": 3, "meshes": True}},
                    "exteriors": {"loose-dress": "synthetic/loose"},
                    "dress": {"avatars": {"peoplesnapshot/male-3-casual": ["loose-dress"]},
                              "settings": {"turntable_frames": 2}},
                    "tryon": {"avatars": {"peoplesnapshot/male-3-casual": ["loose-dress"]},
                              "settings": {"turntable_frames": 2}},
                    "shapes": {"heavier": {"weight": 0.8}},
                    "reshape": {"avatars": {"synthetic/loose": ["heavier"]}, "settings": {"turntable_frames": 2}}}  # fmt: skip


def test_every_jobs_command_is_one_the_command_line_takes(tmp_path):
    """Each job's shell command, as Snakemake would run it, parses with ``delta``'s own parser: a rule and its
    subcommand agree on every option, for every rule of the whole run with every application (the end-to-end
    run executes most of them; dressing and try-on run in-process in tests/applications)."""
    import shlex

    from delta.cli import build_parser

    work = workflow_copy(tmp_path)
    tiny_workflow(work, ALL_APPLICATIONS)
    res = snakemake(work, "--configfile", ".test/config/ci.yaml", "--dry-run", "--printshellcmds")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    parser, seen = build_parser(), set()
    for line in re.findall(r"^(?:\s*|Shell command: )(delta [^\n]*)$", res.stdout, re.M):
        argv = shlex.split(line.split(" > ")[0])[1:]
        try:
            args = parser.parse_args(argv)
        except SystemExit:
            pytest.fail(f"`delta` does not take the command {line}")
        seen.add(argv[0])
        assert args.func is not None
    assert {"synthesize", "prepare", "fit-init", "analyze-scene", "train", "export", "evaluate", "animate", "dress",
            "try-on", "reshape", "application-scores", "aggregate"} <= seen, sorted(seen)  # fmt: skip


@pytest.mark.slow
def test_tiny_configuration_end_to_end(tmp_path, anny_model, mediapipe_pose_model):
    work = workflow_copy(tmp_path)
    # the stand-in's avatar driven by the synthetic subject's fitted motion (across datasets, by the real
    # name); the synthetic avatar made heavier; dressing and try-on have their commands checked above
    main, cfg = tiny_workflow(
        work, {k: v for k, v in ALL_APPLICATIONS.items() if k not in ("exteriors", "dress", "tryon")}
    )
    res = snakemake(work, "--configfile", ".test/config/ci.yaml")
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-4000:]
    model = load_body_model(work / "resources/body/anny_sub1.npz")
    summary = json.loads((work / "results/body/anny_sub1.json").read_text())
    assert summary["vertices"] == model.num_vertices > 13718
    assert model.num_shape == 8
    assert not any(n.startswith(("finger", "toe", "eye.")) for n in model.joint_names)
    for rule in ("convert_anny", "upsample_body"):
        assert list((work / "logs" / rule).glob("*.log")), f"{rule} wrote no log"
    assert (work / "results/benchmarks/convert_anny/all.tsv").is_file()
    # the embedded default: synthetic captures, and People Snapshot's stand-in in that dataset's layout
    for subject in ("loose", STANDIN):
        capture = work / "data/synthetic" / subject
        assert (capture / f"{subject}.mp4").stat().st_size > 0
        for name in ("params.npz", "frames.h5", "meshes.h5", "splits.json"):
            assert (capture / "gt" / name).is_file()
        assert (work / "results/benchmarks/synthesize" / f"{subject}.tsv").is_file()
    ps = work / "data/synthetic_ps" / STANDIN
    assert sorted(p.name for p in ps.iterdir()) == ["camera.pkl", "keypoints.hdf5", "masks.hdf5", f"{STANDIN}.mp4"]
    assert not (work / "data/synthetic_ps/loose").exists()  # not a stand-in: no such layout
    # frame records of every configured subject, with the sources recorded
    for dataset, subject in (("synthetic", "loose"), ("peoplesnapshot", STANDIN)):
        summary = json.loads((work / "results" / dataset / subject / "frames.json").read_text())
        assert summary["frames"] > 0 and "person" in summary["sources"]
    ps_sources = json.loads((work / "results/peoplesnapshot" / STANDIN / "frames.json").read_text())["sources"]
    assert ps_sources["person"] == "dataset:masks.hdf5"  # shipped: no matting ran
    # shipped keypoints are the dataset's; their relative depths the body landmarker's, for the init fit
    assert ps_sources["keypoints"] == "dataset:keypoints.hdf5"
    assert ps_sources["keypoint_depth"] == "model:mediapipe:pose_landmark_full.onnx"
    with h5py.File(work / "results/peoplesnapshot" / STANDIN / "frames.h5") as rec:
        assert rec["keypoint_depth"].shape == (rec["keypoints"].shape[0], 18)
    assert ps_sources["clothing"] == "model:default:pose_landmark_full.onnx"  # not shipped: the default parser
    assert not (work / "logs/matte").exists()
    # the body-model initialisation ran on every subject
    for dataset, subject in (("synthetic", "loose"), ("peoplesnapshot", STANDIN)):
        report = (work / "results" / dataset / subject / "init" / "report.csv").read_text().splitlines()
        assert report[0] == "frame,flagged,few_keypoints,empty_mask,residual_px,confident_keypoints" and len(report) > 5
    # the scene analysis decided what each capture requires, and training took it (where the config is silent)
    for dataset, subject in (("synthetic", "loose"), ("peoplesnapshot", STANDIN)):
        scene = json.loads((work / "results" / dataset / subject / "scene.json").read_text())
        assert scene["decisions"]["exterior"] == "yes" and scene["decisions"]["capture"] == "full"
        assert (
            scene["evidence"]["reach"]["per_region"]
            and (work / "logs/analyze_scene" / f"{dataset}_{subject}.log").is_file()
        )
        taken = json.loads((work / "results" / dataset / subject / "stage1" / "settings.json").read_text())["settings"]
        own = main["training"].get("subjects", {}).get(subject, {}).get("render", {}).get("max_dist")
        assert taken["render"]["max_dist"] == (own if own is not None else scene["decisions"]["render"]["max_dist"])
        # stage 2's length: the config's own where it sets one (the CI config does), else scaled by the room
        assert scene["decisions"]["stage2"]["length_factor"] >= 1.0
        taken2 = json.loads((work / "results" / dataset / subject / "stage2" / "settings.json").read_text())["settings"]
        assert taken2["stage2"]["iterations"] == 4
    # both training stages ran on every subject, resumable checkpoints beside their outputs
    for dataset, subject in (("synthetic", "loose"), ("peoplesnapshot", STANDIN)):
        for stage in (1, 2):
            out = work / "results" / dataset / subject / f"stage{stage}"
            assert (out / "model.pt").is_file() and (out / "checkpoint.pt").is_file()
            assert len((out / "losses.csv").read_text().splitlines()) == 1 + (6 if stage == 1 else 4)
            assert (work / "logs/train" / f"{dataset}_{subject}_stage{stage}.log").is_file()
            assert (work / "results/benchmarks/train" / f"{dataset}_{subject}_stage{stage}.tsv").is_file()
    # the rendering jobs asked for the minutes their renders need, read from the files as each job started
    log = res.stdout + res.stderr
    asked = re.findall(r"(?:local)?rule (evaluate|export_avatar):(?:\n    [^\n]*)*?\n    wildcards: dataset=(\w+), subject=([\w-]+)"
                       r"(?:\n    [^\n]*)*?\n    resources: [^\n]*runtime=(\d+)", log)  # fmt: skip
    assert {a[0] + a[2] for a in asked} == {r + s for r in ("evaluate", "export_avatar") for s in ("loose", STANDIN)}
    evaluation = from_mapping(EvalSettings, {**main["evaluation"], **cfg["evaluation"]}, "evaluation")
    export = from_mapping(ExportSettings, {**main.get("export", {}), **cfg["export"]}, "export")
    for rule, dataset, subject, minutes in asked:
        out = work / "results" / dataset / subject
        job = read_job(out / "frames.h5", out / f"stage{evaluation.stage}" / "settings.json")
        expected = evaluation_minutes(job, evaluation, 1) if rule == "evaluate" else videos_minutes(job, export, 1)
        assert job is not None and int(minutes) == expected, (rule, subject)
    # evaluation, export and the per-dataset tables
    # scored on whole frames at the capture's scoring size: the stand-in's 64² frames halved as People
    # Snapshot's 1080² are (540²), the synthetic capture at its own 64²; exported at that size too
    for dataset, subjects, size in (("synthetic", ["loose"], 64), ("peoplesnapshot", [STANDIN], 32)):
        table = pd.read_csv(work / "results" / dataset / "metrics.csv")
        assert sorted(table["subject"][:-1]) == sorted(subjects) and table["subject"].iloc[-1] == "mean"
        for col in ("psnr", "ssim", "l1", "stlpips_alex"):
            for tag in ("", "_refined"):
                values = table[f"test_view_{col}{tag}"]
                assert values.notna().all() and (values > 0).all(), (dataset, col, tag)
        assert (table["test_view_psnr"] < 60).all() and (table["test_view_ssim"] <= 1).all()
        assert (table["stage1_s"] > 0).all() and (table["stage2_s"] > 0).all()
        assert (table["export_body_faces"] > 0).all() and table["export_body_watertight"].astype(bool).all()
        assert (table["resolution"] == f"{size}x{size}").all() and (table["image"] == "full").all()
        assert (table["train_resolution"] == 32).all() and (table["data_range"] == 1).all()
        for subject in subjects:
            out = work / "results" / dataset / subject
            frames = pd.read_csv(out / "eval" / "metrics.csv")
            assert set(frames["refined"]) == {True, False} and (frames["background"] == "white").all()
            for name in ("avatar.glb", "turntable.mp4", "novel_pose.mp4", "body_canonical.ply", "export.json"):
                assert (out / "export" / name).stat().st_size > 0, name
            sides = sorted((out / "export" / "sidebyside").glob("*.png"))
            assert sides and cv2.imread(str(sides[0])).shape == (size, 3 * size, 3)
            video = cv2.VideoCapture(str(out / "export" / "turntable.mp4"))
            assert (video.get(cv2.CAP_PROP_FRAME_WIDTH), video.get(cv2.CAP_PROP_FRAME_HEIGHT)) == (size, size)
            video.release()
            assert (out / "stage1" / "losses.png").is_file() and (out / "stage2" / "losses.png").is_file()
    # the application: the stand-in's avatar in the loose subject's motion, whole frames, posed meshes
    animated = work / "results/peoplesnapshot" / STANDIN / "animate/loose-motion"
    about = json.loads((animated / "animation.json").read_text())
    assert about["frames"] == 3 and about["motion_kind"] == "body model" and about["resolution"] == "32x32"
    video = cv2.VideoCapture(str(animated / "animation.mp4"))
    assert video.get(cv2.CAP_PROP_FRAME_COUNT) == 3 and video.get(cv2.CAP_PROP_FRAME_WIDTH) == 32
    video.release()
    assert len(list((animated / "meshes").glob("body_*.ply"))) == 3
    assert (work / "logs/animate" / f"peoplesnapshot_{STANDIN}_loose-motion.log").is_file()
    reshaped = json.loads((work / "results/synthetic/loose/reshape/heavier/reshape.json").read_text())
    assert reshaped["edited"]["weight"] == 0.8 and reshaped["betas_after"] != reshaped["betas_before"]
    # scored against what the generator renders for it: loose made heavier
    table = pd.read_csv(work / "results/synthetic/applications.csv")
    assert list(table["variant"]) == ["as_trained", "edited", "gain"]
    assert (table["subject"] == "loose").all() and (table["application"] == "reshape").all()
    assert (table["name"] == "heavier").all() and table.loc[:1, "psnr"].between(5, 60).all()
    assert table["stlpips_alex"].notna().all()
    assert not (work / "results/peoplesnapshot/applications.csv").exists()  # nothing there is scored
    synthetic = pd.read_csv(work / "results/synthetic/metrics.csv")
    assert synthetic["train_body_err_mm"].notna().all()  # ground truth: geometry columns
    ps = pd.read_csv(work / "results/peoplesnapshot/metrics.csv")
    assert ps["train_body_err_mm"].notna().all()  # the stand-in is scored against its ground truth too
    assert (ps["source"] == "synthetic stand-in of People Snapshot (no copy configured)").all()
    assert (synthetic["source"] == "synthetic (generated, ground truth)").all()
    assert "datasets.peoplesnapshot.root is empty" in res.stdout + res.stderr  # said once, with what to change
    assert (res.stdout + res.stderr).count("datasets.peoplesnapshot.root is empty") == 1
    # the report gathers the tables, images, curves and videos under their categories
    report = snakemake(work, "--configfile", ".test/config/ci.yaml", "--report", "report.html")
    assert report.returncode == 0, report.stdout[-3000:] + report.stderr[-3000:]
    html = (work / "report.html").read_text(errors="replace")
    for category in ("Metrics", "Renders", "Training", "Videos", "Applications"):
        assert category in html, category
    assert "synthetic stand-ins" in html and "datasets.peoplesnapshot.root" in html  # said once, with the line
    # a rerun has nothing to do
    again = snakemake(work, "--configfile", ".test/config/ci.yaml", "--dry-run")
    assert "Nothing to be done" in again.stdout + again.stderr
    # settings only stage 2 reads rerun stage 2 (and what reads it), never stage 1 nor the scene analysis:
    # its rate, and its length, which the scene would otherwise decide
    cfg["training"].setdefault("overrides", {}).setdefault("stage2", {})["lr_final"] = 0.5
    cfg["training"]["overrides"]["stage2"]["iterations"] = 5
    (work / ".test/config/stage2.yaml").write_text(yaml.safe_dump(cfg))
    changed = snakemake(work, "--configfile", ".test/config/stage2.yaml", "--dry-run")
    jobs = re.findall(r"rule train:.*?wildcards: ([^\n]*)", changed.stdout, re.S)
    assert jobs and all(j.endswith("stage=2") for j in jobs), jobs
    assert "rule analyze_scene:" not in changed.stdout


def test_bad_config_stops_before_any_job(tmp_path):
    work = workflow_copy(tmp_path)
    (work / "bad.yaml").write_text("body_model:\n  anny:\n    num_shapes: 3\n")
    res = snakemake(work, "--configfile", "bad.yaml")
    assert res.returncode != 0
    out = res.stdout + res.stderr
    assert "body_model.anny" in out and "num_shapes" in out
    assert not (work / "resources").exists() and not (work / "logs").exists()


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="this machine has a CUDA device")
def test_cuda_without_a_gpu_stops_before_any_job(tmp_path):
    work = workflow_copy(tmp_path)
    (work / "cuda.yaml").write_text("device: cuda\n")
    res = snakemake(work, "--configfile", ".test/config/config.yaml", "cuda.yaml")
    assert res.returncode != 0 and "cuda is configured but torch sees no CUDA device" in res.stdout + res.stderr
    assert not (work / "resources").exists() and not (work / "logs").exists()


@pytest.mark.slow
def test_model_steps_run_only_where_the_dataset_ships_nothing(tmp_path, anny_model):  # its jobs read the Anny cache
    """With the synthetic masks set aside, matting and parsing run (stand-in ONNX graphs with the real
    signatures); with them used, the DAG holds no such step."""
    from tests.preprocess.test_onnx_models import parser_graph, rvm_graph

    work = workflow_copy(tmp_path)
    rvm_graph(work / "rvm.onnx")
    parser_graph(work / "cloth.onnx", classes=4, rgb_class=(1, 2, 3), size=64, extra_outputs=6)
    cfg = yaml.safe_load((work / ".test/config/config.yaml").read_text())
    cfg["body_model"]["anny"]["cache_dir"] = str(ANNY_CACHE)
    default = snakemake(work, "--configfile", ".test/config/config.yaml", "--dry-run")
    assert default.returncode == 0 and "matte" not in default.stdout
    assert "logs/parse/synthetic" not in default.stdout  # the synthetic dataset ships its parsing
    # the stand-in matte is the frame's grey value: on a dark background it is the person (a plausible mask)
    tight = {**cfg["datasets"]["synthetic"]["subjects"]["tight"], "background": [0.02, 0.02, 0.02]}
    cfg["datasets"] = {"synthetic": {"subjects": {"tight": tight}, "use_provided": ["keypoints"]}}
    cfg["preprocess"]["matting"] = {"model": "rvm", "path": "rvm.onnx"}
    cfg["preprocess"]["parsing"] = {"model": "u2net_cloth", "path": "cloth.onnx"}
    cfg["preprocess"]["keypoint_depth"] = False  # the keypoints are shipped: no keypoint step either
    (work / "steps.yaml").write_text(yaml.safe_dump(cfg))
    res = snakemake(work, "results/synthetic/tight/frames.json", "--configfile", "steps.yaml")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    sources = json.loads((work / "results/synthetic/tight/frames.json").read_text())["sources"]
    assert sources == {"person": "model:rvm:rvm.onnx", "clothing": "model:u2net_cloth:cloth.onnx",
                       "keypoints": "dataset:gt/frames.h5:keypoints"}  # fmt: skip
    assert (work / "logs/matte/synthetic_tight.log").is_file() and (work / "logs/parse/synthetic_tight.log").is_file()
    assert not (work / "logs/keypoints").exists()


@pytest.mark.parametrize(
    "config_text,messages",
    [
        ("body_model:\n  name: smplx\n", ["SMPLX_NEUTRAL.npz", "body_model.smplx_path"]),
        ("fitting:\n  subjects: {lose: {}}\n", ["'fitting.subjects.lose': not a configured subject"]),
    ],
)  # fmt: skip
def test_config_problems_are_explained_at_dag_construction(tmp_path, config_text, messages):
    """The Snakefile runs the one validation before it builds the DAG (a file-level and a cross-key problem
    here; every other mistake has its message checked in-process by tests/test_validation.py)."""
    work = workflow_copy(tmp_path)
    (work / "c.yaml").write_text(config_text)
    res = snakemake(work, "--configfile", "c.yaml", "--dry-run")
    assert res.returncode != 0
    for message in messages:
        assert message in res.stdout + res.stderr


@pytest.mark.parametrize("profile", ["slurm", "cluster-generic"])
def test_cluster_profiles_build_the_dag(tmp_path, profile):
    work = workflow_copy(tmp_path)
    res = snakemake(work, "--profile", f"workflow/profiles/{profile}", "--configfile", ".test/config/config.yaml",
                    "--dry-run")  # fmt: skip
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    out = res.stdout + res.stderr
    assert "synthesize" in out and "prepare_frames" in out


def _job_resources(dry_run_output: str, rule: str, job: int = 0) -> dict:
    """The ``resources:`` line of a rule's ``job``-th job in a dry run, as a dict."""
    block = dry_run_output.split(f"rule {rule}:")[1 + job]
    line = next(ln for ln in block.splitlines() if ln.strip().startswith("resources:"))
    return dict(kv.split("=", 1) for kv in line.split(":", 1)[1].strip().split(", "))


@pytest.mark.parametrize(
    "device,gpu_model,expected",
    [("cuda", "", {"gpu": "1"}), ("cuda", "a100", {"gpu": "1", "gpu_model": "a100"}), ("auto", "a100", {}), ("cpu", "", {})],
)  # fmt: skip
def test_training_jobs_request_a_gpu_only_for_cuda(tmp_path, device, gpu_model, expected):
    work = workflow_copy(tmp_path)
    (work / "gpu.yaml").write_text(yaml.safe_dump({"device": device, "cluster": {"gpu_model": gpu_model}}))
    res = snakemake(work, "--profile", "workflow/profiles/slurm", "--executor", "dryrun", "--dry-run",
                    "--configfile", ".test/config/config.yaml", "gpu.yaml")  # fmt: skip
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    for job in range(res.stdout.count("rule train:")):  # both stages of every subject
        res_ = _job_resources(res.stdout, "train", job)
        assert {k: v for k, v in res_.items() if k.startswith("gpu")} == expected
        assert int(res_["mem_mb"]) > 1000 and int(res_["runtime"]) >= 10
    assert "gpu" not in _job_resources(res.stdout, "fit_init")  # CPU-only stages ask for none


@pytest.mark.slow
def test_generic_video_runs_the_offline_default_steps(tmp_path, tiny_captures, mediapipe_pose_model):
    """A dataset of plain videos: matting and keypoints come from the converted MediaPipe model. Its folder's
    name has a space and a shell substitution in it: every path reaches the commands quoted, none runs."""
    work = workflow_copy(tmp_path)
    root = "my videos $(touch PWNED)"
    (work / root).mkdir()
    shutil.copy(tiny_captures / "tight" / "tight.mp4", work / root / "clip.mp4")
    cfg = {
        "body_model": {"anny": {"cache_dir": str(ANNY_CACHE), "num_shape": 8, "num_samples": 64}},
        "preprocess": {"resolution": 64, "models_dir": str(mediapipe_pose_model.parent.parent), "face_landmarks": True},
        "datasets": {
            "clips": {"kind": "video", "root": root, "subjects": {"clip": {"train": [0, 4, 1], "test": [5, 6, 1]}}}
        },
    }
    (work / "video.yaml").write_text(yaml.safe_dump(cfg))
    res = snakemake(work, "results/clips/clip/frames.json", "--configfile", "video.yaml")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    summary = json.loads((work / "results/clips/clip/frames.json").read_text())
    pose = "pose_landmark_full.onnx"
    assert summary["sources"] == {"person": f"model:mediapipe:{pose}", "keypoints": f"model:mediapipe:{pose}",
                                  "clothing": f"model:default:{pose}", "skin": f"model:default:{pose}",
                                  "hair": f"model:default:{pose}", "face_landmarks": f"model:mediapipe:{pose}",
                                  "keypoint_depth": f"model:mediapipe:{pose}", "camera": "default"}  # fmt: skip
    assert summary["frames"] == 7
    with h5py.File(work / "results/clips/clip/frames.h5") as rec:
        assert rec["face_landmarks"].shape == (7, 468, 3) and rec["keypoints"].shape == (7, 18, 3)
    assert "convert_mediapipe" not in res.stdout + res.stderr  # the converted model was reused
    assert not (work / "PWNED").exists() and not (work / root / "PWNED").exists()


@pytest.mark.parametrize(
    "target, message",
    [
        (
            "results/nowhere/metrics.csv",
            "dataset 'nowhere' is not configured; configured datasets: ['peoplesnapshot', 'synthetic']",
        ),
        (
            "results/synthetic/bob/eval/metrics.csv",
            "subject 'bob' is not configured for dataset 'synthetic'; configured subjects: ['loose', 'tight', 'upper']",
        ),
        ("results/synthetic/tight/tradeoff/turbo/eval/summary.json", "trade-off variant 'turbo' is not configured"),
    ],
)
def test_unconfigured_targets_fail_at_dag_construction(tmp_path, target, message):
    work = workflow_copy(tmp_path)
    res = snakemake(work, target, "--configfile", ".test/config/config.yaml", "config/tradeoff.yaml", "--dry-run")
    assert res.returncode != 0
    assert message in res.stdout + res.stderr


def test_tradeoff_variants_reuse_the_main_run_and_name_their_subjects(tmp_path):
    """A variant equal to the main run trains nothing of its own; 'subjects' narrows a variant."""
    work = workflow_copy(tmp_path)
    cfg = yaml.safe_load((work / ".test/config/config.yaml").read_text())
    subjects = sorted(cfg["datasets"]["synthetic"]["subjects"])
    cfg["tradeoff"] = {"variants": {"fast": {"stages": 1}, "few_rays": {"stages": 1, "subjects": [subjects[0]],
                                                                        "stage1": {"rays": 64}},
                                    "res_16": {"stages": 1, "subjects": [subjects[0]], "resolution": 16},
                                    # the preset's own room, set: the scene analysis no longer decides it
                                    "preset_room": {"stages": 1, "subjects": [subjects[0]],
                                                    "render": {"max_dist": PRESETS["fast"]["render"]["max_dist"]}}},
                       "evaluation": {"max_frames": 2}}  # fmt: skip
    (work / "sweep.yaml").write_text(yaml.safe_dump(cfg))
    res = snakemake(
        work, "results/synthetic/tradeoff.csv", "--configfile", "sweep.yaml", "--dry-run", "--printshellcmds"
    )
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    # every variant is scored with the study's own evaluation settings (on whole frames, whatever it trains at)
    scored = {m.group(1): m.group(0) for m in re.finditer(r"delta evaluate --model results/synthetic/\w+/(?:tradeoff/(\w+)/)?stage1/model\.pt[^\n]*", out)}  # fmt: skip
    assert '"max_frames": 2' in scored["res_16"] and '"max_frames": 2' in scored["few_rays"]
    trained = set(re.findall(r"output: results/synthetic/(\w+)/tradeoff/(\w+)/stage1/model\.pt", out))
    assert {v for _, v in trained} >= {"few_rays", "preset_room"} and "fast" not in {v for _, v in trained}
    assert {s for s, v in trained if v == "few_rays"} == {subjects[0]}
    # fast is scored from the main run's stage 1
    assert all(f"results/synthetic/{s}/stage1/model.pt" in out for s in subjects)
    # a subject's own training keys reach every variant but one that does not inherit them (the reference)
    cfg.setdefault("training", {})["subjects"] = {subjects[0]: {"render": {"samples": 7}}}
    cfg["tradeoff"]["variants"]["ref"] = {"stages": 1, "inherit_training": False, "stage1": {"rays": 32}}
    (work / "sweep.yaml").write_text(yaml.safe_dump(cfg))
    res = snakemake(
        work, "results/synthetic/tradeoff.csv", "--configfile", "sweep.yaml", "--dry-run", "--printshellcmds"
    )
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    settings = {m.group(1): json.loads(m.group(2)) for m in re.finditer(
        rf"delta train --stage 1 [^\n]*--out results/synthetic/{subjects[0]}/tradeoff/(\w+)/stage1 [^\n]*--settings '([^']*)'", out)}  # fmt: skip
    assert settings["ref"]["stage1"]["rays"] == 32 and settings["ref"]["render"]["samples"] != 7
    assert settings["ref"]["resolution"] != cfg["training"]["overrides"]["resolution"]  # nor training.overrides
    assert settings["few_rays"]["render"]["samples"] == 7  # the subject's own, after training.overrides
    cfg["tradeoff"]["variants"]["ref"]["inherit_training"] = "no"
    (work / "sweep.yaml").write_text(yaml.safe_dump(cfg))
    res = snakemake(work, "results/synthetic/tradeoff.csv", "--configfile", "sweep.yaml", "--dry-run")
    assert (
        res.returncode != 0
        and "tradeoff.variants.ref.inherit_training': 'no' is not true or false" in res.stdout + res.stderr
    )
    del cfg["tradeoff"]["variants"]["ref"], cfg["training"]["subjects"]
    # 'only' runs a part of the study; a name it lists must be a variant
    cfg["tradeoff"]["only"] = ["few_rays"]
    (work / "sweep.yaml").write_text(yaml.safe_dump(cfg))
    res = snakemake(work, "results/synthetic/tradeoff.csv", "--configfile", "sweep.yaml", "--dry-run")
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    assert set(re.findall(r"/tradeoff/(\w+)/eval/summary\.json", out)) == {"few_rays"}
    cfg["tradeoff"]["only"] = ["few_rays", "turbo"]
    (work / "sweep.yaml").write_text(yaml.safe_dump(cfg))
    res = snakemake(work, "results/synthetic/tradeoff.csv", "--configfile", "sweep.yaml", "--dry-run")
    assert res.returncode != 0 and "config key 'tradeoff.only': 'turbo' is not a variant" in res.stdout + res.stderr
    del cfg["tradeoff"]["only"]
    cfg["tradeoff"]["variants"]["few_rays"]["subjects"] = ["nobody"]
    (work / "sweep.yaml").write_text(yaml.safe_dump(cfg))
    res = snakemake(work, "results/synthetic/tradeoff.csv", "--configfile", "sweep.yaml", "--dry-run")
    assert (
        res.returncode != 0
        and "tradeoff.variants.few_rays.subjects': ['nobody'] are not configured subjects" in res.stdout + res.stderr
    )


def test_a_talking_subject_alone_gets_the_face_body_model(tmp_path):
    """config/heads.yaml adds a talking head: its stages read the body model with the expression space, the
    other subjects' read the plain one (their jobs unchanged), and an avatar wearing the talker's hair loads
    the talker with its own body model."""
    work = workflow_copy(tmp_path)
    cfg = yaml.safe_load((work / ".test/config/config.yaml").read_text())
    cfg["applications"] = {"exteriors": {"talker-hair": "synthetic/talker"},
                           "dress": {"avatars": {"synthetic/tight": ["talker-hair"]}}}  # fmt: skip
    (work / "apps.yaml").write_text(yaml.safe_dump(cfg))
    target = "results/synthetic/tight/dress/talker-hair/dress.json"
    res = snakemake(work, target, "--configfile", "apps.yaml", "config/heads.yaml", "--dry-run", "--printshellcmds")
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    face, plain = "resources/body/anny_sub1_face.npz", "resources/body/anny_sub1.npz"
    fits = dict(re.findall(r"delta fit-init --record results/synthetic/(\w+)/frames\.h5 --body (\S+)", out))
    assert fits == {"talker": face, "tight": plain}
    assert "delta anny-expressions" in out and "delta attach-expressions" in out
    assert "--expressions resources/body/anny_expressions.npz" in out  # the talker's capture talks
    dress = re.search(r"delta dress [^\n]*", out).group(0)
    assert f"--body {plain}" in dress and f"--wearer-body {face}" in dress
    # the talker's record keeps its face points; tight's prepare job is the one it always was
    assert '"use_provided": ["person", "clothing", "skin", "hair", "keypoints", "face_points"]' in out
    assert '"use_provided": ["person", "clothing", "skin", "hair", "keypoints"]' in out


def test_hair_moves_between_two_talking_heads_as_a_layer(tmp_path):
    """config/heads.yaml: both talkers train their hair and shirt as layers; the long-haired talker wears the
    short hair over its own shirt, both avatars read with the face body model, scored against a talking
    capture the generator renders with the short hair."""
    work = workflow_copy(tmp_path)
    target = "results/synthetic/talker/dress/short-hair/dress.json"
    res = snakemake(work, target, "--configfile", "config/config.yaml", "config/heads.yaml", "--dry-run",
                    "--printshellcmds")  # fmt: skip
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    face = "resources/body/anny_sub1_face.npz"
    dress = re.search(r"delta dress [^\n]*", out).group(0)
    assert f"--body {face}" in dress and f"--wearer-body {face}" in dress and "--layers hair" in dress
    assert "--model results/synthetic/talker/stage2/model.pt" in dress
    assert "--wearer-model results/synthetic/talker-short/stage2/model.pt" in dress
    trains = re.findall(r"delta train [^\n]*", out)
    assert len(trains) == 4 and all('"layers": "split"' in line for line in trains)
    truth = re.search(r"delta synthesize --subject talker\.wears\.short-hair [^\n]*", out).group(0)
    assert (
        '"expressions": "talk"' in truth
        and '"hair": "short"' in truth
        and '"kind": "tshirt", "pattern": "plaid"' in truth
    )
    assert "--expressions resources/body/anny_expressions.npz" in truth  # the truth talks as the talker does


def test_a_talking_head_is_reenacted_by_a_tracked_face_and_only_by_one(tmp_path):
    """applications.reenact: the talker driven by a tracked face is one job reading both avatars with the
    face body model, scored against a generated truth where both are synthetic; a driver or an avatar
    without a tracked face is refused before any job."""
    work = workflow_copy(tmp_path)
    cfg = yaml.safe_load((work / ".test/config/config.yaml").read_text())
    cfg["applications"] = {"drivers": {"talker-face": "synthetic/talker"},
                           "reenact": {"avatars": {"synthetic/talker": ["talker-face"]}, "max_frames": 12}}  # fmt: skip
    (work / "apps.yaml").write_text(yaml.safe_dump(cfg))
    target = "results/synthetic/talker/reenact/talker-face/reenactment.mp4"
    res = snakemake(work, target, "--configfile", "config/heads.yaml", "apps.yaml", "--dry-run", "--printshellcmds")
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    job = re.search(r"delta reenact [^\n]*", out).group(0)
    assert "--model results/synthetic/talker/stage2/model.pt" in job
    assert "--driver-model results/synthetic/talker/stage2/model.pt" in job
    assert "--body resources/body/anny_sub1_face.npz" in job and "--max-frames 12" in job
    # both synthetic: scored against the talker the generator drives by the driver's true face from frame 0
    assert "--truth data/synthetic/talker.follows.talker-face --perceptual resources/models/stlpips" in job
    assert "--score-frames 4 --supersample 2" in job
    truth = re.search(r"delta synthesize --subject talker\.follows\.talker-face [^\n]*", out).group(0)
    assert '"driven": {"anchor": 0, "by": {' in truth and '"reference": 0}' in truth
    assert "--expressions resources/body/anny_expressions.npz" in truth
    for change, message in (
        ({"drivers": {"talker-face": "synthetic/tight"}}, "'synthetic/tight' is not a tracked face"),
        ({"reenact": {"avatars": {"synthetic/tight": ["talker-face"]}}},
         "applications.reenact.avatars.synthetic/tight': 'synthetic/tight' is not a tracked face"),
    ):  # fmt: skip
        bad = yaml.safe_load(yaml.safe_dump(cfg))
        bad["applications"].update(change)
        (work / "bad.yaml").write_text(yaml.safe_dump(bad))
        res = snakemake(work, target, "--configfile", "config/heads.yaml", "bad.yaml", "--dry-run")
        assert res.returncode != 0 and message in res.stdout + res.stderr, (res.stdout + res.stderr)[-2000:]


def _tiny_video(path: Path, frames: int = 8, size: int = 64) -> None:
    import numpy as np

    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 25, (size, size))
    for k in range(frames):
        writer.write(np.full((size, size, 3), 20 * k % 255, np.uint8))
    writer.release()


def test_a_video_close_up_tracks_its_face_and_gets_the_face_body_model(tmp_path):
    """A video subject marked ``framing: head`` runs its model steps on the tracked face, its record places
    the face-mesh landmarks on the body mesh (the embedding rule), and its stages read the face body model;
    the full-body subject beside it is run as before."""
    work = workflow_copy(tmp_path)
    (work / "clips").mkdir()
    for name in ("talk", "walk"):
        _tiny_video(work / "clips" / f"{name}.mp4")
    cfg = {"datasets": {"clips": {"kind": "video", "root": "clips", "subjects": {
        "talk": {"train": [0, 5, 1], "test": [6, 7, 1], "framing": "head"},
        "walk": {"train": [0, 5, 1], "test": [6, 7, 1]}}}}}  # fmt: skip
    (work / "clips.yaml").write_text(yaml.safe_dump(cfg))
    targets = [f"results/clips/{s}/init/params.npz" for s in ("talk", "walk")]
    res = snakemake(work, *targets, "--configfile", "clips.yaml", "--dry-run", "--printshellcmds")
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    for step in ("matte", "parse", "keypoints"):
        lines = {s: re.search(rf"delta {step} --video clips/{s}\.mp4[^\n]*", out).group(0) for s in ("talk", "walk")}
        assert "--framing head" in lines["talk"] and "--framing full" in lines["walk"], (step, lines)
        assert '"framing"' not in lines["talk"]  # the frame ranges hold the ranges only
        if step == "parse":  # the parser partitions the matting step's person: a head's mask is cut once
            assert all(f"--person results/clips/{s}/matting.h5" in line for s, line in lines.items()), lines
    embedding = "resources/body/anny_sub1_face_landmarks.npz"
    assert "delta embed-face-landmarks" in out
    prepare = {
        s: re.search(rf"delta prepare --root clips --subject {s} [^\n]*", out).group(0) for s in ("talk", "walk")
    }
    assert f"--face-embedding {embedding}" in prepare["talk"] and "--face-embedding" not in prepare["walk"]
    fits = dict(re.findall(r"delta fit-init --record results/clips/(\w+)/frames\.h5 --body (\S+)", out))
    assert fits == {"talk": "resources/body/anny_sub1_face.npz", "walk": "resources/body/anny_sub1.npz"}


def test_a_video_subjects_framing_is_checked_before_any_job(tmp_path):
    work = workflow_copy(tmp_path)
    (work / "clips").mkdir()
    _tiny_video(work / "clips" / "talk.mp4")
    cfg = {"datasets": {"clips": {"kind": "video", "root": "clips",
                                  "subjects": {"talk": {"train": [0, 5, 1], "test": [6, 7, 1], "framing": "face"}}}}}  # fmt: skip
    (work / "clips.yaml").write_text(yaml.safe_dump(cfg))
    res = snakemake(work, "results/clips/talk/frames.h5", "--configfile", "clips.yaml", "--dry-run")
    assert res.returncode != 0
    assert "config key 'datasets.clips.subjects.talk.framing': 'face'; expected one of ['full', 'head']" in (
        res.stdout + res.stderr
    )


def test_a_layer_of_an_exterior_is_worn_alone(tmp_path):
    """config/layers.yaml: loose and tight train in layers, tight wears loose's hair alone and its dress alone,
    each scored against a generated truth that takes only that layer (tight's own garments under loose's hair)."""
    work = workflow_copy(tmp_path)
    targets = [f"results/synthetic/tight/dress/{e}/dress.json" for e in ("loose-hair", "loose-dress-only")]
    res = snakemake(work, *targets, "--configfile", "config/config.yaml", "config/layers.yaml", "--dry-run",
                    "--printshellcmds")  # fmt: skip
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    dress = {
        e: re.search(rf"delta dress [^\n]*dress/{e}[^\n]*", out).group(0) for e in ("loose-hair", "loose-dress-only")
    }
    assert "--layers hair" in dress["loose-hair"] and "--layers clothing" in dress["loose-dress-only"]
    assert "delta synthesize" in out and "tight.wears.loose-hair" in out
    layers = re.findall(r"delta train [^\n]*loose[^\n]*", out)
    assert layers and all('"layers": "split"' in line for line in layers)
    # the wearer in layers too: it keeps its own clothing under loose's hair, as the truth does
    wearer = re.findall(r"delta train [^\n]*results/synthetic/tight/stage[^\n]*", out)
    assert wearer and all('"layers": "split"' in line for line in wearer)
    cfg = yaml.safe_load((work / "config/layers.yaml").read_text())
    cfg["training"] = {}  # loose trained as one NeRF: its hair cannot be taken alone
    (work / "one.yaml").write_text(yaml.safe_dump(cfg))
    res = snakemake(work, targets[0], "--configfile", "config/config.yaml", "one.yaml", "--dry-run")
    assert res.returncode != 0 and "which is trained as one NeRF" in res.stdout + res.stderr


def test_evaluation_waits_for_the_meshes_not_the_videos(tmp_path):
    """The export is two jobs: the meshes (seconds), which evaluation and the applications read, and the
    videos (whole frames rendered at the capture's size), which only the dataset's table waits for; each
    job is given only the export settings it reads."""
    work = workflow_copy(tmp_path)
    res = snakemake(work, "results/synthetic/tight/eval/metrics.csv", "--dry-run", "--printshellcmds")
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    assert re.findall(r"delta export --part (\w+)", out) == ["meshes"]
    evaluate = re.search(r"delta evaluate [^\n]*", out).group(0)
    assert "--export-dir results/synthetic/tight/export" in evaluate
    res = snakemake(work, "results/synthetic/metrics.csv", "--dry-run", "--printshellcmds")
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-3000:]
    jobs = dict(
        re.findall(r"delta export --part (\w+) [^\n]*--out results/synthetic/tight/export --settings '([^']*)'", out)
    )
    meshes, videos = json.loads(jobs["meshes"]), json.loads(jobs["videos"])
    assert "grid" in meshes and "turntable_frames" not in meshes
    assert "turntable_frames" in videos and "grid" not in videos
