"""The one validation: every mistake a user makes in a config is named before any job starts, by the
workflow and by ``delta validate-config`` alike (each case here passed validate-config before)."""

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from delta import DeltaError
from delta.config import load_config, validate_workflow_config
from delta.training.presets import resolve

REPO = Path(__file__).resolve().parents[1]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"
SYN = {"synthetic": {"subjects": {"tight": {}}}}


def problems(cfg: dict, base: Path = REPO, device: bool = True) -> str:
    with pytest.raises(DeltaError) as err:
        validate_workflow_config(cfg, SCHEMA, base_dir=base, device=device)
    return str(err.value)


def video(path: Path, frames: int, size: int = 32) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, (size, size))
    for i in range(frames):
        out.write(np.full((size, size, 3), (10 * i) % 256, np.uint8))
    out.release()
    return path


@pytest.mark.parametrize("cfg,expected", [
    ({"preset": "fast", "training": {"subjects": {"tight": {"preset": "fastest"}}}}, "unknown preset 'fastest'"),
    ({"training": {"overrides": {"stage1": {"iteratons": 5}}}}, "iteratons"),
    ({"fitting": {"settings": {"sil_wieght": 3}}}, "unknown key 'sil_wieght'"),
    ({"datasets": {"synthetic": {"subjects": {"tight": {"garmnets": []}}}}}, "garmnets"),
    ({"fitting": {"settings": {"iterations": [-1, 10, 10]}}}, "'iterations' must be three step counts >= 0"),
    ({"training": {"overrides": {"stage2": {"lr_final": float("nan")}}}}, "training.overrides.stage2.lr_final': NaN"),
    ({"training": {"overrides": {"stage1": {"iterations": -5}}}}, "training.stage1.iterations: -5"),
    ({"training": {"overrides": {"stage1": {"rays": 0}}}}, "training.stage1.rays: 0"),
    ({"training": {"overrides": {"resolution": 100000}}}, "training.resolution: 100000"),
    ({"preprocess": {"crop_margin": float("nan")}}, "'preprocess.crop_margin': NaN"),
    ({"evaluation": {"supersample": 100}}, "'evaluation.supersample': 100 is greater than the maximum"),
    ({"fitting": {"subjects": {"nobody": {}}}}, "'fitting.subjects.nobody': not a configured subject"),
    ({"tradeoff": {"variants": {"v": {"stage1": {"rays": -1}}}}}, "tradeoff.variants.v (subject 'tight')"),
    ({"applications": {"motions": {"m": "synthetic/bob"}}}, "'synthetic/bob' is neither a configured 'dataset/subject' nor a motion file"),
    ({"applications": {"motions": {"a/b": "synthetic/tight"}}}, "motion name 'a/b' is not allowed"),
    ({"applications": {"animate": {"avatars": {"synthetic/bob": []}}}}, "'synthetic/bob' names no configured subject"),
    ({"applications": {"animate": {"avatars": {"synthetic/tight": ["walk"]}}}}, "motions ['walk'] are not in applications.motions"),
    ({"applications": {"animate": {"settings": {"fps": 0}}}}, "applications.animate.settings.fps"),
    ({"applications": {"exteriors": {"e": "synthetic/bob"}}}, "'applications.exteriors.e': 'synthetic/bob' names no configured subject"),
    ({"applications": {"dress": {"avatars": {"synthetic/tight": ["e"]}}}}, "exteriors ['e'] are not in applications.exteriors"),
    ({"applications": {"exteriors": {"e": "synthetic/tight:hat"}}}, "the layers after ':' are one or more of ['clothing', 'hair']"),
    ({"applications": {"exteriors": {"e": "synthetic/tight:hair"}}}, "which is trained as one NeRF: set training.subjects.tight.layers: split"),
    ({"applications": {"shapes": {"s": {"weight": "0.3"}}}}, "'applications.shapes.s.weight'"),
    ({"applications": {"shapes": {"s": {"wieght": 0.3}}}}, "applications.shapes.s"),
    ({"datasets": {"synthetic": {"subjects": {"x": {"garments": ["cape"]}}}}},
     "datasets.synthetic.subjects.x.garments[0]: unknown garment 'cape'"),
    ({"datasets": {"clips": {"root": "videos", "subjects": {"a": {}}}}}, "'datasets.clips.kind' is required"),
    ({"preprocess": {"matting": {"model": "rvm", "path": "nowhere/rvm.onnx"}}},
     "'preprocess.matting.path': ONNX model not found: " + str(REPO / "nowhere/rvm.onnx")),
    ({"fitting": {"subjects": {"tight": {"exterior_fil": 0.1}}}}, "fitting (subject 'tight'): unknown key 'exterior_fil'"),
    ({"fitting": {"settings": {"iterations": [10, 10]}}}, "'iterations' must be three step counts >= 0, got [10, 10]"),
])  # fmt: skip
def test_each_mistake_is_named(cfg, expected):
    cfg = {"datasets": SYN, **cfg} if "datasets" not in cfg else cfg
    assert expected in problems(cfg)


