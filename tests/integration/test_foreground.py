"""A program the launcher runs in its terminal (teleop.run.foreground): started with the
launcher's standard streams and its own log, its command line where an observer finds
it, its early end told in one line, and stopped (SIGTERM, then SIGKILL) with the run."""

from __future__ import annotations

import json
import sys
import time

import pytest

from teleop.core.rundir import FOREGROUND_DIR, LOG_DIR
from teleop.run.foreground import Foreground, ForegroundExited
from teleop.run.supervise import Program


def _program(code: str) -> Program:
    return Program(name="operator", command=[sys.executable, "-c", code])


def test_a_program_that_ends_early_is_told_with_its_code_and_log(tmp_path):
    program = _program("import sys; print('leaving', file=sys.stderr); sys.exit(3)")
    with Foreground(program, tmp_path) as foreground:
        assert json.loads((tmp_path / FOREGROUND_DIR / "operator.json").read_text()) == (
            program.command
        )
        deadline = time.monotonic() + 10
        while foreground.process is not None and foreground.process.poll() is None:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        with pytest.raises(ForegroundExited, match=r"operator ended \(exit code 3\)") as exc:
            foreground.check()
        assert str(tmp_path / LOG_DIR / "operator.log") in str(exc.value)
    assert "leaving" in (tmp_path / LOG_DIR / "operator.log").read_text()


def test_the_run_stops_it_with_sigterm_and_waits_for_its_clean_up(tmp_path):
    code = (
        "import signal, sys, time\n"
        "signal.signal(signal.SIGTERM, lambda *a: (print('cleaned up', file=sys.stderr), "
        "sys.exit(0)))\n"
        "print('up', file=sys.stderr, flush=True)\n"
        "time.sleep(60)\n"
    )
    log = tmp_path / LOG_DIR / "operator.log"
    with Foreground(_program(code), tmp_path) as foreground:
        deadline = time.monotonic() + 10
        while "up" not in (log.read_text() if log.exists() else ""):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        foreground.check()  # still running: nothing to say
    assert foreground.stop() == 0
    assert "cleaned up" in log.read_text()
