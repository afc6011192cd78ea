"""The suite's shared caches under ``resources/``: Anny's build, the converted MediaPipe models, the
perceptual weights.

Each is built under a file lock (:func:`exclusive`): one process builds, the others wait and read it.
On a fresh clone the whole suite starts their builds in the background (``python -m tests.caches
NAME``, from ``conftest.pytest_configure``) so that the two workers keep running tests meanwhile instead
of one of them building Anny and then converting MediaPipe while the other waits for both. This
module takes its lock before it imports anything heavy, so the background build holds it first.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ANNY_CACHE = Path(os.environ.get("DELTA_ANNY_CACHE", REPO / "resources" / "anny_cache"))
MODELS_DIR = REPO / "resources" / "models"
MEDIAPIPE_DIR = MODELS_DIR / "mediapipe"
STLPIPS_DIR = MODELS_DIR / "stlpips"


@contextlib.contextmanager
def exclusive(name: str):
    """Hold the lock ``resources/.{name}.lock``: one worker builds a shared cache, the others wait and read it."""
    path = REPO / "resources" / f".{name}.lock"
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def anny(facial_actions: bool = False):
    """Anny itself (float64, dense LBS), with its 52 facial actions when asked (the two builds share
    most of the cache: the second costs seconds)."""
    from delta.body.anny_convert import build_anny

    with exclusive("anny"):
        return build_anny(ANNY_CACHE, facial_actions=facial_actions)


def mediapipe() -> Path:
    """MediaPipe's models in ONNX, converted once (the first run installs the converter); the pose model's path."""
    from delta.preprocess.mediapipe_convert import MODELS, convert

    with exclusive("mediapipe"):
        if not all((MEDIAPIPE_DIR / f"{m}.onnx").is_file() for m in MODELS):
            convert(MEDIAPIPE_DIR, REPO / "resources" / "envs" / "mediapipe-convert")
    return MEDIAPIPE_DIR / "pose_landmark_full.onnx"


def stlpips() -> Path:
    """The folder of the shift-tolerant VGG16/AlexNet weights, fetched once from the registry when missing."""
    from delta.perceptual import weights as W

    with exclusive("stlpips"):
        return Path(W.ensure_weights(STLPIPS_DIR)["vgg"]).parent


def missing() -> list[str]:
    """The caches not built yet, by the names ``python -m tests.caches`` takes (a cheap look at their files;
    a partly built cache is finished by whoever takes its lock)."""
    out = []
    if not any(ANNY_CACHE.rglob("*.safetensors")):
        out.append("anny")
    if not (MEDIAPIPE_DIR / "manifest.json").is_file():
        out.append("mediapipe")
    if not (STLPIPS_DIR / "weights.json").is_file():
        out.append("stlpips")
    return out


def build(name: str) -> None:
    """Build one cache (both of Anny's builds under one hold of its lock)."""
    if name == "anny":
        with exclusive("anny"):
            from delta.body.anny_convert import build_anny

            build_anny(ANNY_CACHE)
            build_anny(ANNY_CACHE, facial_actions=True)
    elif name == "mediapipe":
        mediapipe()
    elif name == "stlpips":
        stlpips()
    else:
        raise SystemExit(f"unknown cache {name!r}: anny, mediapipe or stlpips")


if __name__ == "__main__":
    build(sys.argv[1])
