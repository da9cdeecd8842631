"""LoopTimer deadline arithmetic, overruns and stall handling on a FakeClock; one real-clock run
that checks only properties which hold however noisy the machine is."""

import numpy as np
import pytest

from teleop.core.clock import (
    MAX_LATE_WAKEUPS,
    Clock,
    FakeClock,
    LoopTimer,
    MonotonicClock,
)

PERIOD_NS = 1_000_000  # 1 kHz
START_NS = 5_000_000_000  # arbitrary non-zero epoch: nothing may assume the clock starts at 0


def test_clocks_satisfy_protocol():
    assert isinstance(MonotonicClock(), Clock)
    assert isinstance(FakeClock(), Clock)


def test_fake_clock_moves_only_on_sleep_and_advance():
    clock = FakeClock(start_ns=START_NS)
    assert clock.now_ns() == START_NS
    clock.sleep_until_ns(START_NS - 1)  # past deadline: no wait, no time passes
    assert clock.now_ns() == START_NS
    assert clock.sleep_calls == 0
    clock.sleep_until_ns(START_NS + 10)
    clock.advance(5)
    assert clock.now_ns() == START_NS + 15
    with pytest.raises(ValueError):
        clock.advance(-1)


def test_deadlines_are_absolute_and_do_not_drift_with_work():
    clock = FakeClock(start_ns=START_NS)
    timer = LoopTimer(PERIOD_NS, clock)
    for expected_tick in range(1, 6):
        assert timer.wait() == expected_tick
        assert clock.now_ns() == START_NS + expected_tick * PERIOD_NS
        clock.advance(PERIOD_NS * 3 // 10)  # work shorter than a period
    assert timer.overruns == 0
    assert timer.skipped == 0
    assert timer.deadline_ns(7) == START_NS + 7 * PERIOD_NS


def test_overrun_within_tolerance_runs_late_then_returns_to_grid():
    clock = FakeClock(start_ns=START_NS)
    timer = LoopTimer(PERIOD_NS, clock)
    assert timer.wait() == 1
    clock.advance(PERIOD_NS + PERIOD_NS // 5)  # work ends 0.2 period after deadline 2
    assert timer.wait() == 2  # late but within max_lateness: run at once, no sleep
    assert clock.now_ns() == START_NS + 2 * PERIOD_NS + PERIOD_NS // 5
    assert timer.wait() == 3  # back on the grid
    assert clock.now_ns() == START_NS + 3 * PERIOD_NS
    assert (timer.overruns, timer.skipped) == (1, 0)


def test_stall_skips_missed_deadlines_without_bursting():
    clock = FakeClock(start_ns=START_NS)
    timer = LoopTimer(PERIOD_NS, clock)
    assert timer.wait() == 1
    clock.advance(int(4.7 * PERIOD_NS))  # stall: now = t0 + 5.7 periods
    wake_times_ns = []
    ticks = []
    for _ in range(3):
        ticks.append(timer.wait())
        wake_times_ns.append(clock.now_ns())
    # Deadlines 2..5 passed more than the default tolerance (0.5 period) ago: skipped; the
    # timer sleeps to deadline 6, the next one in the future.
    assert ticks == [6, 7, 8]
    assert wake_times_ns == [START_NS + k * PERIOD_NS for k in ticks]
    assert timer.skipped == 4
    assert timer.overruns == 1
    assert np.all(np.diff(wake_times_ns) == PERIOD_NS)  # no burst after the stall


def test_stall_resumes_at_once_when_latest_deadline_is_within_tolerance():
    clock = FakeClock(start_ns=START_NS)
    timer = LoopTimer(PERIOD_NS, clock)
    timer.wait()
    clock.advance(int(3.2 * PERIOD_NS))  # now = t0 + 4.2 periods: tick 4 is 0.2 late
    assert timer.wait() == 4
    assert clock.now_ns() == START_NS + int(4.2 * PERIOD_NS)
    assert timer.skipped == 2  # ticks 2 and 3
    assert timer.wait() == 5


def test_late_wakeups_are_skipped_then_accepted_so_wait_never_hangs():
    # A scheduler that always wakes the thread 0.8 period late.
    clock = FakeClock(start_ns=START_NS, wake_latency_ns=PERIOD_NS * 8 // 10)
    timer = LoopTimer(PERIOD_NS, clock)
    tick = timer.wait()
    assert timer.skipped == MAX_LATE_WAKEUPS - 1
    assert tick == 1 + timer.skipped
    assert clock.now_ns() - timer.deadline_ns(tick) < PERIOD_NS


def test_resync_restarts_grid_and_keeps_tick_index():
    clock = FakeClock(start_ns=START_NS)
    timer = LoopTimer(PERIOD_NS, clock)
    timer.wait()
    timer.wait()
    clock.advance(50 * PERIOD_NS + 123)  # deliberate pause
    timer.resync()
    paused_at_ns = clock.now_ns()
    assert timer.wait() == 3
    assert clock.now_ns() == paused_at_ns + PERIOD_NS
    assert (timer.overruns, timer.skipped) == (0, 0)


def test_summary_fields():
    latency_ns = 30_000
    clock = FakeClock(start_ns=START_NS, wake_latency_ns=latency_ns)
    timer = LoopTimer(PERIOD_NS, clock, lateness_samples=8)
    empty = timer.summary()
    assert empty["count"] == 0 and empty["overrun_fraction"] == 0.0
    for _ in range(19):
        timer.wait()
    clock.advance(PERIOD_NS)  # one overrun: the 20th tick runs late by its wake latency
    timer.wait()
    summary = timer.summary()
    assert summary["count"] == 20
    assert summary["overruns"] == 1
    assert summary["overrun_fraction"] == pytest.approx(1 / 20)
    assert summary["skipped"] == 0
    assert summary["period_us"] == pytest.approx(1000.0)
    assert summary["lateness_p50_us"] == pytest.approx(30.0)
    assert summary["lateness_p99_us"] == pytest.approx(30.0, abs=1.0)
    assert summary["lateness_max_us"] == pytest.approx(30.0)


def test_invalid_arguments():
    with pytest.raises(ValueError):
        LoopTimer(0, FakeClock())
    with pytest.raises(ValueError):
        LoopTimer(PERIOD_NS, FakeClock(), max_lateness_ns=PERIOD_NS + 1)
    with pytest.raises(ValueError):
        FakeClock(wake_latency_ns=-1)
