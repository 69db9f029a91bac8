"""The time-left estimate of a pipeline run: nothing until the rate since the first scan means
something, then the scans left at that rate."""

from __future__ import annotations

import pytest

from workers.progress import TimeLeft


class Clock:
    """A clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_no_estimate_until_enough_scans_and_seconds_after_the_first():
    clock = Clock()
    left = TimeLeft(20, min_scans=3, min_seconds=5.0, clock=clock)
    assert left.update(0) is None
    clock.now = 30.0  # start-up: the first scan comes through late
    assert left.update(1) is None
    clock.now = 31.0
    assert left.update(4) is None  # enough scans, too few seconds
    clock.now = 40.0
    assert left.update(11) == pytest.approx(9 * 10.0 / 10)  # 10 scans in 10 s, 9 left


def test_the_start_up_does_not_count_in_the_rate():
    """A run whose first scan took 30 s of start-up and then ran at 2 scans/s: the estimate is
    what remains at 2 scans/s, not at the rate the start-up drags down."""
    clock = Clock()
    left = TimeLeft(100, clock=clock)
    clock.now = 30.0
    left.update(1)
    clock.now = 40.0
    estimate = left.update(21)
    assert estimate == pytest.approx(79 / 2.0)
    assert 3 * estimate < 79 / (21 / 40.0)  # what counting from the start would have said


def test_a_finished_run_has_nothing_left():
    clock = Clock()
    left = TimeLeft(2, clock=clock)
    assert left.update(1) is None
    clock.now = 0.5
    assert left.update(2) == 0.0
