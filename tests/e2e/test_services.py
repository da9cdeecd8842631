"""The services as users run them: real processes, a real supervisord, a real Zenoh bus."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from teleop.bus.messages import JOINT_COMMAND, PLANT_STATE, RUN_EVENT, DropCounter, Event
from teleop.bus.session import (
    Latest,
    Publisher,
    close_session,
    declare_alive,
    open_session,
    subscribe,
    wait_alive,
)
from teleop.bus.topics import Topics
from teleop.core.config import load_config
from teleop.core.net import LoopbackPorts
from teleop.core.summary import summary_problems
from teleop.core.ticks import scene_schedule
from teleop.run.experiments import run_path_following_inprocess
from teleop.run.stack import peer_mesh, service_programs
from teleop.run.supervise import Stack
from teleop.viz import entities as ent
from teleop.viz.rrd import Recording
from tests.e2e.outcome import assert_ran, services_record_problems

OBSERVER = "observer"
ALIVE_TIMEOUT_S = 60.0
# Sim time may lead wall time by the run's first periods (its wall clock starts after
# the first state goes out): a fraction of a 4 s run, far below any real pacing error.
REALTIME_AHEAD_TOLERANCE = 0.05
EVENT_TIMEOUT_S = 30.0


def teleop(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "teleop.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        stdin=subprocess.DEVNULL,
    )


def run_services(tmp_path: Path, name: str, *args: str) -> dict:
    out = tmp_path / f"{name}.json"
    result = teleop(
        "run", "path-following", "--run-dir", str(tmp_path / name), "--summary-json", str(out),
        "--quiet", *args,
    )  # fmt: skip
    summary = json.loads(out.read_text()) if out.exists() else None
    assert_ran(result.returncode, summary, result.stderr)
    assert summary_problems(summary) == []  # as teleop.core.summary describes it
    assert services_record_problems(summary) == []  # as their records read them
    return summary


def test_lockstep_is_deterministic_and_equals_the_inprocess_run(tmp_path):
    settings = ["--duration", "3", "--seed", "2", "--set", "run.settle_s=1"]
    first = run_services(tmp_path, "a", "--mode", "lockstep", *settings)
    second = run_services(tmp_path, "b", "--mode", "lockstep", *settings)
    reference = run_path_following_inprocess(
        load_config(None, ["run.duration_s=3", "run.seed=2", "run.settle_s=1"]), progress=None
    )
    assert first["final_state_sha256"] == second["final_state_sha256"]
    assert first["final_state_sha256"] == reference["final_state_sha256"]
    assert first["path_error_rms_m"] == pytest.approx(reference["path_error_rms_m"], rel=1e-12)
    assert first["steps"] == round(3 / load_config().tick_s) and first["mode"] == "lockstep"
    assert first["dropped_messages"] == 0 and first["stale_commands"] == 0
    assert first["unlinked_peers"] == {}
    assert Path(first["rrd"]).stat().st_size > 0
    # Outside teleoperation the plant computes contact and proximity at the scene rate
    # only: the recording has them for those states alone, at their own sim times.
    config = load_config()
    scene = scene_schedule(config)
    timestep_ns = round(config.tick_s * 1e9)
    q_entity = ent.joint_entity(ent.ENTITY_JOINT_Q, config.robot.arm_joints[0])
    data = Recording(first["rrd"]).lists((ent.ENTITY_OBSTACLE_DISTANCE, q_entity))
    state_sims = set(data[q_entity][ent.TIMELINE_SIM])
    sims = data[ent.ENTITY_OBSTACLE_DISTANCE][ent.TIMELINE_SIM]
    assert set(sims) == {t for t in state_sims if scene.is_sample(t // timestep_ns)}
    assert len(set(sims)) >= first["steps"] * config.plant.scene_rate_hz * config.tick_s - 1


@pytest.mark.parametrize("delay_steps", [0, 2])
def test_lockstep_delay_is_the_same_in_services_and_in_process(tmp_path, delay_steps):
    """Step k applies the answer to state k - delay on the services as in process; the
    delay changes the trajectory (so the setting is really applied) but not its accuracy
    once settled (two bus periods of delay take about a second to settle)."""
    overrides = ["run.duration_s=2", "run.seed=3", "run.settle_s=1"]
    settings = ["--duration", "2", "--seed", "3", "--set", "run.settle_s=1"]
    delayed = f"plant.lockstep_delay_steps={delay_steps}"
    services = run_services(tmp_path, "s", "--mode", "lockstep", *settings, "--set", delayed)
    reference = run_path_following_inprocess(load_config(None, [*overrides, delayed]), None)
    default = run_path_following_inprocess(load_config(None, overrides), progress=None)
    assert services["final_state_sha256"] == reference["final_state_sha256"]
    assert reference["final_state_sha256"] != default["final_state_sha256"]
    assert services["services"]["plant"]["unanswered_commands"] == 0
    ticks = round(2 / load_config().tick_s)
    assert services["services"]["plant"]["commands_applied"] == ticks - delay_steps
    assert reference["path_error_max_m"] < 1e-3


def test_a_tls_run_links_only_by_tls_and_equals_the_inprocess_run(tmp_path):
    """With bus.tls every process of the run has its own certificate and every link of
    the mesh is mutual TLS (tls/ endpoints only, none left on tcp/); the lockstep run is
    the same run as in process."""
    settings = ["--duration", "2", "--seed", "4", "--set", "run.settle_s=1"]
    summary = run_services(
        tmp_path, "tls", "--mode", "lockstep", *settings, "--set", "bus.tls=true"
    )
    reference = run_path_following_inprocess(
        load_config(None, ["run.duration_s=2", "run.seed=4", "run.settle_s=1"]), progress=None
    )
    assert summary["final_state_sha256"] == reference["final_state_sha256"]
    assert summary["steps"] == round(2 / load_config().tick_s) and summary["unlinked_peers"] == {}
    assert summary["dropped_messages"] == 0 and summary["stale_commands"] == 0
    run_dir = tmp_path / "tls"
    commands = (run_dir / "supervisord.conf").read_text()
    assert "tls/127.0.0.1:" in commands and "tcp/" not in commands
    for name in ("plant", "controller", "recorder", "launcher", "observer"):
        assert (run_dir / "auth" / f"{name}.cert.pem").exists(), name


def test_realtime_run_keeps_time_and_accuracy(tmp_path):
    summary = run_services(
        tmp_path, "rt", "--mode", "realtime", "--duration", "4", "--set", "run.settle_s=2"
    )
    assert summary["mode"] == "realtime" and summary["steps"] == round(4 / load_config().tick_s)
    # Realtime pacing never runs ahead of the wall clock (a loaded machine can only make
    # it slower); how close to 1.0 it keeps is measured by tests/benchmarks/lockstep_speed.py
    # and `teleop latency`, not asserted on a shared machine.
    assert summary["realtime_factor"] <= 1.0 + REALTIME_AHEAD_TOLERANCE
    assert summary["path_error_rms_m"] < 0.001
    assert summary["dropped_messages"] == 0


class Observer:
    """A test's own session: the run's listener, watching events and plant states."""

    def __init__(self, config, topics: Topics) -> None:
        self.session = open_session(config.bus, listen=True)
        self.events: list[tuple[int, int]] = []
        self.event_arrived = threading.Condition()
        self.states = Latest()
        self.drops = DropCounter()
        self.entities = [
            subscribe(self.session, topics.plant_events, RUN_EVENT, self._on_event, self.drops),
            subscribe(self.session, topics.plant_state, PLANT_STATE, self._on_state, self.drops),
            declare_alive(self.session, topics, OBSERVER),
            declare_alive(self.session, topics, OBSERVER, ready=True),  # the plant awaits it
        ]

    def _on_state(self, rec: np.ndarray, rx_ns: int) -> None:
        self.states(rec.copy(), rx_ns)

    def _on_event(self, rec: np.ndarray, rx_ns: int) -> None:
        with self.event_arrived:
            self.events.append((int(rec["event"]), int(rec["step"])))
            self.event_arrived.notify_all()

    def count(self, event: Event) -> int:
        with self.event_arrived:
            return sum(e == event for e, _ in self.events)

    def wait_event(self, event: Event, count: int = 1) -> int:
        """Wait for the ``count``-th ``event``; the plant step it carries."""
        with self.event_arrived:
            ok = self.event_arrived.wait_for(lambda: self.count(event) >= count, EVENT_TIMEOUT_S)
            assert ok, f"no {event.name} event; events so far: {self.events}"
            return [step for e, step in self.events if e == event][count - 1]

    def state_after(self, seq: int) -> np.ndarray:
        got = self.states.wait_newer(seq, EVENT_TIMEOUT_S)
        assert got is not None
        return got[0]

    def close(self) -> None:
        close_session(self.session, *reversed(self.entities))


@pytest.fixture
def realtime_pair(tmp_path):
    """Plant and controller (realtime, continuous) under supervisord, and a Observer."""
    ports = LoopbackPorts()  # held until the stack is down, as a launcher holds them
    endpoint = f"tcp/127.0.0.1:{ports.take()}"
    overrides = [f'bus.endpoint="{endpoint}"', 'run.mode="realtime"']
    config = load_config(None, overrides)
    topics = Topics(config.robot.robot_id)
    services = ("plant", "controller")
    programs = service_programs(
        services,
        None,
        overrides,
        tmp_path,
        listener=None,
        await_services={"plant": ["controller", OBSERVER]},
        continuous=True,
        mesh=peer_mesh(services, None, ports),
    )
    stack = Stack(tmp_path, programs)
    tester = Observer(config, topics)
    try:
        stack.start()
        wait_alive(tester.session, topics, ["plant", "controller"], ALIVE_TIMEOUT_S)
        tester.wait_event(Event.STARTED)
        yield stack, tester, config, topics
    finally:
        stack.stop()
        tester.close()
        ports.close()


def test_watchdog_brakes_and_holds_on_a_frozen_controller_then_resumes(realtime_pair):
    stack, tester, config, _ = realtime_pair
    tester.state_after(500)  # half a second of normal running
    # A loaded machine may have braked (and resumed) already: the freeze's brake is the next.
    brakes, resumes = tester.count(Event.WATCHDOG_BRAKE), tester.count(Event.WATCHDOG_RESUME)
    os.kill(stack.pid("controller"), signal.SIGSTOP)
    try:
        brake_step = tester.wait_event(Event.WATCHDOG_BRAKE, brakes + 1)
        braking_start = tester.state_after(brake_step + 50)
        held = tester.state_after(int(braking_start["seq"]) + 500)  # 0.5 s later
    finally:
        os.kill(stack.pid("controller"), signal.SIGCONT)
    n = len(config.robot.arm_joints)
    assert int(braking_start["flags"]) & 1 and int(held["flags"]) & 1  # BRAKING on both
    drift_rad = np.abs(held["q_rad"][:n] - braking_start["q_rad"][:n]).max()
    assert drift_rad < 1e-3, f"the arm drifted {drift_rad} rad while braked"
    assert np.abs(held["qd_rad_s"][:n]).max() < 1e-2
    tester.wait_event(Event.WATCHDOG_RESUME, resumes + 1)


def test_plant_drops_bad_commands_counts_them_and_keeps_running(realtime_pair, tmp_path):
    stack, tester, config, topics = realtime_pair
    raw = tester.session.declare_publisher(topics.joint_command)
    typed = Publisher.declare(tester.session, topics.joint_command, JOINT_COMMAND)
    bad = [b"short", b"\x00" * JOINT_COMMAND.size]  # wrong size; wrong version
    nan_command = JOINT_COMMAND.new()
    nan_command["n_joints"] = 6
    nan_command["qd_ref_rad_s"][0] = np.nan
    wrong_arm = JOINT_COMMAND.new()
    wrong_arm["n_joints"] = 3
    for payload in bad:
        raw.put(payload)
    typed.put(nan_command)
    typed.put(wrong_arm)
    # STARTED and the first state travel on different keys: wait for a state itself.
    before = int(tester.state_after(-1)["seq"])
    tester.state_after(before + 200)  # still stepping
    stack.stop()
    summary = json.loads((tmp_path / "plant.summary.json").read_text())
    assert summary["dropped_messages"] == 4


def wait_for_line(stream, needle: str, timeout_s: float) -> bool:
    """Read ``stream`` (a process's text output) until a line holds ``needle``; False if
    the stream ends or ``timeout_s`` passes first (the timeout only bounds a failure)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        ready, _, _ = select.select([stream], [], [], 1.0)
        if not ready:
            continue
        line = stream.readline()
        if not line:
            return False
        if needle in (line.decode(errors="replace") if isinstance(line, bytes) else line):
            return True
    return False


def test_ctrl_c_on_a_run_leaves_no_process_behind(tmp_path):
    run_dir = tmp_path / "interrupted"
    proc = subprocess.Popen(
        [sys.executable, "-m", "teleop.cli", "run", "path-following", "--mode", "realtime",
         "--duration", "20", "--run-dir", str(run_dir)],
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    # The first progress line ("  sim   0.5 s of 20 s ...") says the run is under way.
    assert wait_for_line(proc.stderr, "  sim ", ALIVE_TIMEOUT_S), "the run never started"
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=60)
    assert proc.returncode != 0
    leftovers = subprocess.run(
        ["pgrep", "-f", str(run_dir)], capture_output=True, text=True
    ).stdout.split()
    assert leftovers == [], f"processes left behind: {leftovers}"
