"""Read pickles that should hold only arrays and plain values, never executing code.

SMPL-X ``.pkl`` files and People Snapshot's ``camera.pkl`` are pickles; an
unrestricted ``pickle.load`` would run whatever the file names. This
unpickler resolves only numpy array reconstruction, scipy sparse matrices and
builtin containers; anything else is refused with the class it asked for.
"""

from __future__ import annotations

import io
import os
import pickle
from pathlib import Path
from typing import Any

from delta import DeltaError

_ALLOWED = {
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"),
    ("numpy._core.numeric", "_frombuffer"),
    ("builtins", "set"),
    ("builtins", "frozenset"),
    ("builtins", "slice"),
    ("builtins", "complex"),
    ("collections", "OrderedDict"),
    ("_codecs", "encode"),
}
_SPARSE = {"csc_matrix", "csr_matrix", "coo_matrix"}


class RestrictedUnpickler(pickle.Unpickler):
    """An unpickler that only builds arrays, sparse matrices and plain containers."""

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _ALLOWED:
            return super().find_class(module, name)
        if module.startswith("scipy.sparse") and name in _SPARSE:
            import scipy.sparse

            return getattr(scipy.sparse, name)
        if module.startswith("chumpy"):
            raise pickle.UnpicklingError(
                "the file holds chumpy objects; convert it to .npz first (the official SMPL-X release has an npz)"
            )
        raise pickle.UnpicklingError(f"refusing to load '{module}.{name}': only arrays and plain values are allowed")


def load_pickle(path: str | os.PathLike) -> Any:
    """Load a pickle of arrays and plain values; errors name the file and the refused class."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DeltaError(f"cannot read {path}: {exc.strerror}") from exc
    try:
        return RestrictedUnpickler(io.BytesIO(data), encoding="latin1").load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError) as exc:
        raise DeltaError(f"{path}: not a safe pickle of arrays ({exc})") from exc
