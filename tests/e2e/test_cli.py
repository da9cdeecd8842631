"""The teleop command as a user runs it: a real subprocess, a real summary file."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
from pathlib import Path

from teleop.bus.messages import PLANT_STATE, DropCounter
from teleop.bus.session import close_session, open_session, subscribe
from teleop.bus.topics import Topics
from teleop.core.config import load_config
from teleop.core.summary import SUMMARY_VERSION, read_run_summary, summary_problems

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
        "--set", "run.settle_s=1", "--summary-json", str(out), "--json",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    summary = json.loads(out.read_text())
    assert SUMMARY_KEYS <= summary.keys()
    assert summary_problems(summary) == [] and summary["summary_version"] == SUMMARY_VERSION
    assert summary["steps"] == round(3 / load_config().tick_s) and summary["compensation"] is True
    assert json.loads(result.stdout) == summary  # --json: the full summary on stdout
    assert "100%" in result.stderr  # progress is shown


def test_without_json_the_summary_is_short_and_the_file_full(tmp_path):
    result = teleop(
        "run", "path-following", "--inprocess", "--duration", "2", "--set", "run.settle_s=1",
        "--run-dir", str(tmp_path),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0].startswith("path-following") and len(lines) <= 15
    assert f"  full summary       {tmp_path / 'summary.json'}" in lines
    summary = read_run_summary(tmp_path / "summary.json").to_json()
    assert SUMMARY_KEYS <= summary.keys() and summary_problems(summary) == []


def test_bad_override_exits_2_with_the_key_named():
    result = teleop("run", "path-following", "--inprocess", "--set", "control.gain=1")
    assert result.returncode == 2
    assert "control: unknown key(s) gain" in result.stderr


def _read_json(path: Path) -> dict:
    return json.loads(path.read_text())


# Plant states that applied a controller command, seen on the bus before `teleop down`.
STATES_TO_SEE = 500


class StateCount:
    """A session on the stack's bus (the plant listens on ``endpoint``) with
    ``credentials`` (None: none), counting the plant states that carry an applied
    command."""

    def __init__(self, endpoint: str, credentials: Path | None, target: int = 0) -> None:
        overrides = [f'bus.endpoint="{endpoint}"', "bus.gossip=false"]
        if credentials is not None:
            overrides.append(f'bus.credentials_file="{credentials}"')
        config = load_config(None, overrides)
        self.count, self.target, self.done = 0, target, threading.Event()
        self.session = open_session(config.bus, listen=False)
        topics = Topics(config.robot.robot_id)
        self.sub = subscribe(self.session, topics.plant_state, PLANT_STATE, self._on, DropCounter())

    def _on(self, rec, rx_ns) -> None:
        if int(rec["cmd_seq_applied"]) > 0:
            self.count += 1
            if self.target and self.count >= self.target:
                self.done.set()

    def close(self) -> None:
        close_session(self.session, self.sub)


def applied_states(endpoint: str, count: int, credentials: Path | None) -> int:
    """Wait, event driven, for ``count`` applied plant states (a bound of UP_TIMEOUT_S)
    seen by a :class:`StateCount`; how many came."""
    watcher = StateCount(endpoint, credentials, target=count)
    try:
        watcher.done.wait(UP_TIMEOUT_S)  # bounds a failure only
        return min(watcher.count, count)
    finally:
        watcher.close()


def test_up_status_down_runs_a_linked_stack_until_stopped(tmp_path):
    """The README's long-running stack: `teleop up` starts the services detached (the
    plant listens, the others join it by the launcher's mesh), `teleop status` says
    RUNNING, `teleop down` stops them. The plant applied the controller's commands and
    every pair linked (unlinked_peers empty), so the mesh worked without gossip."""
    run_dir = tmp_path / "up"
    up = teleop("up", "--mode", "realtime", "--run-dir", str(run_dir))
    try:
        assert up.returncode == 0, up.stderr
        endpoint = re.search(r"bus: (tls/127\.0\.0\.1:\d+)", up.stdout).group(1)
        services = ("plant", "controller", "recorder", "eyeview")
        # The plant steps only once every service is ready: its states applying the
        # controller's commands mean the whole stack runs. The run's read-only observer
        # credentials let this test watch; a second stack on the same endpoint is refused.
        observer = run_dir / "auth" / "observer.json"
        assert applied_states(endpoint, STATES_TO_SEE, observer) == STATES_TO_SEE
        other = tmp_path / "other"
        second = teleop("up", "--run-dir", str(other), "--endpoint", endpoint)
        assert second.returncode == 1 and second.stderr.count("\n") == 1, second.stderr
        assert f"bus endpoint {endpoint} is in use" in second.stderr
        status = teleop("status", "--run-dir", str(run_dir))
        assert status.returncode == 0, status.stdout + status.stderr
        for name in services:
            assert f"{name:12s} RUNNING" in status.stdout
    finally:
        down = teleop("down", "--run-dir", str(run_dir))
    assert down.returncode == 0, down.stderr
    assert teleop("status", "--run-dir", str(run_dir)).returncode != 0  # nothing left
    plant = _read_json(run_dir / "plant.summary.json")
    # Stale commands are the realtime verdict's business (a busy machine has some).
    assert plant["commands_applied"] >= STATES_TO_SEE and "stale_commands" in plant
    for name in services:
        assert _read_json(run_dir / f"{name}.summary.json")["unlinked_peers"] == [], name
    assert (run_dir / "recording.rrd").stat().st_size > 0


def test_a_session_without_the_runs_credentials_sees_nothing_of_a_stack(tmp_path):
    """`teleop up`'s bus is closed to anyone without the run's files: a session with no
    credentials (another user, another stack) gets none of the plant's states while
    the run's observer gets them, through the same endpoint at the same time."""
    run_dir = tmp_path / "up"
    up = teleop("up", "--mode", "realtime", "--run-dir", str(run_dir))
    try:
        assert up.returncode == 0, up.stderr
        endpoint = re.search(r"bus: (tls/127\.0\.0\.1:\d+)", up.stdout).group(1)
        stranger = StateCount(endpoint, None)
        try:
            observer = run_dir / "auth" / "observer.json"
            assert applied_states(endpoint, STATES_TO_SEE, observer) == STATES_TO_SEE
        finally:
            stranger.close()
        assert stranger.count == 0
    finally:
        assert teleop("down", "--run-dir", str(run_dir)).returncode == 0
