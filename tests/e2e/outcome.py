"""How an e2e test judges a realtime run: its exit code, and whether this machine can
keep the realtime stack's time at all.

A realtime run on a loaded machine may lose real time and say so (exit code 3 and
``realtime_verdict: "lost"`` with its problems listed): that is the run telling the
truth, not a failure of what the test checks. Any other non-zero code is a failure.
"""

from __future__ import annotations

import os
import threading
from typing import Any

import pytest

from teleop.bus import graph
from teleop.bus.service import fifo_scheduling
from teleop.cli import EXIT_REALTIME_LOST
from teleop.core.service_summaries import record_problems
from teleop.run.verdict import GRANTED

# The whole realtime stack takes about 1.2 cores of CPU at the default bus rate
# (docs/realtime.md, "The rate sweep"). Normally scheduled, its loops share the cores with
# everything else: on the 2-core machine an ordinary user's grasp succeeds, but a late
# command now and then makes its verdict degraded, which the tests below judge. With at
# least this many CPUs the loops have cores to spare; not measured here (the project's
# machine has 2).
CPUS_WITHOUT_FIFO = 4


def sched_fifo_refusal() -> str | None:
    """Why this process may not run threads under SCHED_FIFO (None: it may), asked of
    the kernel from a throwaway thread."""
    outcome: list[str] = []

    def probe() -> None:
        with fifo_scheduling(1) as result:
            outcome.append(result)

    thread = threading.Thread(target=probe)
    thread.start()
    thread.join()
    return None if outcome[0].startswith(GRANTED) else outcome[0]


def _realtime_stack_skip_reason() -> str | None:
    refusal = sched_fifo_refusal()
    cpus = len(os.sched_getaffinity(0))
    if refusal is None or cpus >= CPUS_WITHOUT_FIFO:
        return None
    return (
        f"the realtime stack's clean timing needs SCHED_FIFO on {cpus} CPUs ({refusal}); "
        "run as root or with CAP_SYS_NICE (docs/running.md, Privileges)"
    )


_SKIP_REASON = _realtime_stack_skip_reason()
# For tests that need the full realtime stack to keep its timing (their outcome, not only
# their exit code, depends on it); the short realtime run of test_unprivileged.py runs
# either way.
needs_realtime_stack = pytest.mark.skipif(_SKIP_REASON is not None, reason=_SKIP_REASON or "")


def assert_ran(code: int, summary: dict[str, Any] | None, stderr: str = "") -> None:
    """``code`` is 0, or 3 with a summary whose verdict is "lost" and says why."""
    if code == EXIT_REALTIME_LOST and summary is not None:
        assert summary.get("realtime_verdict") == "lost", stderr[-3000:]
        assert summary.get("realtime_problems"), stderr[-3000:]
        return
    assert code == 0, stderr[-3000:]


def services_record_problems(summary: dict[str, Any]) -> list[str]:
    """What of each service's summary under a run summary's ``services`` its record
    (teleop.core.service_summaries) does not read as its type (empty: all of it)."""
    services = summary.get("services") or {}
    return [p for name, s in services.items() for p in record_problems(graph.role_of(name), s)]
