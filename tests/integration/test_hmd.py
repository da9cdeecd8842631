"""The HMD service as a process on an isolated bus, clocked by TOOL_POSE ticks.

Waits on liveliness and on the records themselves, never on a fixed sleep.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading

import numpy as np
import pytest

from teleop.bus.messages import HEAD_POSE, TOOL_POSE, DropCounter
from teleop.bus.session import Publisher, close_session, open_session, subscribe, wait_alive
from teleop.bus.topics import Topics
from teleop.core.config import REPO_ROOT, load_config
from teleop.core.net import free_loopback_port
from teleop.core.ticks import head_schedule, last_sample_tick
from teleop.devices.hmd import HmdEmulator
from tests.unit.test_hmd import run_emulator

ALIVE_TIMEOUT_S = 60.0
RECORDS_TIMEOUT_S = 30.0
EXIT_TIMEOUT_S = 30.0


def test_hmd_process_publishes_on_the_sample_ticks(tmp_path):
    """services/hmd.py on an isolated bus, clocked by TOOL_POSE ticks from this test."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    overrides = [f'bus.endpoint="{endpoint}"', "run.seed=9"]
    config = load_config(None, overrides)
    topics = Topics(config.robot.robot_id)
    schedule = head_schedule(config)
    assert schedule.tick_s == config.tick_s  # the HMD samples on bus ticks
    tick_ns = round(config.tick_s * 1e9)
    last_tick = 300
    sample_ticks = [k for k in range(last_tick + 1) if schedule.is_sample(k)]
    assert last_sample_tick(last_tick, schedule.rate_hz, schedule.tick_s) == sample_ticks[-1]

    received: list[np.ndarray] = []
    cond = threading.Condition()
    drops = DropCounter()

    def on_pose(rec: np.ndarray, rx_ns: int) -> None:
        with cond:
            received.append(rec.copy())
            cond.notify_all()

    def wait_records(count: int) -> None:
        with cond:
            ok = cond.wait_for(lambda: len(received) >= count, RECORDS_TIMEOUT_S)
        assert ok, f"{len(received)} HEAD_POSE records, expected {count}"

    session = open_session(config.bus, listen=True)
    sub = subscribe(session, topics.head_pose, HEAD_POSE, on_pose, drops)
    state_pub = Publisher.declare(session, topics.tool_pose, TOOL_POSE)
    command = [sys.executable, "-m", "services.hmd", "--run-dir", str(tmp_path)]
    for override in overrides:
        command += ["--set", override]
    proc = subprocess.Popen(command, cwd=REPO_ROOT, stdin=subprocess.DEVNULL)
    try:
        wait_alive(session, topics, ["hmd"], ALIVE_TIMEOUT_S)
        assert state_pub.wait_matched(ALIVE_TIMEOUT_S)
        state = TOOL_POSE.new()
        # The plant's TOOL_POSE period (ticks of loop.rate_hz), as PlantStepCore sends them.
        scene_period = max(1, round(1 / (config.plant.scene_rate_hz * config.tick_s)))
        resent_tick = scene_period * 2  # a re-sent clock tick must not give more records
        for run in range(2):  # the second run (tick 0 again) must reset the filter
            for k in range(0, last_tick + 1, scene_period):
                state["seq"] += 1
                state["sim_time_ns"] = k * tick_ns
                state_pub.put(state)
                if k == resent_tick:
                    state_pub.put(state)
            wait_records(len(sample_ticks) * (run + 1))
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(EXIT_TIMEOUT_S) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        close_session(session, sub, state_pub)

    n = len(sample_ticks)
    assert len(received) == 2 * n and drops.total == 0
    first, second = received[:n], received[n:]
    assert [int(r["sim_time_ns"]) // tick_ns for r in first] == sample_ticks
    assert [int(r["valid_from_tick"]) for r in first] == [
        k + schedule.lead_ticks for k in sample_ticks
    ]
    assert [int(r["seq"]) for r in received] == list(range(2 * n))
    # Same seed, fresh filter: the second run repeats the first, and both equal the
    # in-process emulator bit for bit.
    reference = run_emulator(HmdEmulator(config), sim_s=(last_tick + 1) * schedule.tick_s)
    payload = ("measured_p_m", "filtered_p_m", "predicted_p_m", "predicted_yaw_rad")
    for a, b, ref in zip(first, second, reference, strict=True):
        for field in payload:
            assert np.array_equal(a[field], b[field])
        assert np.array_equal(a["predicted_p_m"], ref.predicted.p_m)
        assert float(a["measured_yaw_rad"]) == ref.measured.yaw_rad
        assert float(a["horizon_s"]) == pytest.approx(schedule.lead_s)
    summary = json.loads((tmp_path / "hmd.summary.json").read_text())
    assert summary["samples"] == n and summary["published"] == 2 * n
    assert summary["runs"] == 2 and summary["resent_states"] == 2
    assert summary["dropped_messages"] == 0
    assert summary["filtered_error"]["position_rms_m"] < summary["measured_error"]["position_rms_m"]
