"""The haptic device emulator: handle physics, Kalman velocity, stale feedback, the service."""

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
from teleop.core.config import REPO_ROOT, Config, HapticConfig, load_config
from teleop.devices.haptic import (
    EmulatedDevice,
    FeedbackHold,
    KalmanVelocityEstimator,
    max_stable_stiffness_n_per_m,
)
from teleop.run.stack import free_loopback_port

PERIOD_S = 0.001  # the plant period the device steps at
NS_PER_MS = 1_000_000
NS_PER_S = 1_000_000_000
# The velocity-filter tuning these tests recommend (m/s^2); see KalmanVelocityEstimator.
KF_ACCEL_NOISE_M_S2 = 3.0


def simulate(device: EmulatedDevice, steps: int, target: np.ndarray | None) -> np.ndarray:
    """Step ``steps`` periods toward ``target``; the true positions, (steps, 3)."""
    out = np.empty((steps, 3))
    for i in range(steps):
        device.step(PERIOD_S, target, Button.NONE)
        out[i] = device.true_p_m
    return out


def critically_damped_reference(config: HapticConfig, amplitude_m: float, t_s: np.ndarray):
    """Exact step response of m x'' + (b + B_h) x' + K_h x = K_h A from rest (A = amplitude)."""
    m, k = config.handle_mass_kg, config.hand_stiffness_n_per_m
    c = config.damping_n_s_per_m + config.hand_damping_n_s_per_m
    disc = complex(c * c - 4 * m * k) ** 0.5
    s1, s2 = (-c + disc) / (2 * m), (-c - disc) / (2 * m)
    x = 1 + (s2 * np.exp(s1 * t_s) - s1 * np.exp(s2 * t_s)) / (s1 - s2)
    return amplitude_m * x.real


# --- device physics -------------------------------------------------------------------


def test_handle_follows_the_hand_as_a_mass_spring_damper_and_stays_inside():
    config = HapticConfig()
    device = EmulatedDevice(config, PERIOD_S)
    target = np.array([0.02, -0.01, 0.03])
    p = simulate(device, 1000, target)
    assert np.allclose(p[-1], target, atol=1e-6)
    assert np.all(np.abs(p) <= config.workspace_half_m)
    # Against the continuous solution, per axis: within 1 % of the step (integration error).
    t_s = PERIOD_S * np.arange(1, 1001)
    for axis in range(3):
        reference = critically_damped_reference(config, target[axis], t_s)
        assert np.max(np.abs(p[:, axis] - reference)) < 0.01 * abs(target[axis])
    # The encoders report the position to within half a count.
    q = config.encoder_resolution_m
    assert np.all(np.abs(device.read().p_m - device.true_p_m) <= q / 2 + 1e-12)


def test_feedback_force_is_felt_as_a_displacement_of_f_over_k_hand():
    config = HapticConfig()
    device = EmulatedDevice(config, PERIOD_S)
    force_n = np.array([0.0, 2.0, -1.0])
    device.render(force_n)
    simulate(device, 1000, np.zeros(3))
    expected_m = force_n / config.hand_stiffness_n_per_m  # 10 mm left, 5 mm down
    assert np.allclose(device.true_p_m, expected_m, atol=1e-6)
    assert np.allclose(device.read().f_n, force_n)


def test_rendered_force_saturates_at_peak():
    config = HapticConfig()
    device = EmulatedDevice(config, PERIOD_S)
    device.render(np.array([30.0, 40.0, 0.0]))  # 50 N
    simulate(device, 1000, np.zeros(3))
    rendered = device.read().f_n
    assert np.linalg.norm(rendered) == pytest.approx(config.peak_force_n, rel=1e-12)
    assert np.allclose(rendered / np.linalg.norm(rendered), [0.6, 0.8, 0.0])
    # Displacement is that of the saturated force: 8 N / 200 N/m = 40 mm, inside the stops.
    assert np.linalg.norm(device.true_p_m) == pytest.approx(0.04, abs=1e-5)


def test_end_stops_hold_against_hand_and_force():
    config = HapticConfig()
    half = config.workspace_half_m
    device = EmulatedDevice(config, PERIOD_S)
    p = simulate(device, 500, np.array([0.2, -0.2, 0.0]))
    assert np.all(np.abs(p) <= half)
    assert np.allclose(device.true_p_m, [half, -half, 0.0])
    assert np.allclose(device.true_v_m_s, 0.0)
    # Released handle under a force: it slides to the stop and stays there.
    device.reset()
    device.render(np.array([0.0, 0.0, 5.0]))
    p = simulate(device, 500, None)
    assert p[:, 2].max() == half and np.allclose(device.true_p_m, [0.0, 0.0, half])


def test_stability_bound_is_colgates():
    config = HapticConfig(damping_n_s_per_m=3.0)
    assert max_stable_stiffness_n_per_m(config, 0.001) == pytest.approx(6000.0)


# --- velocity estimate ----------------------------------------------------------------


