"""A service that fails under `teleop run` ends the run with its cause, in one block.

The block must come from watching the programs (a failed state, a restarted pid), not
from the liveliness time-out: each test checks what the block says happened, and that
the previous run's results did not survive the failed one.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from teleop.run.supervise import Stack, StackError

# A run that neither fails nor finishes within this long is a hang (s); only so that a
# broken test ends: the failures below are reported long before.
HANG_S = 300
# How often the test looks for the service it kills (s; not a control loop).
POLL_S = 0.1
EXIT_FAILED = 1


def _teleop(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "teleop.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
    )


def test_a_service_that_crashes_at_start_up_is_named_with_its_exception(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    # A previous run's results: none may survive (or pass for) the failed run's.
    stale = {run_dir / "plant.summary.json": "{}\n", run_dir / "summary.json": "{}\n"}
    for path, text in stale.items():
        path.write_text(text)
    proc = _teleop(
        "run", "path-following", "--mode", "lockstep", "--duration", "2",
        "--run-dir", str(run_dir), "--quiet", "--summary-json", str(run_dir / "summary.json"),
        "--set", 'recorder.rrd_path="/proc/no-such-dir/x.rrd"',
    )  # fmt: skip
    _, err = proc.communicate(timeout=HANG_S)
    assert proc.returncode == EXIT_FAILED, err
    # Which supervisord shows first depends on timing: the exit (code 1), the already
    # restarted process, or (a busy machine, still in the launcher's start-up wait) the
    # program's failed start.
    assert re.search(
        r"service recorder (exited with code 1|died and was restarted|failed to start)", err
    ), err
    assert "FileNotFoundError" in err and "/proc/no-such-dir" in err
    assert f"log:  {run_dir / 'logs' / 'recorder.log'}" in err
    assert "did not come alive" not in err
    assert "Traceback" not in err.split("teleop: the run failed:")[0]
    for path, text in stale.items():
        assert not path.exists() or path.read_text() != text
    assert not (run_dir / "summary.json").exists()


def test_a_service_killed_during_the_run_fails_it_at_once(tmp_path):
    run_dir = tmp_path / "run"
    proc = _teleop(
        "run", "path-following", "--mode", "realtime", "--duration", "60",
        "--run-dir", str(run_dir), "--quiet",
    )  # fmt: skip
    try:
        deadline = time.monotonic() + HANG_S
        pid = 0
        while not pid and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(POLL_S)
            try:
                pid = Stack.attach(run_dir).pid("controller")
            except (StackError, OSError):
                pid = 0
        assert pid, "the controller never started"
        os.kill(pid, signal.SIGKILL)
        _, err = proc.communicate(timeout=HANG_S)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            proc.communicate(timeout=HANG_S)
    assert proc.returncode == EXIT_FAILED, err
    # Killed before or after every program was RUNNING: either way named at once, with
    # how it ended (its own log may be empty: then supervisord's lines about it).
    assert "service controller failed to start" in err or "service controller died" in err
    assert "did not come alive" not in err
    assert Path(run_dir / "logs" / "controller.log").as_posix() in err


def test_up_fails_naming_a_service_that_dies_in_start_up_and_leaves_nothing_running(tmp_path):
    """`teleop up` waits for every service's ready token, not supervisord's one-second
    start check: a recorder that fails while opening (after its imports, well past that
    second on this machine) is named with its exception, and the stack is stopped."""
    run_dir = tmp_path / "up"
    proc = _teleop(
        "up", "--run-dir", str(run_dir), "--set", 'recorder.rrd_path="/proc/no-such-dir/x.rrd"'
    )
    _, err = proc.communicate(timeout=HANG_S)
    try:
        assert proc.returncode == EXIT_FAILED, err
        assert "service recorder" in err and "FileNotFoundError" in err, err
        assert f"log:  {run_dir / 'logs' / 'recorder.log'}" in err
        assert "Traceback" not in err.split("teleop: the run failed:")[0]
        with pytest.raises(StackError):
            Stack.attach(run_dir)  # nothing left running
    finally:
        with contextlib.suppress(StackError):
            Stack.attach(run_dir).stop()  # a failed test leaves no stack behind


def test_up_on_a_port_in_use_is_one_line_naming_the_port(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        endpoint = f"tls/127.0.0.1:{taken.getsockname()[1]}"
        proc = _teleop("up", "--run-dir", str(tmp_path / "up"), "--endpoint", endpoint)
        _, err = proc.communicate(timeout=HANG_S)
    assert proc.returncode == EXIT_FAILED
    assert err.count("\n") == 1 and f"bus endpoint {endpoint} is in use" in err, err
    assert "teleop down" in err
