"""A progress line for long jobs: steps done, time elapsed and an estimate of the time left.

Printed to stderr, which Snakemake writes to the rule's log; ``tail -f logs/train/...`` follows a job.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Callable, Iterable, Iterator, TypeVar

T = TypeVar("T")


def duration(seconds: float) -> str:
    """``'1h02m'``, ``'3m05s'``, ``'12s'``; ``'?'`` when unknown."""
    if not math.isfinite(seconds) or seconds < 0:
        return "?"
    s = int(round(seconds))
    if s >= 3600:
        return f"{s // 3600}h{s % 3600 // 60:02d}m"
    if s >= 60:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s}s"


class Progress:
    """Steps of a job of ``total`` steps, ``done`` of them before this process started (a resumed run):
    the estimate extrapolates this process's own rate."""

    def __init__(self, what: str, total: int, done: int = 0, clock: Callable[[], float] = time.monotonic):
        self.what, self.total, self.start, self.clock = what, int(total), int(done), clock
        self.t0 = clock()
        self.done = self.start

    def line(self, done: int, extra: str = "") -> str:
        elapsed = self.clock() - self.t0
        steps = done - self.start
        left = (self.total - done) * elapsed / steps if steps > 0 and elapsed > 0 else math.nan
        pct = 100 * done / self.total if self.total else 100.0
        text = f"{self.what} {done}/{self.total} ({pct:.0f}%) elapsed {duration(elapsed)} left ~{duration(left)}"
        return f"{text} {extra}".rstrip()

    def report(self, done: int, extra: str = "") -> None:
        self.done = done
        print(self.line(done, extra), file=sys.stderr, flush=True)

    def tick(self, extra: str = "") -> None:
        """One more step done."""
        self.report(self.done + 1, extra)

    def counted(self, items: Iterable[T], extra: str = "") -> Iterator[T]:
        """``items``, a step reported after each."""
        for item in items:
            yield item
            self.tick(extra)
