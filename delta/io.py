"""File input and output: atomic writes (nothing half-written survives an interruption) and a
loader for shared model files that cannot run code."""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
import zipfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from delta import DeltaError


def require_files(**files: str | os.PathLike) -> None:
    """Raise one DeltaError naming the first missing file: ``require_files(model=path, record=path)`` says
    "PATH: no such model file" (underscores in a name read as spaces)."""
    for what, path in files.items():
        if not Path(path).is_file():
            raise DeltaError(f"{path}: no such {what.replace('_', ' ')} file")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; move it into place only on success.

    The temporary file keeps the final suffix so that libraries which infer a
    format from the extension (numpy, OpenCV, trimesh) write the right one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".part{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp makes 0600; give the file the usual permissions
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def save_npz(path: str | os.PathLike, **arrays: Any) -> None:
    """Write arrays to ``path`` atomically as an npz without pickled objects.

    Byte-identical for identical arrays: zip entries carry a fixed timestamp
    (``np.savez`` stamps the current time).
    """
    with atomic_path(path) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
            for name, value in arrays.items():
                info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                with zf.open(info, "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, np.asarray(value), allow_pickle=False)


def save_json(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented JSON atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=True) + "\n")


def load_json(path: str | os.PathLike) -> Any:
    """A JSON file's content, or an error naming the file and what is wrong with it."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise DeltaError(f"{path}: cannot read ({e})") from None


def load_state(path: str | os.PathLike, map_location: Any = "cpu") -> dict:
    """A ``model.pt`` or ``checkpoint.pt``: tensors and plain values only, never code.

    Avatars and checkpoints are files people share. ``torch.load(weights_only=True)`` builds
    tensors, numbers, strings and containers and refuses every other object, so a crafted
    pickle that would call ``os.system`` is rejected before anything in it runs. A missing,
    truncated or corrupt file is a :class:`DeltaError` naming it.
    """
    import pickle

    import torch

    path = Path(path)
    if not path.is_file():
        raise DeltaError(f"{path}: file not found")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        found = re.search(r"GLOBAL (\S+)", str(exc))
        if found is None:
            raise DeltaError(
                f"{path}: not a model or checkpoint file written by delta (no torch archive in it)"
            ) from None
        raise DeltaError(f"{path}: refused: it holds objects other than tensors and plain values "
                         f"({found.group(1)}), which could run code when loaded") from None  # fmt: skip
    except (RuntimeError, EOFError, OSError, ValueError, zipfile.BadZipFile):
        raise DeltaError(f"{path}: cannot be read: truncated or corrupt (delete it; the step that writes it "
                         "will write it again)") from None  # fmt: skip
    if not isinstance(state, dict):
        raise DeltaError(f"{path}: holds a {type(state).__name__}, not the dictionary a model or checkpoint file holds")
    return state
