"""The haptic service as a process on a real Zenoh bus, in lockstep and in realtime."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from teleop.bus.messages import (
    FORCE_FEEDBACK,
    HAND_INPUT,
    HAPTIC_STATE,
    PLANT_STATE,
    Button,
    DropCounter,
    Flag,
    Schema,
    Stage,
)
from teleop.bus.session import Publisher, close_session, open_session, subscribe, wait_alive
from teleop.bus.topics import Topics
from teleop.core.config import REPO_ROOT, Config, load_config
from teleop.core.net import free_loopback_port
from teleop.core.ticks import is_sample_tick, lead_ticks

NS_PER_S = 1_000_000_000

# --- the service as a process, in lockstep ----------------------------------------------

ALIVE_TIMEOUT_S = 30.0  # bound for a process start on a loaded machine; typically ~1 s
REPLY_TIMEOUT_S = 5.0


class Replies:
    """HAPTIC_STATE records received by the test, in arrival order."""

    def __init__(self) -> None:
        self.records: list[np.ndarray] = []
        self.cond = threading.Condition()

    def __call__(self, rec: np.ndarray, rx_ns: int) -> None:
        with self.cond:
            self.records.append(rec.copy())
            self.cond.notify_all()

    def wait_count(self, count: int) -> np.ndarray:
        with self.cond:
            ok = self.cond.wait_for(lambda: len(self.records) >= count, REPLY_TIMEOUT_S)
            assert ok, f"{len(self.records)} HAPTIC_STATE replies, waited for {count}"
            return self.records[count - 1]


@dataclasses.dataclass
class HapticRig:
    """A haptic service process on a test session: its config, the HAPTIC_STATE replies,
    publishers the test declares, and the service's summary once it has stopped."""

    config: Config
    topics: Topics
    session: zenoh.Session
    replies: Replies
    drops: DropCounter
    entities: list
    summary: dict | None = None

    def publisher(self, key: str, schema: Schema) -> Publisher:
        pub = Publisher.declare(self.session, key, schema)
        self.entities.append(pub)
        assert pub.wait_matched(REPLY_TIMEOUT_S)
        return pub