def test_an_exterior_of_a_layer_needs_an_avatar_trained_in_layers():
    from delta.config import exterior_layers, exterior_source

    cfg = {"datasets": SYN, "training": {"subjects": {"tight": {"layers": "split"}}},
           "applications": {"exteriors": {"e": "synthetic/tight:hair", "both": "synthetic/tight:clothing+hair",
                                          "all": "synthetic/tight"}}}  # fmt: skip
    full = validate_workflow_config(cfg, SCHEMA, base_dir=REPO, device=False)  # no problem
    assert exterior_source(full, "e") == ("synthetic", "tight") and exterior_layers(full, "e") == ["hair"]
    assert exterior_layers(full, "both") == ["clothing", "hair"] and exterior_layers(full, "all") == []


@pytest.mark.parametrize("name", ["..", "../../etc", "my subject", "sujet-é", ".hidden", "a/b"])
def test_unsafe_subject_and_dataset_names_are_refused(name):
    assert f"subject name {name!r} is not allowed" in problems({"datasets": {"synthetic": {"subjects": {name: {}}}}})
    msg = problems({"datasets": {name: {"kind": "video", "root": "v", "subjects": {"clip": {}}}}})
    assert f"dataset name {name!r} is not allowed" in msg


def test_frame_ranges_are_checked_against_the_video(tmp_path):
    video(tmp_path / "videos" / "clip.mp4", 12)
    ds = lambda subject: {"clips": {"kind": "video", "root": "videos", "subjects": {"clip": subject}}}  # noqa: E731
    assert "no 'test' frame range" in problems({"datasets": ds({"train": [0, 8, 1]})}, tmp_path)
    msg = problems({"datasets": ds({"train": [0, 8, 1], "test": [9, 30, 1]})}, tmp_path)
    assert "clip.test': ends at frame 30, but" in msg and "has 12 frames (0 to 11)" in msg
    assert "is not a valid range" in problems({"datasets": ds({"train": [5, 2, 1], "test": [9, 11, 1]})}, tmp_path)
    assert "unknown key(s) ['tset']" in problems({"datasets": ds({"train": [0, 8, 1], "tset": [9, 11, 1]})}, tmp_path)
    cfg = validate_workflow_config(
        {"datasets": ds({"train": [0, 8, 1], "test": [9, 11, 1]})}, SCHEMA, base_dir=tmp_path
    )
    assert cfg["datasets"]["clips"]["subjects"]["clip"]["test"] == [9, 11, 1]


def people_snapshot_copy(root: Path, subject: str, frames: int, skip: str = "") -> Path:
    """A subject folder in People Snapshot's layout (the files the existence check reads; ``skip`` left out)."""
    video(root / subject / f"{subject}.mp4", frames)
    for name in ("masks.hdf5", "camera.pkl", "keypoints.hdf5"):
        if name != skip:
            (root / subject / name).write_bytes(b"")
    if skip == f"{subject}.mp4":
        (root / subject / skip).unlink()
    return root


def test_a_standard_people_snapshot_split_is_checked_against_a_short_copy(tmp_path):
    people_snapshot_copy(tmp_path / "ps", "male-3-casual", 100)
    cfg = {"datasets": {"peoplesnapshot": {"kind": "peoplesnapshot", "root": "ps", "subjects": {"male-3-casual": {}}}}}
    assert "ends at frame 455, but" in problems(cfg, tmp_path)


@pytest.mark.parametrize("skip", ["camera.pkl", "male-3-casual.mp4"])
def test_a_partial_people_snapshot_copy_names_the_missing_file_and_where(tmp_path, skip):
    people_snapshot_copy(tmp_path / "ps", "male-3-casual", 700, skip=skip)
    cfg = {"datasets": {"peoplesnapshot": {"kind": "peoplesnapshot", "root": "ps", "subjects": {"male-3-casual": {}}}}}
    msg = problems(cfg, tmp_path)
    assert f"People Snapshot subject 'male-3-casual' lacks ['{skip}'] in {tmp_path / 'ps' / 'male-3-casual'}" in msg
    assert "leave root empty for the synthetic stand-in" in msg


def test_animations_name_subjects_by_their_configured_names(tmp_path):
    """A People Snapshot subject run on its stand-in is still named by its real name; a motion file is a path."""
    from delta.config import application_jobs, exterior_source, motion_source

    (tmp_path / "walk.npz").write_bytes(b"")
    cfg = validate_workflow_config({"datasets": {**SYN, "peoplesnapshot": {"kind": "peoplesnapshot", "subjects": {"male-3-casual": {}}}},
                                    "applications": {"motions": {"theirs": "peoplesnapshot/male-3-casual", "walk": "walk.npz"},
                                                     "animate": {"avatars": {"synthetic/tight": ["theirs", "walk"],
                                                                             "peoplesnapshot/male-3-casual": ["walk"]}},
                                                     "exteriors": {"jeans": "peoplesnapshot/male-3-casual"},
                                                     "dress": {"avatars": {"synthetic/tight": ["jeans"]}}}},
                                   SCHEMA, base_dir=tmp_path)  # fmt: skip
    assert motion_source(cfg, "theirs") == ("peoplesnapshot", "standin-male-3-casual")
    assert motion_source(cfg, "walk") == "walk.npz"
    assert application_jobs(cfg, "animate") == [("synthetic", "tight", "theirs"), ("synthetic", "tight", "walk"),
                                                ("peoplesnapshot", "standin-male-3-casual", "walk")]  # fmt: skip
    assert exterior_source(cfg, "jeans") == ("peoplesnapshot", "standin-male-3-casual")
    assert application_jobs(cfg, "dress") == [("synthetic", "tight", "jeans")]


