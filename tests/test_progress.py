"""The progress line of long jobs: the estimate extrapolates this process's own rate."""

import math

from delta.progress import Progress, duration


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def test_durations_read_as_a_person_writes_them():
    assert [duration(s) for s in (0, 12.4, 65, 3599, 3725)] == ["0s", "12s", "1m05s", "59m59s", "1h02m"]
    assert duration(math.nan) == duration(math.inf) == duration(-1) == "?"


def test_estimate_is_the_rest_at_the_rate_so_far():
    clock = Clock()
    p = Progress("stage 1", 100, clock=clock)
    assert p.line(0) == "stage 1 0/100 (0%) elapsed 0s left ~?"
    clock.now += 5.0
    assert p.line(10, "loss 0.1") == "stage 1 10/100 (10%) elapsed 5s left ~45s loss 0.1"  # 90 steps at 2 steps/s


def test_a_resumed_job_counts_only_its_own_steps():
    clock = Clock()
    p = Progress("stage 2", 1000, done=600, clock=clock)  # 600 steps came from the checkpoint, not this process
    clock.now += 40.0
    assert p.line(700) == "stage 2 700/1000 (70%) elapsed 40s left ~2m00s"  # 300 steps at 2.5 steps/s


def test_counted_items_report_one_step_each(capsys):
    clock = Clock()
    p = Progress("export", 3, clock=clock)
    assert list(p.counted(iter("ab"), "turntable")) == ["a", "b"]
    lines = capsys.readouterr().err.splitlines()
    assert [line.split(" (")[0] for line in lines] == ["export 1/3", "export 2/3"] and p.done == 2
    assert lines[-1].endswith("turntable")