@pytest.mark.parametrize("speed_m_s", [0.0123, -0.05])
def test_kalman_velocity_converges_and_beats_finite_differences(speed_m_s):
    q = HapticConfig().encoder_resolution_m
    estimator = KalmanVelocityEstimator(q, KF_ACCEL_NOISE_M_S2, PERIOD_S)
    n = 2000
    offset_m = 0.0013  # not on an encoder count
    p_true = offset_m + speed_m_s * PERIOD_S * np.arange(n)
    p_quantised = q * np.round(p_true / q)
    estimator.reset(np.full(3, p_quantised[0]))
    v_kf = np.array([estimator.update(np.full(3, z), PERIOD_S)[0] for z in p_quantised])
    v_fd = np.diff(p_quantised) / PERIOD_S
    settled = slice(n // 2, None)
    assert np.mean(v_kf[settled]) == pytest.approx(speed_m_s, rel=0.02)
    assert np.mean(v_kf[50:200]) == pytest.approx(speed_m_s, rel=0.05)  # after 50 ms
    assert np.std(v_kf[settled]) < 0.35 * np.std(v_fd[settled])


def test_device_reports_kalman_velocity_of_quantised_motion():
    config = HapticConfig(kf_accel_noise_m_s2=KF_ACCEL_NOISE_M_S2)
    device = EmulatedDevice(config, PERIOD_S)
    target = np.array([0.03, 0.0, 0.0])
    velocity_error = []
    for _ in range(300):
        device.step(PERIOD_S, target, Button.GRIPPER_CLOSE)
        velocity_error.append(device.read().v_m_s[0] - device.true_v_m_s[0])
    sample = device.read()
    assert sample.buttons == Button.GRIPPER_CLOSE
    # Peak handle speed is about 0.4 m/s; the estimate tracks it to a few mm/s after 50 ms.
    assert np.sqrt(np.mean(np.square(velocity_error[50:]))) < 0.02


# --- stale feedback -------------------------------------------------------------------


def test_feedback_fades_to_zero_when_stale_and_is_never_held():
    hold = FeedbackHold(stale_after_s=0.020, fade_s=0.020)
    force_n = np.array([1.0, -2.0, 0.5])
    assert np.allclose(hold.force_at(0)[0], 0.0)  # nothing received yet
    hold.receive(force_n, 5 * NS_PER_MS)
    for t_ms in (5, 15, 25):
        force, stale = hold.force_at(t_ms * NS_PER_MS)
        assert np.allclose(force, force_n) and not stale
    norms = []
    for t_ms in range(26, 100):
        force, stale = hold.force_at(t_ms * NS_PER_MS)
        assert stale
        assert float(force @ force_n) >= 0.0  # same direction, never reversed
        norms.append(np.linalg.norm(force))
    norms = np.array(norms)
    assert np.all(np.diff(norms) <= 1e-12)  # monotone fade
    assert norms[35 - 26] == pytest.approx(0.5 * np.linalg.norm(force_n))  # half way
    assert np.all(norms[45 - 26 :] == 0.0)  # gone after stale + fade
    assert hold.stale_events == 1
    hold.receive(-force_n, 100 * NS_PER_MS)  # fresh again: rendered in full
    force, stale = hold.force_at(101 * NS_PER_MS)
    assert np.allclose(force, -force_n) and not stale
    hold.force_at(200 * NS_PER_MS)
    assert hold.stale_events == 2


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
        lead_ticks = round(1.0 / (config.operator.decision_rate_hz * config.plant.timestep_s))
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
            state["sim_time_ns"] = k * NS_PER_MS
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
            assert int(reply["sim_time_ns"]) == k * NS_PER_MS
            assert reply["trace_ns"][Stage.HAPTIC_SAMPLE] > 0
            if k < lead_ticks:  # no hand input applies yet: the handle rests at the centre
                assert np.all(reply["device_p_m"] == 0.0)
            if k % lead_ticks == 0:  # the operator's decision, valid lead_ticks later
                hand["seq"] = k // lead_ticks + 1
                hand["valid_from_tick"] = k + lead_ticks
                hand["target_p_m"] = hand_target_m
                hand["buttons"] = Button.GRIPPER_CLOSE
                hand_pub.put(hand)

        before_push = replies.records[push_from - 1]
        assert before_push["device_p_m"][0] == pytest.approx(0.02, abs=5e-4)
        assert abs(before_push["device_p_m"][1]) < 1e-4
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
        period_ns = round(rig.config.plant.timestep_s * NS_PER_S)
        feedback_pub = rig.publisher(rig.topics.force_feedback, FORCE_FEEDBACK)
        replies = rig.replies

        def send(seq: int, tick: int) -> None:
            feedback["seq"] = seq
            feedback["tick"] = tick
            feedback["sim_time_ns"] = tick * NS_PER_MS
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
        assert int(first["sim_time_ns"]) == 500 * NS_PER_MS
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
