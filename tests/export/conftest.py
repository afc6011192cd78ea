"""A tiny trained avatar (stage 1, a few steps on the tiny orthographic capture) and its export."""

import pytest

from delta.export.run import export_avatar
from delta.export.settings import ExportSettings
from delta.training.run import run_stage

TINY = {
    "resolution": 48,
    "exterior": "yes",
    "render": {"samples": 8},
    "stage1": {"iterations": 4, "rays": 128, "checkpoint_every": 100, "preview_every": 0, "log_every": 1},
}
SETTINGS = ExportSettings(grid=64, threshold=500.0, smooth=2, decimate=4000, min_component_faces=10,
                          turntable_frames=2, sidebyside=1)  # fmt: skip


@pytest.fixture(scope="session")
def tiny_model(tiny_training, tmp_path_factory):
    """{"model", "record", "body", "other_record"}: a stage-1 model.pt of the loose subject."""
    inputs = tiny_training["loose"]
    out = tmp_path_factory.mktemp("export_model")
    run_stage(1, inputs["record"], inputs["body"], inputs["init"], str(out), "fast", [TINY])
    return {"model": str(out / "model.pt"), "record": inputs["record"], "body": inputs["body"],
            "other_record": tiny_training["tight"]["record"]}  # fmt: skip


@pytest.fixture(scope="session")
def tiny_export(tiny_model, tmp_path_factory):
    out = tmp_path_factory.mktemp("export")
    summary = export_avatar(tiny_model["model"], tiny_model["record"], tiny_model["body"], out, SETTINGS)
    return out, summary
