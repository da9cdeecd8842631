"""The loop timer on the real clock: the properties no machine load can break.

The timing rules themselves (deadlines, skipping, lateness bounds) are exact on the fake
clock (tests/unit/test_clock.py); how late a real loop wakes is a measurement, not a test.
"""

from __future__ import annotations

import numpy as np

from teleop.core.clock import LoopTimer, MonotonicClock

PERIOD_NS = 1_000_000
DURATION_NS = 300_000_000


def test_real_clock_ticks_are_never_early_never_repeated_and_all_accounted_for():
    clock = MonotonicClock()
    timer = LoopTimer(PERIOD_NS, clock)
    end_ns = clock.now_ns() + DURATION_NS
    ticks, wakes_ns = [], []
    while clock.now_ns() < end_ns:
        ticks.append(timer.wait())
        wakes_ns.append(timer.last_wake_ns)
    lateness = np.array(wakes_ns) - np.array([timer.deadline_ns(k) for k in ticks])
    assert np.all(np.diff(np.array(ticks)) >= 1)  # no deadline run twice, none bursted
    assert np.all(lateness >= 0)  # never early
    assert np.all(lateness < PERIOD_NS)  # a late tick is skipped, not run a period late
    assert ticks[-1] == timer.count + timer.skipped  # every deadline run or skipped
    assert timer.summary()["count"] == len(ticks)
