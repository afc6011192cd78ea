"""Which implementation a query takes on a device: the host's or a GPU's.

On the CPU some per-step work has faster host implementations than tensor work: Embree's ray casting,
SciPy's KD-tree and distance transform, the grid encodings' sparse matrices, hierarchy walks that
compact their pairs level by level, small chunks. On any other device the same work runs as tensor
operations, as a GPU needs. Every such choice asks :func:`host_paths`, so one switch,
:func:`tensor_paths`, runs a GPU's code on the CPU: the tests hold a GPU's training step to the CPU's
without a GPU (``tests/training/test_devices.py``), and ``benchmarks/step_ops.py`` counts the
operations a GPU's step dispatches.
"""

from __future__ import annotations

import contextlib
from typing import Iterator

import torch

_TENSOR_PATHS = False


def host_paths(device: torch.device) -> bool:
    """Whether work on ``device`` takes the host's implementations: on the CPU, unless inside
    :func:`tensor_paths`."""
    return device.type == "cpu" and not _TENSOR_PATHS


@contextlib.contextmanager
def tensor_paths() -> Iterator[None]:
    """Inside, CPU tensors take a GPU's implementations (tensor searches and transforms, ``grid_sample``,
    flat leaf tests, a device's chunk sizes). Not thread-safe: one switch for the process."""
    global _TENSOR_PATHS
    saved, _TENSOR_PATHS = _TENSOR_PATHS, True
    try:
        yield
    finally:
        _TENSOR_PATHS = saved
