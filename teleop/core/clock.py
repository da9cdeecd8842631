"""Replaceable monotonic clocks and the one loop timer for periodic work.

Every periodic loop in the project (the 1 kHz plant, the haptic device, the 90 Hz HMD) paces
itself with :class:`LoopTimer` on top of a :class:`Clock`. Services get a
:class:`MonotonicClock`; tests get a :class:`FakeClock`, so deadline arithmetic, overruns
and stall handling are checked deterministically without waiting on the wall clock.

Times are integer nanoseconds of a monotonic clock (never the wall clock): wall time jumps
under NTP and would corrupt both pacing and latency measurements.
"""

from __future__ import annotations

import os
import time
from typing import Protocol, runtime_checkable

from teleop.core.ring import Ring

NS_PER_S = 1_000_000_000  # nanoseconds per second
NS_PER_US = 1_000  # nanoseconds per microsecond

# How long before a deadline MonotonicClock stops trusting one long time.sleep and switches to
# short sleeps, ns. A long sleep wakes late by the kernel's timer slack plus scheduling;
# ending with short sleeps takes most of that away for a few wake-ups per deadline. A
# shorter margin lets more of a long sleep's lateness through; a longer one only adds
# wake-ups.
FINE_SLEEP_MARGIN_NS = 200_000
# Upper bound of one short sleep inside that margin, ns. Each short sleep still overshoots by
# up to the kernel timer slack (50 us by default), so smaller values only add wake-ups.
FINE_SLEEP_QUANTUM_NS = 20_000

# Default number of wake-up lateness samples kept for percentiles (about 65 s at 1 kHz).
DEFAULT_LATENESS_SAMPLES = 65_536
# Default fraction of a period a tick may be late and still be run (beyond it: skipped).
DEFAULT_MAX_LATENESS_FRACTION = 0.5
# Wake-ups in a row that may come too late before LoopTimer.wait gives up skipping and runs the
# latest passed deadline anyway: a loop must not hang on a scheduler that is always late.
MAX_LATE_WAKEUPS = 2


@runtime_checkable
class Clock(Protocol):
    """Monotonic time source that can also wait, so loops can run on fake time in tests."""

    def now_ns(self) -> int:
        """Current monotonic time, ns (arbitrary epoch; only differences mean anything)."""
        ...

    def sleep_until_ns(self, deadline_ns: int) -> None:
        """Block until ``now_ns() >= deadline_ns``; return at once if it already passed."""
        ...


class MonotonicClock:
    """The real clock: ``time.monotonic_ns`` and sleeps to an absolute deadline.

    Sleeping to an absolute deadline (rather than for a fixed duration) keeps a periodic loop
    from drifting by the time its own work takes. The last ``fine_margin_ns`` are covered
    by short sleeps, never by spinning: the machine is shared and a spin would burn a core.

    ``fine_margin_ns`` None: 0 (one sleep) when the thread that builds the clock runs under
    a realtime policy (SCHED_FIFO or SCHED_RR: the kernel applies no timer slack to it),
    else ``FINE_SLEEP_MARGIN_NS``. Under SCHED_FIFO one sleep wakes about as precisely as
    the short sleeps do for a sixth of their CPU cost.
    """

    def __init__(self, fine_margin_ns: int | None = None) -> None:
        if fine_margin_ns is None:
            realtime = os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR)
            fine_margin_ns = 0 if realtime else FINE_SLEEP_MARGIN_NS
        self.fine_margin_ns = fine_margin_ns

    def now_ns(self) -> int:
        """Current ``time.monotonic_ns()``."""
        return time.monotonic_ns()

    def sleep_until_ns(self, deadline_ns: int) -> None:
        """Sleep until ``deadline_ns``: one long sleep, then short ones near the deadline."""
        remaining_ns = deadline_ns - time.monotonic_ns()
        if remaining_ns > self.fine_margin_ns:
            time.sleep((remaining_ns - self.fine_margin_ns) / NS_PER_S)
            remaining_ns = deadline_ns - time.monotonic_ns()
        while remaining_ns > 0:
            time.sleep(min(remaining_ns, FINE_SLEEP_QUANTUM_NS) / NS_PER_S)
            remaining_ns = deadline_ns - time.monotonic_ns()


class FakeClock:
    """Deterministic clock for tests: time moves only through sleeps and :meth:`advance`.

    ``wake_latency_ns`` makes every sleep that has to wait overshoot its deadline by that much,
    to model a scheduler that wakes threads late.
    """

    def __init__(self, start_ns: int = 0, wake_latency_ns: int = 0) -> None:
        if wake_latency_ns < 0:
            raise ValueError(f"wake_latency_ns must be >= 0, got {wake_latency_ns}")
        self._now_ns = start_ns
        self.wake_latency_ns = wake_latency_ns
        self.sleep_calls = 0  # number of sleeps that actually waited

    def now_ns(self) -> int:
        """Current fake time, ns."""
        return self._now_ns

    def sleep_until_ns(self, deadline_ns: int) -> None:
        """Jump to ``deadline_ns`` (plus the configured wake latency) if it lies ahead."""
        if deadline_ns > self._now_ns:
            self._now_ns = deadline_ns + self.wake_latency_ns
            self.sleep_calls += 1

    def advance(self, duration_ns: int) -> None:
        """Let ``duration_ns`` pass, as the work of a loop cycle or a stall would."""
        if duration_ns < 0:
            raise ValueError(f"a monotonic clock cannot go back ({duration_ns} ns)")
        self._now_ns += duration_ns


