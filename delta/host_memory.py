"""How the host's C allocator hands memory back: kept for reuse, where glibc would return it every step.

glibc serves an allocation of more than its mmap threshold (at most 32 MB; dynamic below that) with fresh
pages from the kernel and unmaps them again when freed, and it trims the heap's free top above 128 kB. A
training step allocates and frees tensors of tens to hundreds of megabytes (a batch's samples × features,
a dense grid's gradient), so every step pays for the same pages again: a page fault and the kernel's
zeroing per 4 kB, on every large tensor, every step. With both thresholds at their largest, freed memory
stays in the process and the next step reuses it. Stage-1 steps of `fast` at 512² on two cores
(``benchmarks/host_allocator.py``, docs/tradeoff.md "Where a training step's time goes"): loose 0.78–0.81 s
against 0.87 s, the long-haired talker 1.77–1.79 s against 2.37–2.45 s, at a peak RSS a fifth to two fifths
higher (loose 1.74–1.78 against 1.45–1.47 GB, the talker 2.32–2.45 against 1.73 GB).

``DELTA_HOST_MALLOC=system`` leaves glibc's own settings (a machine short of memory); other C libraries
(macOS, musl) are left as they are.
"""

from __future__ import annotations

import ctypes
import logging
import os
import platform

from delta import DeltaError

log = logging.getLogger(__name__)

#: glibc's ``mallopt`` parameters (malloc.h)
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
#: the largest value ``mallopt`` takes (an ``int``): in effect, never unmap and never trim
NEVER = 2**31 - 1
#: the environment variable that leaves the C library's settings as they are
SWITCH = "DELTA_HOST_MALLOC"

_held: bool | None = None


def hold_freed_memory() -> bool:
    """Keep freed memory in the process for reuse (glibc only; once a process; ``DELTA_HOST_MALLOC=system``:
    not at all). Returns whether the allocator holds it now."""
    global _held
    if _held is not None:
        return _held
    _held = False
    choice = os.environ.get(SWITCH, "hold")
    if choice not in ("hold", "system"):
        raise DeltaError(f"{SWITCH}={choice!r}: expected 'hold' (the default) or 'system'")
    if choice == "system" or platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return _held
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # pragma: no cover - a glibc without mallopt
        return _held
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _held = bool(mallopt(M_MMAP_THRESHOLD, NEVER)) and bool(mallopt(M_TRIM_THRESHOLD, NEVER))
    if not _held:  # pragma: no cover - glibc refused a value
        log.warning("the C library refused to keep freed memory (mallopt); each step pays for its pages again")
    return _held
