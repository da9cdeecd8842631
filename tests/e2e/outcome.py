"""How an e2e test judges a realtime run's exit code.

A realtime run on a loaded machine may lose real time and say so (exit code 3 and
``realtime_verdict: "lost"`` with its problems listed): that is the run telling the
truth, not a failure of what the test checks. Any other non-zero code is a failure.
"""

from __future__ import annotations

from typing import Any

from teleop.cli import EXIT_REALTIME_LOST


def assert_ran(code: int, summary: dict[str, Any] | None, stderr: str = "") -> None:
    """``code`` is 0, or 3 with a summary whose verdict is "lost" and says why."""
    if code == EXIT_REALTIME_LOST and summary is not None:
        assert summary.get("realtime_verdict") == "lost", stderr[-3000:]
        assert summary.get("realtime_problems"), stderr[-3000:]
        return
    assert code == 0, stderr[-3000:]
