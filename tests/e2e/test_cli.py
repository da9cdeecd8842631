"""The teleop command as a user runs it: a real subprocess, a real summary file."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path

from teleop.bus.messages import PLANT_STATE, DropCounter
from teleop.bus.session import close_session, open_session, subscribe
from teleop.bus.topics import Topics
from teleop.core.config import load_config
from teleop.run.stack import free_loopback_port

SUMMARY_KEYS = {
    "scenario",
    "duration_s",
    "path_error_rms_m",
    "path_error_max_m",
    "settle_s",
    "min_manipulability",
    "compensation",
    "steps",
    "wall_s",
    "final_state_sha256",
}


# teleop up: services' start-up (imports, models, sessions) on a loaded 2-core machine.
UP_TIMEOUT_S = 90.0


def teleop(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "teleop.cli", *args],
        capture_output=True,
        text=True,
        timeout=120,
        stdin=subprocess.DEVNULL,
    )


def test_inprocess_run_writes_the_summary(tmp_path):
    out = tmp_path / "out.json"
    result = teleop(
        "run", "path-following", "--inprocess", "--duration", "3", "--seed", "1",
        "--set", "run.settle_s=1", "--summary-json", str(out),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    summary = json.loads(out.read_text())
    assert SUMMARY_KEYS <= summary.keys()
    assert summary["steps"] == 3000 and summary["compensation"] is True
    assert json.loads(result.stdout) == summary
    assert "100%" in result.stderr  # progress is shown


def test_bad_override_exits_2_with_the_key_named():
    result = teleop("run", "path-following", "--inprocess", "--set", "control.gain=1")
    assert result.returncode == 2
    assert "control: unknown key(s) gain" in result.stderr


def _read_json(path: Path) -> dict:
    return json.loads(path.read_text())


# Plant states that applied a controller command, seen on the bus before `teleop down`.
STATES_TO_SEE = 500


def applied_states(endpoint_override: str, count: int) -> int:
    """Join the stack's bus (the plant listens on ``bus.endpoint``) and wait, event driven,
    for ``count`` plant states that carry an applied command; how many came."""
    config = load_config(None, [endpoint_override, "bus.gossip=false"])
    topics = Topics(config.robot.robot_id)
    seen, done = [0], threading.Event()

    def on_state(rec, rx_ns) -> None:
        if int(rec["cmd_seq_applied"]) > 0:
            seen[0] += 1
            if seen[0] >= count:
                done.set()

    session = open_session(config.bus, listen=False)
    sub = subscribe(session, topics.plant_state, PLANT_STATE, on_state, DropCounter())
    try:
        done.wait(UP_TIMEOUT_S)  # bounds a failure only
        return min(seen[0], count)
    finally:
        close_session(session, sub)


def test_up_status_down_runs_a_linked_stack_until_stopped(tmp_path):
    """The README's long-running stack: `teleop up` starts the services detached (the
    plant listens, the others join it by the launcher's mesh), `teleop status` says
    RUNNING, `teleop down` stops them. The plant applied the controller's commands and
    every pair linked (unlinked_peers empty), so the mesh worked without gossip."""
    run_dir = tmp_path / "up"
    endpoint = f'bus.endpoint="tcp/127.0.0.1:{free_loopback_port()}"'  # not 7447: CI
    up = teleop("up", "--mode", "realtime", "--run-dir", str(run_dir), "--set", endpoint)
    try:
        assert up.returncode == 0, up.stderr
        services = ("plant", "controller", "recorder", "eyeview")
        # The plant steps only once every service is ready: its states applying the
        # controller's commands mean the whole stack runs.
        assert applied_states(endpoint, STATES_TO_SEE) == STATES_TO_SEE
        status = teleop("status", "--run-dir", str(run_dir))
        assert status.returncode == 0, status.stdout + status.stderr
        for name in services:
            assert f"{name:12s} RUNNING" in status.stdout
    finally:
        down = teleop("down", "--run-dir", str(run_dir))
    assert down.returncode == 0, down.stderr
    assert teleop("status", "--run-dir", str(run_dir)).returncode != 0  # nothing left
    plant = _read_json(run_dir / "plant.summary.json")
    assert plant["commands_applied"] >= STATES_TO_SEE and plant["stale_commands"] == 0
    for name in services:
        assert _read_json(run_dir / f"{name}.summary.json")["unlinked_peers"] == [], name
    assert (run_dir / "recording.rrd").stat().st_size > 0
