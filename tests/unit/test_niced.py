"""teleop.run.niced: a restarted recorder or eye view starts niced, its first start not."""

from __future__ import annotations

import os
import subprocess
import sys

from teleop.core.rundir import incarnation_path, summary_path
from teleop.run.niced import command, ran_before

NICE = 7
# Prints the niceness the command runs at (the shim exec's it: the same process).
PRINT_NICE = [sys.executable, "-c", "import os; print(os.getpriority(os.PRIO_PROCESS, 0))"]


def _niceness_of_start(run_dir) -> int:
    argv = command(NICE, run_dir, "recorder", PRINT_NICE)
    return int(subprocess.run(argv, capture_output=True, text=True, check=True).stdout)


def test_a_restart_starts_niced_the_first_start_does_not(tmp_path):
    own = os.getpriority(os.PRIO_PROCESS, 0)
    assert not ran_before(tmp_path, "recorder")
    assert _niceness_of_start(tmp_path) == own  # the first start: nothing runs yet
    incarnation_path(tmp_path, "recorder", 4242).write_text("{}")  # killed while running
    assert ran_before(tmp_path, "recorder") and not ran_before(tmp_path, "eyeview")
    assert _niceness_of_start(tmp_path) == min(max(NICE, own), 19)
    incarnation_path(tmp_path, "recorder", 4242).unlink()
    summary_path(tmp_path, "recorder").write_text("{}")  # closed, then started again
    assert _niceness_of_start(tmp_path) == min(max(NICE, own), 19)