@contextlib.contextmanager
def haptic_service(tmp_path: Path, mode: str) -> Iterator[HapticRig]:
    """Run ``services.haptic`` in ``mode`` until the block ends; it must exit cleanly,
    and ``rig.summary`` then holds its summary."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    overrides = [f'bus.endpoint="{endpoint}"', f'run.mode="{mode}"']
    config = load_config(None, overrides)
    topics = Topics(config.robot.robot_id)
    session = open_session(config.bus, listen=True)
    replies, drops = Replies(), DropCounter()
    entities = [subscribe(session, topics.haptic_state, HAPTIC_STATE, replies, drops)]
    rig = HapticRig(config, topics, session, replies, drops, entities)
    command = [sys.executable, "-m", "services.haptic", "--run-dir", str(tmp_path)]
    for override in overrides:
        command += ["--set", override]
    log = open(tmp_path / "haptic.log", "w")  # noqa: SIM115 (closed in finally)
    proc = subprocess.Popen(command, cwd=REPO_ROOT, stdin=subprocess.DEVNULL, stderr=log)
    try:
        wait_alive(session, topics, ["haptic"], ALIVE_TIMEOUT_S)
        yield rig
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(REPLY_TIMEOUT_S)
        finally:
            if proc.poll() is None:
                proc.kill()
            log.close()
            close_session(session, *reversed(rig.entities))
    assert proc.returncode == 0, (tmp_path / "haptic.log").read_text()[-3000:]
    rig.summary = json.loads((tmp_path / "haptic.summary.json").read_text())


def test_service_steps_once_per_tick_in_lockstep(tmp_path):
    with haptic_service(tmp_path, "lockstep") as rig:
        config, topics, replies = rig.config, rig.topics, rig.replies
        tick_ns = round(config.tick_s * NS_PER_S)  # one bus period (loop.rate_hz)
        hand_rate_hz = config.operator.decision_rate_hz
        hand_lead = lead_ticks(hand_rate_hz, config.tick_s)
        state_pub = rig.publisher(topics.plant_state, PLANT_STATE)
        feedback_pub = rig.publisher(topics.force_feedback, FORCE_FEEDBACK)
        hand_pub = rig.publisher(topics.hand_input, HAND_INPUT)

        state, feedback, hand = PLANT_STATE.new(), FORCE_FEEDBACK.new(), HAND_INPUT.new()
        state["n_joints"] = 6
        hand_target_m = np.array([0.02, 0.0, 0.0])
        push_n = np.array([0.0, 2.0, 0.0])
        ticks, push_from = 600, 300
        for k in range(ticks):
            # State first, then the feedback it needs: most ticks k >= 1 wait for it (Zenoh
            # does not order deliveries across keys, so the feedback may still come first).
            state["seq"] = state["step"] = k
            state["sim_time_ns"] = k * tick_ns
            state_pub.put(state)
            if k >= 1:
                if k == push_from:  # garbage first: oversized, then NaN; both dropped
                    feedback["tick"] = k - 1
                    feedback["device_f_n"] = [100.0, 0.0, 0.0]
                    feedback_pub.put(feedback)
                    feedback["device_f_n"] = [math.nan, 0.0, 0.0]
                    feedback_pub.put(feedback)
                feedback["seq"] = k
                feedback["tick"] = k - 1
                feedback["device_f_n"] = push_n if k >= push_from else 0.0
                feedback_pub.put(feedback)
            reply = replies.wait_count(k + 1)
            assert int(reply["tick"]) == k and int(reply["seq"]) == k + 1
            assert int(reply["sim_time_ns"]) == k * tick_ns
            assert reply["trace_ns"][Stage.HAPTIC_SAMPLE] > 0
            if k < hand_lead:  # no hand input applies yet: the handle rests at the centre
                assert np.all(reply["device_p_m"] == 0.0)
            if is_sample_tick(k, hand_rate_hz, config.tick_s):  # a decision, valid hand_lead later
                hand["seq"] += 1
                hand["valid_from_tick"] = k + hand_lead
                hand["target_p_m"] = hand_target_m
                hand["buttons"] = Button.GRIPPER_CLOSE
                hand_pub.put(hand)

        before_push = replies.records[push_from - 1]
        assert before_push["device_p_m"][0] == pytest.approx(0.02, abs=5e-4)
        assert abs(before_push["device_p_m"][1]) < 1e-4
        # The push ramps in at haptic.max_force_rate_n_per_s (ForceSlew), one step per
        # servo period: it is all there by the end of its first tick's renders.
        slew_step_n = config.haptic.max_force_rate_n_per_s * config.haptic.render_period_s
        assert math.ceil(np.linalg.norm(push_n) / slew_step_n) <= config.renders_per_tick
        assert not replies.records[push_from - 1]["device_f_n"].any()
        assert np.allclose(replies.records[push_from]["device_f_n"], push_n)
        last = replies.records[-1]
        assert last["device_p_m"][0] == pytest.approx(0.02, abs=5e-4)
        assert last["device_p_m"][1] == pytest.approx(2.0 / 200.0, abs=5e-4)  # F / K_hand
        assert last["buttons"] == Button.GRIPPER_CLOSE and last["flags"] == Flag.NONE

        # A plant re-send of the last state: the same reply again, no second step.
        state_pub.put(state)
        again = replies.wait_count(ticks + 1)
        assert int(again["seq"]) == ticks and int(again["tick"]) == ticks - 1
        assert np.array_equal(again["device_p_m"], last["device_p_m"])
        # The plant re-sends every state in flight: state 0 again, byte for byte (same
        # t_source_ns), is no new run (the handle is not re-centred, no reply), then the
        # last state again (same key, so it arrives after: the service has seen both).
        last_state = state.copy()
        state["seq"] = state["step"] = state["sim_time_ns"] = 0
        state_pub.put(state)
        state_pub.put(last_state)
        again = replies.wait_count(ticks + 2)
        assert int(again["seq"]) == ticks and np.array_equal(
            again["device_p_m"], last["device_p_m"]
        )
    summary = rig.summary
    assert summary is not None
    assert summary["steps"] == ticks and summary["runs"] == 1
    assert 0 < summary["lockstep_waits"] <= ticks - 1
    assert summary["dropped_messages"] == 1 and summary["oversized_feedback"] == 1
    assert summary["republished_states"] == 2 and summary["missing_hand_inputs"] == 0
    assert summary["max_rendered_force_n"] == pytest.approx(2.0)
    assert summary["stale_feedback_events"] == 0
    assert len(replies.records) == ticks + 2 and rig.drops.total == 0


def test_service_in_realtime_takes_its_clock_from_the_feedback(tmp_path):
    """Realtime: no PLANT_STATE needed; the samples carry the newest feedback's tick and sim
    time and the device period's deadline; a feedback tick that goes back is a new run."""
    feedback = FORCE_FEEDBACK.new()
    with haptic_service(tmp_path, "realtime") as rig:
        period_ns = round(rig.config.tick_s * NS_PER_S)  # one bus period (loop.rate_hz)
        feedback_pub = rig.publisher(rig.topics.force_feedback, FORCE_FEEDBACK)
        replies = rig.replies

        def send(seq: int, tick: int) -> None:
            feedback["seq"] = seq
            feedback["tick"] = tick
            feedback["sim_time_ns"] = tick * period_ns
            feedback["device_f_n"] = [0.0, 0.5, 0.0]
            feedback["trace_ns"][Stage.FEEDBACK_TX] = time.monotonic_ns()
            feedback_pub.put(feedback)

        def reply_with_tick(tick: int) -> np.ndarray:
            deadline = time.monotonic() + REPLY_TIMEOUT_S
            while time.monotonic() < deadline:
                with replies.cond:
                    found = [r for r in replies.records if int(r["tick"]) == tick]
                    if found:
                        return found[-1]
                    replies.cond.wait(0.05)
            raise AssertionError(f"no HAPTIC_STATE with tick {tick}")

        send(1, 500)
        first = reply_with_tick(500)
        assert int(first["sim_time_ns"]) == 500 * period_ns
        send(2, 501)
        reply_with_tick(501)
        with replies.cond:
            deadlines = np.array([int(r["device_deadline_ns"]) for r in replies.records])
        steps = np.diff(deadlines)
        assert (deadlines > 0).all() and (steps > 0).all() and (steps % period_ns == 0).all()
        send(3, 7)  # the plant started over
        reply_with_tick(7)
    summary = rig.summary
    assert summary is not None
    assert summary["runs"] == 2 and summary["feedback_lost"] == 0
    assert summary["feedback_rendered"] == 3 and rig.drops.total == 0
