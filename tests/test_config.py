"""Configuration validation: defaults, unknown keys, wrong types, missing files."""

from pathlib import Path

import pytest

from delta import DeltaError
from delta.config import load_config, validate_config

REPO = Path(__file__).resolve().parents[1]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"


def test_shipped_configs_are_valid():
    main, tiny = REPO / "config" / "config.yaml", REPO / ".test" / "config" / "config.yaml"
    for paths in ([main], [main, tiny]):  # the tiny one is merged over the main one
        cfg = load_config(paths, SCHEMA)
        assert cfg["body_model"]["name"] == "anny"


def test_defaults_are_filled():
    cfg = validate_config({}, SCHEMA)
    assert cfg["body_model"]["anny"]["num_shape"] == 32
    assert cfg["body_model"]["upsample_level"] == 1
    assert cfg["preset"] == "fast"


def test_unknown_key_is_named():
    with pytest.raises(DeltaError) as err:
        validate_config({"body_model": {"anny": {"num_shapes": 3}}}, SCHEMA)
    msg = str(err.value)
    assert "'body_model.anny'" in msg and "num_shapes" in msg and "num_shape" in msg


def test_wrong_type_is_named():
    with pytest.raises(DeltaError, match=r"'body_model.upsample_level': 'two' is not of type 'integer'"):
        validate_config({"body_model": {"upsample_level": "two"}}, SCHEMA)


def test_all_problems_reported_at_once():
    with pytest.raises(DeltaError, match=r"2 problem\(s\)") as err:
        validate_config({"preset": "fastest", "body_model": {"name": "smpl"}}, SCHEMA)
    assert "'preset'" in str(err.value) and "'body_model.name'" in str(err.value)


def test_missing_smplx_file_says_where(tmp_path):
    with pytest.raises(DeltaError) as err:
        validate_config({"body_model": {"name": "smplx", "smplx_path": "x/SMPLX_NEUTRAL.npz"}}, SCHEMA, tmp_path)
    msg = str(err.value)
    assert "body_model.smplx_path" in msg and "x/SMPLX_NEUTRAL.npz" in msg and "name: anny" in msg


def test_smplx_file_present_passes(tmp_path):
    (tmp_path / "m.npz").write_bytes(b"")
    cfg = validate_config({"body_model": {"name": "smplx", "smplx_path": "m.npz"}}, SCHEMA, tmp_path)
    assert cfg["body_model"]["name"] == "smplx"


def test_dataset_needs_subjects():
    with pytest.raises(DeltaError, match="(?s)'datasets.synthetic'.*'subjects' is a required property"):
        validate_config({"datasets": {"synthetic": {}}}, SCHEMA)


def test_load_config_names_the_file(tmp_path):
    path = tmp_path / "config" / "bad.yaml"
    path.parent.mkdir()
    path.write_text("preset: [1, 2\n")
    with pytest.raises(DeltaError, match="bad.yaml: cannot read configuration"):
        load_config(path, SCHEMA)
    path.write_text("preset: slow\n")
    with pytest.raises(DeltaError, match="(?s)bad.yaml.*'preset'"):
        load_config(path, SCHEMA)
