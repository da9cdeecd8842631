"""A short realtime run as an ordinary user (``nobody``; tests/e2e/users.py).

Without root's capabilities the run must still complete and say in its summary's
``machine`` section what it was refused, and the eye view's frames must still arrive
over shared memory (a pool sized within the locked-memory limit). The lockstep grasp as
``nobody`` is half of the determinism pair (tests/e2e/test_grasp.py): it must end in
the same state as root's.
"""

from __future__ import annotations

import json

from teleop.cli import EXIT_REALTIME_LOST
from tests.e2e.users import USER, UserEnv

# Exit code of `teleop run` when the run completed: 0, or 3 when it lost real time (a
# verdict on the machine's load, judged apart below).
EXIT_OK = 0


def _run_as_user(user_env: UserEnv, name: str, args: list[str]) -> tuple[int, dict]:
    run_dir = user_env.home / name
    summary = user_env.home / f"{name}.json"
    result = user_env.run(
        ["-m", "teleop.cli", "run", *args, "--quiet", "--run-dir", str(run_dir),
         "--summary-json", str(summary)]
    )  # fmt: skip
    assert result.returncode in (EXIT_OK, EXIT_REALTIME_LOST), result.stderr[-3000:]
    return result.returncode, json.loads(summary.read_text())


def test_a_realtime_run_as_an_ordinary_user_reports_what_it_was_refused(user_env):
    code, summary = _run_as_user(
        user_env, "realtime", ["path-following", "--mode", "realtime", "--duration", "4"]
    )
    assert (code == EXIT_REALTIME_LOST) == (summary["realtime_verdict"] == "lost")
    machine = summary["machine"]
    assert machine["user"] == USER and machine["uid"] != 0
    # No CAP_SYS_NICE: every loop service that asked for SCHED_FIFO was refused.
    assert machine["sched_fifo"]["granted"] == {}
    assert set(machine["sched_fifo"]["refused"]) >= {"plant", "controller"}
    # The eye view's pool fits the default locked-memory limit, and its frames arrive
    # through it (before, the pool was refused and the eye view never came alive).
    pool = machine["shm"]
    if pool["memlock_bound"] and pool["memlock_limit_bytes"] is not None:
        assert pool["pool_bytes"] < pool["memlock_limit_bytes"]
    eye = summary["eye_view"]
    assert eye["frames_received"] > 0
    assert eye["frames_received_shm"] == eye["frames_received"]
