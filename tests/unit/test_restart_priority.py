"""teleop.run.restart_priority: a restart starts at its own priority, a first start not."""

from __future__ import annotations

import os
import subprocess
import sys

from teleop.core.rundir import incarnation_path, summary_path
from teleop.run.restart_priority import command, ran_before

NICE, FIFO = 7, 1
# Prints the niceness and the policy the command runs at (exec'd: the same process).
PRINT_PRIORITY = [
    sys.executable,
    "-c",
    "import os; print(os.getpriority(os.PRIO_PROCESS, 0), os.sched_getscheduler(0))",
]


def _start(run_dir, **priority) -> tuple[int, int]:
    argv = command(run_dir, "recorder", PRINT_PRIORITY, **priority)
    out = subprocess.run(argv, capture_output=True, text=True, check=True).stdout.split()
    return int(out[0]), int(out[1])


def test_a_restart_starts_niced_the_first_start_does_not(tmp_path):
    own = os.getpriority(os.PRIO_PROCESS, 0)
    assert not ran_before(tmp_path, "recorder")
    assert _start(tmp_path, nice=NICE)[0] == own  # the first start: nothing runs yet
    incarnation_path(tmp_path, "recorder", 4242).write_text("{}")  # killed while running
    assert ran_before(tmp_path, "recorder") and not ran_before(tmp_path, "eyeview")
    assert _start(tmp_path, nice=NICE)[0] == min(max(NICE, own), 19)
    incarnation_path(tmp_path, "recorder", 4242).unlink()
    summary_path(tmp_path, "recorder").write_text("{}")  # closed, then started again
    assert _start(tmp_path, nice=NICE)[0] == min(max(NICE, own), 19)


def test_a_control_path_restart_starts_under_sched_fifo_where_allowed(tmp_path):
    assert _start(tmp_path, fifo=FIFO)[1] == os.SCHED_OTHER  # the first start
    summary_path(tmp_path, "recorder").write_text("{}")
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(FIFO))
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        allowed = True
    except OSError:  # no CAP_SYS_NICE: refused, said, and started normally anyway
        allowed = False
    policy = _start(tmp_path, fifo=FIFO)[1]
    assert policy == (os.SCHED_FIFO if allowed else os.SCHED_OTHER)