def test_without_a_copy_people_snapshot_is_its_stand_in():
    from delta.synthetic.standin import standin

    real = ["male-3-casual", "female-4-casual"]
    cfg = validate_workflow_config({"datasets": {"peoplesnapshot": {"kind": "peoplesnapshot", "subjects": {s: {} for s in real}}}},
                                   SCHEMA, base_dir=REPO)  # fmt: skip
    ps = cfg["datasets"]["peoplesnapshot"]
    assert sorted(ps["subjects"]) == ["standin-female-4-casual", "standin-male-3-casual"]
    assert ps["standin_of"]["standin-male-3-casual"] == "male-3-casual"
    assert ps["root"] == "data/synthetic_ps" and sorted(cfg["standins"]) == sorted(ps["subjects"])
    # the real splits' shapes at a quarter of their frames, rounded up: male-3-casual trains on 114, tests on 55
    assert ps["subjects"]["standin-male-3-casual"] == {"train": [0, 28, 1], "test": [29, 42, 1]}
    spec = cfg["standins"]["standin-male-3-casual"]
    assert spec["resolution"] == 1080 and spec["turn_frames"] == 43 and spec["camera"] == "pinhole"
    assert standin("female-4-casual")[1]["phenotype"]["gender"] < 0.5 < spec["phenotype"]["gender"]
    assert (
        len(cfg["standin_notes"]) == 1 and "set datasets.peoplesnapshot.root to the folder" in cfg["standin_notes"][0]
    )
    small = validate_workflow_config({"datasets": {"peoplesnapshot": {"kind": "peoplesnapshot", "subjects": {"male-3-casual": {}},
                                                                      "standin": {"resolution": 64, "frames": 0.04}}}},
                                     SCHEMA, base_dir=REPO)  # fmt: skip
    assert small["standins"]["standin-male-3-casual"]["turn_frames"] == 5 + 3  # ceil(4.56), ceil(2.2)


def test_cuda_without_a_gpu_is_refused_before_any_job(monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert "cuda is configured but torch sees no CUDA device" in problems({"datasets": SYN, "device": "cuda"})
    validate_workflow_config({"datasets": SYN, "device": "cuda"}, SCHEMA, base_dir=REPO, device=False)  # cluster


def test_validate_config_runs_outside_the_repository(tmp_path):
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    cfg["training"]["overrides"] = {"stage1": {"iteratons": 5}}
    (tmp_path / "config").mkdir()
    (tmp_path / "config" / "bad.yaml").write_text(yaml.safe_dump(cfg))
    run = lambda path: subprocess.run(
        [sys.executable, "-m", "delta.cli", "validate-config", str(path)],  # noqa: E731
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env={**os.environ},
    )
    good = run(REPO / "config" / "config.yaml")
    assert good.returncode == 0 and "valid" in good.stdout, good.stderr
    bad = run(tmp_path / "config" / "bad.yaml")
    assert bad.returncode == 2 and "iteratons" in bad.stderr and "Traceback" not in bad.stderr


def test_the_shipped_configs_are_valid_as_the_workflow_merges_them():
    main, tiny, study = (
        REPO / "config" / "config.yaml",
        REPO / ".test" / "config" / "config.yaml",
        REPO / "config" / "tradeoff.yaml",
    )
    for paths in ([main], [main, tiny], [main, study], [main, tiny, study]):
        cfg = load_config(paths, SCHEMA)
        assert ("tradeoff" in cfg) == (study in paths)  # the study is opt-in
    with pytest.raises(DeltaError, match=r"(?s)tradeoff.yaml: invalid configuration .*not configured subjects"):
        load_config([study], SCHEMA)  # the study alone names subjects no dataset has


def test_every_preset_passes_its_own_ranges():
    for preset in ("fast", "balanced", "paper"):
        resolve(preset)


@pytest.mark.parametrize("override,key", [
    ({"render": {"round_trip": 3}}, "render.round_trip: 3"),
    ({"render": {"perturb": "no"}}, "render.perturb: 'no'"),
    ({"render": {"occupancy": {"enabled": 1}}}, "render.occupancy.enabled: 1"),
])  # fmt: skip
def test_a_switch_that_is_not_true_or_false_is_named(override, key):
    with pytest.raises(DeltaError, match=f"training.{key} is not true or false"):
        resolve("fast", override)
    assert resolve("fast", {"render": {"round_trip": False}}).avatar.render.round_trip is False