class LoopTimer:
    """Paces a periodic loop on absolute deadlines ``t0 + k * period`` and keeps statistics.

    Usage::

        timer = LoopTimer(period_ns=1_000_000, clock=MonotonicClock())
        while not stop.is_set():
            tick = timer.wait()
            step(tick)
        log.info("loop: %s", timer.summary())

    :meth:`wait` returns the index ``k`` of the deadline it woke for (1 for the first one,
    ``t0`` being construction time). A cycle whose work ends after the next deadline is an
    *overrun*. A tick that would start more than ``max_lateness_ns`` after its deadline (after
    a stall, or a wake-up that came far too late) is *skipped* instead: the timer moves on to
    the next deadline that can still be met, so the loop never bursts through missed cycles to
    catch up. Every returned tick therefore starts within ``[deadline, deadline +
    max_lateness_ns)`` (unless the scheduler wakes the thread too late ``MAX_LATE_WAKEUPS``
    times in a row: then the latest passed deadline runs, late by less than one period), and
    indices of skipped ticks are never returned.
    """

    def __init__(
        self,
        period_ns: int,
        clock: Clock | None = None,
        max_lateness_ns: int | None = None,
        lateness_samples: int = DEFAULT_LATENESS_SAMPLES,
    ) -> None:
        if period_ns <= 0:
            raise ValueError(f"period_ns must be > 0, got {period_ns}")
        if max_lateness_ns is None:
            max_lateness_ns = int(period_ns * DEFAULT_MAX_LATENESS_FRACTION)
        if not 0 < max_lateness_ns <= period_ns:
            # Above one period two consecutive deadlines could both be "on time" at once,
            # which is exactly the burst the timer exists to prevent.
            raise ValueError(f"max_lateness_ns must be in (0, period_ns], got {max_lateness_ns}")
        if lateness_samples <= 0:
            raise ValueError(f"lateness_samples must be > 0, got {lateness_samples}")
        self.period_ns = period_ns
        self.max_lateness_ns = max_lateness_ns
        self.clock: Clock = clock if clock is not None else MonotonicClock()
        self._lateness_ns = Ring(lateness_samples)
        self.count = 0  # ticks returned by wait()
        self.overruns = 0  # cycles whose work ended after the next deadline
        self.skipped = 0  # deadlines never returned (stalls, very late wake-ups)
        self._lateness_max_ns = 0
        self._tick = 0  # index of the last tick returned (0: the start, t0)
        self.last_wake_ns = 0  # clock time at which the last returned tick started, ns
        self._t0_ns = 0
        self._tick0 = 0
        self.resync()

    def deadline_ns(self, tick: int) -> int:
        """Absolute deadline of tick ``tick`` on the current grid, ns."""
        return self._t0_ns + (tick - self._tick0) * self.period_ns

    def resync(self) -> None:
        """Restart the deadline grid from now; the next tick is due one period later.

        Used when the loop was paused on purpose (a realtime plant held by the operator): the
        pause is then neither an overrun nor skipped ticks. Tick indices keep increasing.
        """
        self._t0_ns = self.clock.now_ns()
        self._tick0 = self._tick

    def wait(self) -> int:
        """Sleep until the next deadline that can still be met and return its tick index."""
        tick = self._tick + 1
        now_ns = self.clock.now_ns()
        if now_ns > self.deadline_ns(tick):
            self.overruns += 1
        late_wakeups = 0
        while True:
            lateness_ns = now_ns - self.deadline_ns(tick)
            if lateness_ns < 0:
                self.clock.sleep_until_ns(self.deadline_ns(tick))
                now_ns = self.clock.now_ns()
                lateness_ns = now_ns - self.deadline_ns(tick)
                if lateness_ns < self.max_lateness_ns:
                    break
                late_wakeups += 1  # descheduled past the tolerance while asleep
            elif lateness_ns < self.max_lateness_ns:
                break
            if late_wakeups >= MAX_LATE_WAKEUPS:
                # Run the latest deadline that has passed: late by less than one period.
                missed = lateness_ns // self.period_ns
                self.skipped += missed
                tick += missed
                lateness_ns -= missed * self.period_ns
                break
            # Too late to run this tick: move on to the first deadline that is not.
            missed = (lateness_ns - self.max_lateness_ns) // self.period_ns + 1
            self.skipped += missed
            tick += missed
        self._record(lateness_ns)
        self._tick = tick
        self.last_wake_ns = now_ns
        return tick

    def _record(self, lateness_ns: int) -> None:
        self._lateness_ns.append(lateness_ns)
        self.count += 1
        self._lateness_max_ns = max(self._lateness_max_ns, lateness_ns)

    def summary(self) -> dict[str, float | int]:
        """Statistics since construction, for the log line a loop prints on exit.

        Lateness is wake-up time minus deadline of returned ticks, in us; p50/p99 cover the
        most recent ``lateness_samples`` ticks, ``lateness_max_us`` all of them.
        """
        p50_ns, p99_ns = self._lateness_ns.percentiles([50.0, 99.0]) or (0.0, 0.0)
        return {
            "period_us": self.period_ns / NS_PER_US,
            "count": self.count,
            "overruns": self.overruns,
            "overrun_fraction": self.overruns / self.count if self.count else 0.0,
            "skipped": self.skipped,
            "lateness_p50_us": float(p50_ns) / NS_PER_US,
            "lateness_p99_us": float(p99_ns) / NS_PER_US,
            "lateness_max_us": self._lateness_max_ns / NS_PER_US,
        }
