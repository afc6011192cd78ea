"""Checkpoints and model files: finished work is not redone, corrupt or crafted files are set aside
or refused (never run), and a stage's fingerprint covers what that stage reads and nothing else."""

import copy
import os

import pytest
import torch

from delta import DeltaError
from delta.io import load_state
from delta.training.presets import resolve, stage_view
from delta.training.run import MODEL_FORMAT, migrate_model
from delta.training.trainer import CHECKPOINT, PREVIOUS_CHECKPOINT, fingerprint, train_stage
from tests.training.test_training import TINY, _model

pytestmark = pytest.mark.slow


class _Payload:
    """Unpickling this runs ``touch <marker>``: what a crafted avatar file would do."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return os.system, (f"touch '{self.marker}'",)


def crafted_file(path, marker, **extra):
    torch.save({"model": {}, "step": 1, "payload": _Payload(marker), **extra}, path)
    return path


def test_a_crafted_file_is_refused_and_nothing_runs(tmp_path):
    marker = tmp_path / "ran"
    path = crafted_file(tmp_path / "model.pt", marker)
    with pytest.raises(DeltaError, match="refused: it holds objects other than tensors"):
        load_state(path)
    assert not marker.exists()


def test_export_refuses_a_crafted_model(tiny_training, tmp_path, capsys):
    from delta.cli import main

    marker = tmp_path / "ran"
    path = crafted_file(tmp_path / "model.pt", marker)
    inputs = tiny_training["tight"]
    code = main(["export", "--model", str(path), "--record", inputs["record"], "--body", inputs["body"],
                 "--out", str(tmp_path / "out")])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "refused" in err and str(path) in err and "Traceback" not in err
    assert not marker.exists() and not (tmp_path / "out").exists()


@pytest.mark.parametrize("cut", [0, 100, 0.5])
def test_a_truncated_file_names_itself(tmp_path, cut):
    path = tmp_path / "model.pt"
    torch.save({"model": {"w": torch.ones(1000)}}, path)
    data = path.read_bytes()
    path.write_bytes(data[: int(cut * len(data)) if isinstance(cut, float) else cut])
    with pytest.raises(DeltaError, match=r"model\.pt: cannot be read: truncated or corrupt"):
        load_state(path)


def test_model_format_migration():
    old = {"model": {"w": torch.zeros(1)}, "stage": 1, "preset": "fast", "settings": {"dynamics": {"dropout": 0.2}}}
    new = migrate_model(old, "old.pt")
    assert new["format"] == MODEL_FORMAT and new["capture"] == "full" and new["frozen_joints"] == []
    assert new["settings"]["dynamics"] == {"dropout": 0.2, "time_freqs": 0, "pose_knots": 0}
    assert new["settings"]["render"]["occupancy"]["enabled"] is False  # no grid in the file: none is built
    assert new["settings"]["mouth_shade"] == 1.0  # the mouth's inside started at the skin colour
    second = {**old, "format": 2, "settings": {"dynamics": {"time_freqs": 0, "pose_knots": 0}, "mouth_shade": 0.5}}
    assert migrate_model(second, "second.pt")["settings"]["mouth_shade"] == 0.5  # a user's own value stands
    assert migrate_model(new, "new.pt") == new
    with pytest.raises(DeltaError, match="model format 99"):
        migrate_model({**new, "format": 99}, "future.pt")
    with pytest.raises(DeltaError, match="missing 'settings'"):
        migrate_model({"model": {}, "stage": 1, "preset": "fast"}, "bad.pt")


def test_a_stage_fingerprint_covers_what_the_stage_reads(tiny_training):
    st = resolve("fast", TINY)
    data = _model(tiny_training["tight"], st)[1]
    only2 = resolve("fast", TINY, {"stage2": {"lr_final": 0.5}, "deformation": {"depth": 2}})
    only1 = resolve("fast", TINY, {"stage1": {"lr_final": 0.5}})
    shared = resolve("fast", TINY, {"render": {"samples": 6}})
    assert fingerprint(1, only2, data) == fingerprint(1, st, data)
    assert fingerprint(2, only1, data) == fingerprint(2, st, data)
    assert fingerprint(2, only2, data) != fingerprint(2, st, data)
    assert fingerprint(1, only1, data) != fingerprint(1, st, data)
    assert fingerprint(1, shared, data) != fingerprint(1, st, data) and fingerprint(2, shared, data) != fingerprint(
        2, st, data
    )
    assert fingerprint(2, st, data, origin="a") != fingerprint(2, st, data, origin="b")
    # the model's state shapes: the same settings over other boxes build other grids
    model = _model(tiny_training["tight"], st)[0]
    other = copy.deepcopy(model)
    other.albedo_field.encoding.grids[-1] = torch.nn.Parameter(torch.zeros(1, 2, 3, 3, 3))
    assert fingerprint(1, st, data, model=model) == fingerprint(1, st, data, model=copy.deepcopy(model))
    assert fingerprint(1, st, data, model=model) != fingerprint(1, st, data, model=other)
    # a stage's view resolves to the same settings for everything that stage reads
    view = resolve("fast", stage_view(only2.raw, 1))
    assert stage_view(view.raw, 1) == stage_view(only2.raw, 1) and view.stage1 == only2.stage1


@pytest.fixture(scope="module")
def whole_run(tiny_training, tmp_path_factory):
    """One uninterrupted stage-1 run of the tiny tight subject: its folder, model and losses."""
    st = resolve("fast", TINY)
    model, data = _model(tiny_training["tight"], st)
    out = tmp_path_factory.mktemp("whole")
    result = train_stage(1, model, data, st, out)
    return {"dir": out, "model": model, "losses": result.losses, "data": data, "settings": st}


def test_a_finished_checkpoint_is_written_out_and_a_stale_one_is_not_resumed(
    tiny_training, whole_run, tmp_path, caplog
):
    """A checkpoint at the last step of the same run is finished work (Snakemake marks model.pt incomplete
    after a SIGTERM, and --rerun-incomplete removes it): loaded and written out, not trained again.
    One of other settings is not resumed."""
    import shutil

    st, data = whole_run["settings"], whole_run["data"]
    inputs = tiny_training["tight"]
    shutil.copytree(whole_run["dir"], tmp_path / "run")
    assert load_state(tmp_path / "run" / CHECKPOINT)["step"] == 6
    model_b, _ = _model(inputs, st)
    with caplog.at_level("INFO"):
        again = train_stage(1, model_b, data, st, tmp_path / "run")
    assert "the stage is finished" in caplog.text
    assert again.losses.equals(whole_run["losses"])
    for k, v in whole_run["model"].state_dict().items():
        assert torch.equal(v, model_b.state_dict()[k]), k
    # an interrupted run of other settings is not resumed
    other = resolve("fast", TINY, {"stage1": {"lr": {"nerf": 1e-3}}})
    train_stage(1, _model(inputs, other)[0], data, other, tmp_path / "other", max_steps=4)
    caplog.clear()
    with caplog.at_level("WARNING"):
        res = train_stage(1, _model(inputs, st)[0], data, st, tmp_path / "other")
    assert "other settings, frames or start" in caplog.text and list(res.losses["step"]) == list(range(1, 7))


@pytest.mark.parametrize("damage", ["truncate", "crafted"])
def test_a_bad_checkpoint_is_set_aside_and_the_one_before_resumes(tiny_training, whole_run, tmp_path, caplog, damage):
    """checkpoint_every 2: steps 2 and 4 are kept (checkpoint.prev.pt, checkpoint.pt). With the newest
    damaged, the run resumes from step 2 and ends where an uninterrupted run ends."""
    st, data, whole = whole_run["settings"], whole_run["data"], whole_run["model"]
    inputs = tiny_training["tight"]
    run = tmp_path / "run"
    train_stage(1, _model(inputs, st)[0], data, st, run, max_steps=4)
    assert load_state(run / PREVIOUS_CHECKPOINT)["step"] == 2 and load_state(run / CHECKPOINT)["step"] == 4
    marker = tmp_path / "ran"
    if damage == "truncate":
        (run / CHECKPOINT).write_bytes((run / CHECKPOINT).read_bytes()[:1000])
    else:
        crafted_file(run / CHECKPOINT, marker, optimizer={}, generator=torch.zeros(1), rows=[])
    resumed = _model(inputs, st)[0]
    with caplog.at_level("INFO"):
        res = train_stage(1, resumed, data, st, run)
    assert (
        "set aside as checkpoint.pt.corrupt" in caplog.text and "resuming" in caplog.text and "at step 2" in caplog.text
    )
    assert (run / "checkpoint.pt.corrupt").is_file() and not marker.exists()
    assert list(res.losses["step"]) == list(range(1, 7))
    for k, v in whole.state_dict().items():
        assert torch.equal(v, resumed.state_dict()[k]), f"{k} differs after resuming from the previous checkpoint"
