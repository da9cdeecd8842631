"""The haptic device and its loop, pure: handle physics, Kalman velocity, stale feedback,
the service's loop on a fake clock with the emulator and with a replay device."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from teleop.bus.messages import (
    FORCE_FEEDBACK,
    HAND_INPUT,
    HAPTIC_STATE,
    PLANT_STATE,
    Button,
    Flag,
    Stage,
)
from teleop.bus.service import STOP_POLL_S
from teleop.control.wave import handle_rate_m_s
from teleop.core.clock import FakeClock
from teleop.core.config import ConfigError, HapticConfig, load_config
from teleop.core.ticks import is_sample_tick
from teleop.devices.haptic.device import (
    EmulatedDevice,
    FeedbackHold,
    ForceSlew,
    HapticDevice,
    KalmanVelocityEstimator,
    LocalContactModel,
    StaleSpells,
    max_stable_stiffness_n_per_m,
    steady_state_gains,
)
from teleop.devices.haptic.loop import HAND_INPUT_WAIT_S, HapticLoop
from teleop.devices.haptic.replay import ReplayDevice

PERIOD_S = 0.001  # the servo period the device steps at (haptic.render_period_s)
NS_PER_MS = 1_000_000
NS_PER_S = 1_000_000_000
# One tick: the bus period (loop.rate_hz) the plant's states and the feedback come at.
TICK_NS = round(load_config().tick_s * NS_PER_S)
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
    device.send_force(force_n)
    simulate(device, 1000, np.zeros(3))
    expected_m = force_n / config.hand_stiffness_n_per_m  # 10 mm left, 5 mm down
    assert np.allclose(device.true_p_m, expected_m, atol=1e-6)
    assert np.allclose(device.read().f_n, force_n)


def test_rendered_force_saturates_at_peak():
    config = HapticConfig()
    device = EmulatedDevice(config, PERIOD_S)
    device.send_force(np.array([30.0, 40.0, 0.0]))  # 50 N
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
    device.send_force(np.array([0.0, 0.0, 5.0]))
    p = simulate(device, 500, None)
    assert p[:, 2].max() == half and np.allclose(device.true_p_m, [0.0, 0.0, half])


def test_stability_bound_is_colgates():
    config = HapticConfig(damping_n_s_per_m=3.0)
    assert max_stable_stiffness_n_per_m(config, 0.001) == pytest.approx(6000.0)


# --- velocity estimate ----------------------------------------------------------------


@pytest.mark.parametrize(
    ("resolution_m", "accel_noise_m_s2", "dt_s"),
    [(2e-5, 3.0, 0.001), (2e-5, 30.0, 0.001), (1e-4, 0.5, 0.004), (5e-6, 3.0, 0.0005)],
)
def test_steady_state_gains_are_filterpys_kalman_filter_converged(
    resolution_m, accel_noise_m_s2, dt_s
):
    """The closed form equals the gain filterpy's KalmanFilter settles to on the model."""
    from filterpy.common import Q_discrete_white_noise
    from filterpy.kalman import KalmanFilter

    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.F = np.array([[1.0, dt_s], [0.0, 1.0]])
    kf.H = np.array([[1.0, 0.0]])
    kf.R = np.array([[resolution_m**2 / 12.0]])
    kf.Q = Q_discrete_white_noise(dim=2, dt=dt_s, var=accel_noise_m_s2**2)
    kf.P = np.diag([resolution_m**2, 1.0])
    for _ in range(5000):
        kf.predict()
        kf.update(np.array([0.0]))
    g, h = steady_state_gains(resolution_m, accel_noise_m_s2, dt_s)
    assert g == pytest.approx(kf.K[0, 0], rel=1e-9)
    assert h == pytest.approx(kf.K[1, 0] * dt_s, rel=1e-9)


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

    def force_at(t_ns: int) -> tuple[np.ndarray, bool]:
        model, stale, _ = hold.model_at(t_ns)
        return model.force_at(np.zeros(3)), stale

    assert np.allclose(force_at(0)[0], 0.0)  # nothing received yet
    hold.receive(LocalContactModel.constant(force_n), 5 * NS_PER_MS)
    assert np.allclose(force_at(4 * NS_PER_MS)[0], 0.0)  # not yet arrived then
    for t_ms in (5, 15, 25):
        force, stale = force_at(t_ms * NS_PER_MS)
        assert np.allclose(force, force_n) and not stale
    norms = []
    for t_ms in range(26, 100):
        force, stale = force_at(t_ms * NS_PER_MS)
        assert stale
        assert float(force @ force_n) >= 0.0  # same direction, never reversed
        norms.append(np.linalg.norm(force))
    norms = np.array(norms)
    assert np.all(np.diff(norms) <= 1e-12)  # monotone fade
    assert norms[35 - 26] == pytest.approx(0.5 * np.linalg.norm(force_n))  # half way
    assert np.all(norms[45 - 26 :] == 0.0)  # gone after stale + fade
    assert hold.stale_events == 1
    hold.receive(LocalContactModel.constant(-force_n), 100 * NS_PER_MS)  # fresh again
    force, stale = force_at(101 * NS_PER_MS)
    assert np.allclose(force, -force_n) and not stale
    force_at(200 * NS_PER_MS)
    assert hold.stale_events == 2


def test_each_render_takes_the_model_that_had_arrived_by_its_time():
    """A bus period rendered in one go renders each servo period with the model received
    by then, as a 1 kHz servo thread would have; the model's stiffness acts about its
    reference position; old models beyond the history still answer for their time."""
    hold = FeedbackHold(stale_after_s=0.020, fade_s=0.020)
    k = -100.0 * np.eye(3)
    for i in range(20):
        hold.receive(LocalContactModel(np.array([float(i), 0, 0]), np.zeros(3), k), i * NS_PER_MS)
    for i in range(12, 20):
        model, stale, received_ns = hold.model_at(i * NS_PER_MS + NS_PER_MS // 2)
        assert received_ns == i * NS_PER_MS and not stale
        assert model.force_at(np.array([0.01, 0.0, 0.0]))[0] == pytest.approx(i - 1.0)


def test_the_force_rate_limit_ramps_a_step_and_keeps_its_direction():
    slew = ForceSlew(max_rate_n_per_s=2000.0, period_s=0.001)  # 2 N per servo period
    forces = [slew.limit(np.array([0.0, 6.0, 8.0])) for _ in range(6)]
    norms = [float(np.linalg.norm(f)) for f in forces]
    assert norms[:5] == pytest.approx([2, 4, 6, 8, 10])
    assert np.allclose(forces[-1], [0.0, 6.0, 8.0]) and slew.limited_steps == 4
    assert all(abs(f[1] * 8.0 - f[2] * 6.0) < 1e-9 for f in forces)  # along the change


# --- the service's loop, on a fake clock ---------------------------------------------


class Sent:
    """HapticOutputs that keeps copies of what the loop sends, and can stop a run."""

    def __init__(self, stop_after: int | None = None) -> None:
        self.samples: list[np.ndarray] = []
        self.resent: list[np.ndarray] = []
        self.stop = threading.Event()
        self.stop_after = stop_after

    def sample(self, rec: np.ndarray, robot: int = 0) -> None:
        self.samples.append(rec.copy())
        if self.stop_after is not None and len(self.samples) >= self.stop_after:
            self.stop.set()

    def resend(self, rec: np.ndarray, robot: int = 0) -> None:
        self.resent.append(rec.copy())


def make_loop(
    device: HapticDevice | None = None, *, lockstep: bool, stop_after: int | None = None
) -> tuple[HapticLoop, Sent, FakeClock]:
    mode = "lockstep" if lockstep else "realtime"
    config = load_config(None, [f'run.mode="{mode}"'])
    device = device or EmulatedDevice(config.haptic, config.haptic.render_period_s)
    sent, clock = Sent(stop_after), FakeClock(start_ns=10 * NS_PER_S)
    return HapticLoop(config, device, sent, clock, lockstep=lockstep), sent, clock


def hand_sample_ticks(loop: HapticLoop, ticks: int) -> list[int]:
    """The ticks below ``ticks`` the operator decides on (operator.decision_rate_hz on
    the loop's ticks): each one's hand input applies from ``lead_ticks`` later, exactly
    the inputs the lockstep device waits for."""
    config = loop.config
    rate_hz, tick_s = config.operator.decision_rate_hz, config.tick_s
    return [k for k in range(ticks) if is_sample_tick(k, rate_hz, tick_s)]


def plant_state(tick: int, t_source_ns: int = 1) -> np.ndarray:
    state = PLANT_STATE.new()
    state["seq"] = state["step"] = tick
    state["sim_time_ns"] = tick * TICK_NS
    state["t_source_ns"] = t_source_ns
    return state


def feedback(seq: int, tick: int, force_n, tx_ns: int = 0) -> np.ndarray:
    rec = FORCE_FEEDBACK.new()
    rec["seq"] = seq
    rec["tick"] = tick
    rec["sim_time_ns"] = tick * TICK_NS
    rec["device_f_n"] = force_n
    rec["trace_ns"][Stage.FEEDBACK_TX] = tx_ns
    return rec


def hand(valid_from_tick: int, target_m, buttons: Button = Button.GRIPPER_CLOSE) -> np.ndarray:
    rec = HAND_INPUT.new()
    rec["valid_from_tick"] = valid_from_tick
    rec["target_p_m"] = target_m
    rec["buttons"] = buttons
    return rec


def test_loop_steps_once_per_tick_in_lockstep():
    """The lockstep barrier: tick k steps once state k, the feedback of k-1 and the hand
    input that applies at k are in; re-sent states step nothing."""
    loop, sent, _ = make_loop(lockstep=True)
    lead = loop.hand_schedule.lead_ticks
    target_m, push_n = np.array([0.02, 0.0, 0.0]), np.array([0.0, 2.0, 0.0])
    ticks, push_from = 600, 300
    decided = set(hand_sample_ticks(loop, ticks))
    for k in range(ticks):
        loop.on_state(plant_state(k))
        if k >= 1:
            if k == push_from:  # oversized: dropped
                loop.on_feedback(feedback(k, k - 1, [100.0, 0.0, 0.0]), 0)
            loop.on_feedback(feedback(k, k - 1, push_n if k >= push_from else 0.0), 0)
        assert len(sent.samples) == k + 1
        reply = sent.samples[k]
        assert int(reply["tick"]) == k and int(reply["seq"]) == k + 1
        assert int(reply["sim_time_ns"]) == k * TICK_NS
        if k < lead:
            assert np.all(reply["device_p_m"] == 0.0)
        if k in decided:
            loop.on_hand(hand(k + lead, target_m))
    assert sent.samples[push_from - 1]["device_p_m"][0] == pytest.approx(0.02, abs=5e-4)
    assert np.allclose(sent.samples[push_from]["device_f_n"], push_n)
    last = sent.samples[-1]
    assert last["device_p_m"][1] == pytest.approx(2.0 / 200.0, abs=5e-4)  # F / K_hand
    assert last["buttons"] == Button.GRIPPER_CLOSE and last["flags"] == Flag.NONE
    # A re-send of the last state: its sample again, unchanged; of state 0 (same stamp):
    # no new run, nothing sent.
    loop.on_state(plant_state(ticks - 1))
    loop.on_state(plant_state(0))
    assert len(sent.samples) == ticks and len(sent.resent) == 1
    assert np.array_equal(sent.resent[0], last)
    summary = loop.summary()
    assert summary["steps"] == ticks and summary["runs"] == 1
    assert summary["lockstep_waits"] == ticks - 1  # every tick after 0 waited for feedback
    assert summary["oversized_feedback"] == 1 and summary["republished_states"] == 1
    assert summary["missing_hand_inputs"] == 0 and summary["stale_feedback_events"] == 0
    assert summary["max_rendered_force_n"] == pytest.approx(2.0)
    # State 0 with a new stamp: a new run, the handle back at the centre.
    loop.on_state(plant_state(0, t_source_ns=2))
    assert loop.runs == 2 and np.all(sent.samples[-1]["device_p_m"] == 0.0)


def run_lockstep_push(loop: HapticLoop, ticks: int, push_from: int, push_n) -> None:
    """Drive a lockstep loop: a hand 2 cm along x from the start, a feedback force
    ``push_n`` from the feedback of tick ``push_from - 1`` on."""
    lead = loop.hand_schedule.lead_ticks
    decided = set(hand_sample_ticks(loop, ticks))
    for k in range(ticks):
        loop.on_state(plant_state(k))
        if k >= 1:
            loop.on_feedback(feedback(k, k - 1, push_n if k >= push_from else 0.0), 0)
        if k in decided:
            loop.on_hand(hand(k + lead, [0.02, 0.0, 0.0]))


def test_an_emulated_link_delays_the_handle_forward_and_the_force_back():
    """site.emulated_round_trip_ms = 25 ticks: the controller takes at tick k the handle
    as it was 12 ticks before (under tick k's seq and tick), the handle feels the feedback
    of tick k-1 only 13 ticks later; the barrier still waits for feedback k-1."""
    plain, plain_sent, _ = make_loop(lockstep=True)
    round_trip_ms = 25 * plain.tick_s * 1e3  # 25 bus periods (loop.rate_hz)
    config = load_config(
        None, ['run.mode="lockstep"', f"site.emulated_round_trip_ms={round_trip_ms:g}"]
    )
    assert config.link_delay_ticks() == (12, 13)
    delayed_sent, clock = Sent(), FakeClock(start_ns=10 * NS_PER_S)
    device = EmulatedDevice(config.haptic, config.haptic.render_period_s)
    delayed = HapticLoop(config, device, delayed_sent, clock, lockstep=True)
    ticks, push_from, push_n = 400, 200, np.array([0.0, 0.0, 1.5])
    run_lockstep_push(plain, ticks, push_from, push_n)
    run_lockstep_push(delayed, ticks, push_from, push_n)
    assert len(delayed_sent.samples) == ticks
    for k, rec in enumerate(delayed_sent.samples):
        assert int(rec["tick"]) == k and int(rec["seq"]) == k + 1
        assert int(rec["sim_time_ns"]) == k * TICK_NS
        if k < push_from:  # no force yet: the same handle, 12 ticks late
            sampled = plain_sent.samples[max(k - 12, 0)]
            assert np.array_equal(rec["device_p_m"], sampled["device_p_m"])
    # The plain loop renders the push at tick push_from; across the link the handle
    # feels it 13 ticks later, and the robot's site sees that 12 ticks after.
    assert np.allclose(plain_sent.samples[push_from]["device_f_n"], push_n)
    felt = push_from + 13 + 12
    assert np.all(delayed_sent.samples[felt - 1]["device_f_n"] == 0.0)
    assert np.allclose(delayed_sent.samples[felt]["device_f_n"], push_n)
    # Without feedback k-1 tick k does not step, delay or not.
    delayed.on_state(plant_state(ticks))
    assert len(delayed_sent.samples) == ticks
    assert delayed.summary()["link_delay_ticks"] == {"forward": 12, "backward": 13}


class RenderLog(EmulatedDevice):
    """The emulator, keeping each servo period's force sent and the handle position
    (encoders) it was rendered at."""

    def __init__(self, config: HapticConfig, period_s: float) -> None:
        super().__init__(config, period_s)
        self.renders: list[tuple[np.ndarray, np.ndarray]] = []  # (at p_m, force sent)

    def send_force(self, force_n: np.ndarray) -> None:
        self.renders.append((self.read().p_m, np.array(force_n, dtype=np.float64)))
        super().send_force(force_n)


def test_with_wave_variables_the_handle_renders_the_channels_resistance():
    """teleop.stabiliser "wave", nothing coming back (wave 0): every servo period the
    handle feels the matching drag -b r of its own rate there, and each sample carries
    the force its tick's last render sent and the mean of its renders' waves sqrt(2 b) r
    (teleop/control/wave.py: the period's wave carries what its servo periods put in)."""
    config = load_config(None, ['run.mode="lockstep"', 'teleop.stabiliser="wave"'])
    sent, clock = Sent(), FakeClock(start_ns=10 * NS_PER_S)
    device = RenderLog(config.haptic, config.haptic.render_period_s)
    loop = HapticLoop(config, device, sent, clock, lockstep=True)
    plain, plain_sent, _ = make_loop(lockstep=True)
    run_lockstep_push(loop, 600, 600, 0.0)
    run_lockstep_push(plain, 600, 600, 0.0)
    b, teleop = config.teleop.wave_impedance_n_s_m, config.teleop
    renders = config.renders_per_tick
    assert len(device.renders) == renders * len(sent.samples)
    for at_m, force_n in device.renders:
        assert np.allclose(force_n, -b * handle_rate_m_s(at_m, False, teleop))
    for k, rec in enumerate(sent.samples):
        tick_renders = device.renders[k * renders : (k + 1) * renders]
        assert np.allclose(rec["device_f_n"], tick_renders[-1][1])
        waves = [
            math.sqrt(2 * b) * handle_rate_m_s(at_m, False, teleop) for at_m, _ in tick_renders
        ]
        assert np.allclose(rec["wave_u"], np.mean(waves, axis=0))
    # The drag holds the handle back from where the plain one goes (the hand's 2 cm).
    held_back_m = plain_sent.samples[-1]["device_p_m"][0] - sent.samples[-1]["device_p_m"][0]
    assert held_back_m > 0.002
    assert np.all(plain_sent.samples[-1]["wave_u"] == 0.0)


@pytest.mark.parametrize(
    ("settings", "error"),
    [
        (["site.emulated_round_trip_ms=25"], "lockstep runs only"),
        (['run.mode="lockstep"', "site.emulated_round_trip_ms=2.5"], "whole number"),
        (['run.mode="lockstep"', "site.emulated_round_trip_ms=-1"], r"in \[0, 2000\]"),
        (['run.mode="lockstep"', 'run.operator="web"', "site.emulated_round_trip_ms=20"],
         "scripted operator only"),
    ],
)  # fmt: skip
def test_an_emulated_link_is_refused_where_it_cannot_be_emulated(settings, error):
    with pytest.raises(ConfigError, match=error):
        load_config(None, settings)


def test_lockstep_goes_on_without_an_operator_after_the_hand_wait():
    loop, sent, clock = make_loop(lockstep=True)
    lead = loop.hand_schedule.lead_ticks
    for k in range(lead + 1):
        loop.on_state(plant_state(k))
        if k >= 1:
            loop.on_feedback(feedback(k, k - 1, 0.0), 0)
    assert len(sent.samples) == lead  # tick `lead` waits for its hand input
    with loop.cond:
        assert 0 < loop.poll_hand_wait() <= STOP_POLL_S
        clock.advance(round(HAND_INPUT_WAIT_S * NS_PER_S))
        assert loop.poll_hand_wait() == 0.0  # gave up: the tick stepped
    assert len(sent.samples) == lead + 1 and loop.missing_hand_inputs == 1
    loop.on_state(plant_state(lead + 1))
    loop.on_feedback(feedback(lead + 1, lead, 0.0), 0)
    assert len(sent.samples) == lead + 2  # no more waiting


def test_lockstep_does_not_wait_for_a_hand_input_a_later_one_overtook():
    """A restarted operator's first input is for a later tick than the one the device
    waits for: that one will never come, the tick steps at once with the hand input in
    effect (its predecessor's), without the hand wait."""
    loop, sent, _ = make_loop(lockstep=True)
    lead = loop.hand_schedule.lead_ticks
    # The hand inputs' first three valid_from ticks: decisions 0, 1 and 2, a lead later.
    first, waited, later = (s + lead for s in hand_sample_ticks(loop, 100)[:3])
    target_m = np.array([0.0, 0.02, 0.0])
    for k in range(later + 1):
        loop.on_state(plant_state(k))
        if k == 0:  # the run has begun: the old operator's last input
            loop.on_hand(hand(first, target_m))
        if k >= 1:
            loop.on_feedback(feedback(k, k - 1, 0.0), 0)
    assert len(sent.samples) == waited  # tick `waited` waits for its hand input
    loop.on_hand(hand(later, -target_m))  # the new operator's first: a later tick
    assert len(sent.samples) == later + 1  # stepped through, no wait
    assert loop.missing_hand_inputs == 1


def test_a_stale_hand_input_centres_the_handle_and_keeps_the_buttons():
    """Realtime: no new hand input for haptic.hand_input_stale_s of sim ticks (the
    operator starved or restarting): the hand centres the handle, the tool holds still,
    and the gripper button stays pressed. A plant that stalls does not advance the ticks:
    wall time alone never makes the hand stale."""
    loop, sent, clock = make_loop(lockstep=False)
    stale_ticks = round(loop.config.haptic.hand_input_stale_s / loop.tick_s)
    target_m = np.array([0.03, 0.0, 0.0])
    loop.on_hand(hand(100, target_m))

    seq = iter(range(1, 10**6))

    def run(first_tick: int, ticks: int, advance_ticks: bool = True) -> np.ndarray:
        for k in range(first_tick, first_tick + ticks):
            tick = k if advance_ticks else first_tick
            rec = feedback(next(seq), tick, 0.0, tx_ns=clock.now_ns())
            loop.on_feedback(rec, clock.now_ns())
            loop.step_realtime(deadline_ns=clock.now_ns())
            clock.advance(NS_PER_MS)
        return sent.samples[-1]

    held = run(100, stale_ticks + 1)  # within the limit: the hand pulls the handle out
    assert held["device_p_m"][0] > 0.02 and loop.hand_holds == 0
    stalled = run(100 + stale_ticks, 3 * stale_ticks, advance_ticks=False)  # a frozen plant
    assert stalled["device_p_m"][0] == pytest.approx(0.03, abs=1e-3) and loop.hand_holds == 0
    centred = run(100 + stale_ticks + 1, 3 * stale_ticks)
    assert abs(centred["device_p_m"][0]) < 1e-3  # back at the centre: no rate command
    assert centred["buttons"] == Button.GRIPPER_CLOSE
    assert loop.hand_holds == 1 and loop.summary()["hand_held_steps"] == 3 * stale_ticks
    resumed_tick = 100 + 4 * stale_ticks + 1
    loop.on_hand(hand(resumed_tick, target_m))  # the operator is back
    back = run(resumed_tick, stale_ticks + 1)
    assert back["device_p_m"][0] > 0.02 and loop.hand_holds == 1


def test_realtime_renders_feedback_on_arrival_and_checks_its_order_and_age():
    loop, sent, clock = make_loop(lockstep=False)
    force_n = np.array([0.0, 0.5, 0.0])
    rec = feedback(1, 500, force_n, tx_ns=clock.now_ns())
    rec["trace_ns"][Stage.HAPTIC_SAMPLE] = clock.now_ns() - 1
    clock.advance(100_000)
    loop.on_feedback(rec, clock.now_ns())
    trace = loop.trace_log.rows[-1]
    assert trace[Stage.FEEDBACK_RX] == clock.now_ns() == trace[Stage.FEEDBACK_RENDERED]
    # The bus period that ends a period after it came renders it (the one before not).
    loop.step_realtime(deadline_ns=clock.now_ns())
    assert np.allclose(sent.samples[-1]["device_f_n"], 0.0)
    loop.step_realtime(deadline_ns=clock.now_ns() + loop.tick_ns)
    sample = sent.samples[-1]
    assert int(sample["tick"]) == 500 and int(sample["sim_time_ns"]) == 500 * TICK_NS
    assert np.allclose(sample["device_f_n"], force_n) and sample["flags"] == Flag.NONE
    # Stale after haptic.stale_feedback_s: flagged, fading.
    clock.advance(round(loop.config.haptic.stale_feedback_s * NS_PER_S) + 2 * NS_PER_MS)
    loop.step_realtime(deadline_ns=clock.now_ns())
    assert sent.samples[-1]["flags"] == Flag.STALE
    # Older than the newest: dropped; too old on arrival: shed and logged; a lower tick
    # later on: a new run.
    loop.on_feedback(feedback(1, 501, force_n, tx_ns=clock.now_ns()), clock.now_ns())
    old = feedback(2, 501, force_n, tx_ns=clock.now_ns() - 10 * loop.feedback_in.shed_age_ns)
    old["trace_ns"][Stage.HAPTIC_SAMPLE] = 42
    loop.on_feedback(old, clock.now_ns())
    loop.on_feedback(feedback(4, 7, force_n, tx_ns=clock.now_ns()), clock.now_ns())
    summary = loop.summary()
    assert summary["feedback_reordered"] == 1 and summary["feedback_shed"] == 1
    assert summary["feedback_lost"] == 1  # seq 3 never came (2 came, too late: shed)
    assert loop.feedback_in.shed_log.rows.tolist() == [[42]]
    assert summary["runs"] == 2 and summary["feedback_rendered"] == 2


def test_realtime_loop_paces_on_the_clocks_deadlines():
    loop, sent, clock = make_loop(lockstep=False, stop_after=50)
    loop.run_realtime(sent.stop)
    deadlines = np.array([int(s["device_deadline_ns"]) for s in sent.samples])
    assert len(deadlines) == 50 and np.all(np.diff(deadlines) == loop.tick_ns)
    assert loop.summary()["rate_hz"] == pytest.approx(1.0 / loop.tick_s)


# --- a second device behind the same interface ----------------------------------------


def recorded_path(n: int) -> np.ndarray:
    """A handle trajectory (n, 3), m: a slow circle in the horizontal plane."""
    angle = np.linspace(0.0, 2.0 * np.pi, n)
    return np.stack([0.02 * np.cos(angle), 0.02 * np.sin(angle), np.zeros(n)], axis=1)


@pytest.mark.parametrize("lockstep", [True, False], ids=["lockstep", "realtime"])
def test_the_loop_drives_a_replay_device_through_the_interface_alone(lockstep):
    """ReplayDevice in place of the emulator, the loop's code unchanged: its recorded
    positions come out as samples (one row per servo period, a tick's last one per
    sample), and the feedback comes out as rendered force."""
    config = load_config()
    ticks, renders, period_s = 199, config.renders_per_tick, config.haptic.render_period_s
    n = ticks * renders + 1  # the rest position, then a tick's servo periods per tick
    path_m = recorded_path(n)
    buttons = [Button.GRIPPER_CLOSE if i >= n // 2 else Button.NONE for i in range(n)]
    device = ReplayDevice(path_m, period_s, HapticConfig().peak_force_n, buttons)
    loop, sent, clock = make_loop(device, lockstep=lockstep)
    assert loop.renders_per_tick == renders
    force_n = np.array([0.0, 0.0, -1.5])
    with device:
        for k in range(ticks):
            if lockstep:
                loop.on_state(plant_state(k))
                if k == 0:  # the run started: the operator's inputs (a replay ignores them)
                    for s in hand_sample_ticks(loop, ticks):
                        loop.on_hand(hand(s + loop.hand_schedule.lead_ticks, np.full(3, 0.04)))
                if k >= 1:
                    loop.on_feedback(feedback(k, k - 1, force_n), 0)
            else:
                loop.on_feedback(feedback(k + 1, k, force_n, tx_ns=clock.now_ns()), clock.now_ns())
                loop.step_realtime(clock.now_ns())
                clock.advance(loop.tick_ns)
    assert not device.connected and device.samples_left == 0
    assert len(sent.samples) == ticks
    positions = np.array([s["device_p_m"] for s in sent.samples])
    np.testing.assert_array_equal(positions, path_m[renders::renders])  # each tick's last row
    velocities = np.array([s["device_v_m_s"] for s in sent.samples])
    last_steps_m = path_m[renders::renders] - path_m[renders - 1 : -1 : renders]
    np.testing.assert_allclose(velocities, last_steps_m / period_s)
    forces = np.array([s["device_f_n"] for s in sent.samples])
    # Lockstep: tick 0 has no feedback to render yet; realtime: a feedback is rendered
    # from the servo period after it came, in the next bus period.
    first_fed = 1
    np.testing.assert_allclose(forces[first_fed:], np.tile(force_n, (len(forces) - first_fed, 1)))
    assert [int(s["buttons"]) for s in sent.samples] == [int(b) for b in buttons[renders::renders]]
    assert loop.summary()["max_rendered_force_n"] == pytest.approx(1.5)


def test_replay_device_saturates_holds_its_last_sample_and_restarts():
    path_m = recorded_path(3)
    device = ReplayDevice(path_m, PERIOD_S, peak_force_n=8.0)
    assert isinstance(device, HapticDevice) and device.read().p_m.tolist() == path_m[0].tolist()
    device.send_force(np.array([30.0, 40.0, 0.0]))
    assert np.linalg.norm(device.next_sample(None).f_n) == pytest.approx(8.0)
    device.next_sample(None)
    last = device.next_sample(None)  # past the end: rests at the last position
    np.testing.assert_array_equal(last.p_m, path_m[-1])
    assert not last.v_m_s.any()
    device.reset()
    np.testing.assert_array_equal(device.next_sample(None).p_m, path_m[1])
    with pytest.raises(ValueError, match="p_m"):
        ReplayDevice(np.zeros((4, 2)), PERIOD_S, 8.0)


def test_replay_device_plays_a_recording_of_haptic_states():
    records = np.zeros(3, dtype=HAPTIC_STATE.dtype)
    records["device_p_m"] = recorded_path(3)
    records["buttons"] = [Button.NONE, Button.GRIPPER_CLOSE, Button.GRIPPER_CLOSE]
    device = ReplayDevice.from_haptic_states(records, PERIOD_S, peak_force_n=8.0)
    sample = device.next_sample(None)
    np.testing.assert_array_equal(sample.p_m, records["device_p_m"][1])
    assert sample.buttons == Button.GRIPPER_CLOSE


# --- several robots (run.robots): one handle, the robot it drives switched ----------------


class SentPerRobot(Sent):
    """HapticOutputs that keeps each robot's samples apart."""

    def __init__(self) -> None:
        super().__init__()
        self.by_robot: dict[int, list[np.ndarray]] = {}

    def sample(self, rec: np.ndarray, robot: int = 0) -> None:
        super().sample(rec, robot)
        self.by_robot.setdefault(robot, []).append(rec.copy())


def make_two_robot_loop() -> tuple[HapticLoop, SentPerRobot]:
    config = load_config(None, ['run.mode="lockstep"', 'run.scenario="grasp"', "run.robots=2"])
    device = EmulatedDevice(config.haptic, config.plant.timestep_s)
    sent = SentPerRobot()
    loop = HapticLoop(config, device, sent, FakeClock(start_ns=10 * NS_PER_S), lockstep=True)
    return loop, sent


def test_two_robots_step_together_and_the_idle_one_holds_a_centred_handle():
    """Tick k steps once both robots' states k and feedbacks k-1 are in; the robot the
    hand drives gets the handle, the other a centred handle with its buttons held."""
    loop, sent = make_two_robot_loop()
    lead = loop.hand_schedule.lead_ticks
    for k in range(300):
        loop.on_state(plant_state(k), 0)
        if k >= 1:
            loop.on_feedback(feedback(k, k - 1, 0.0), 0, 0)
        if k % lead == 0:
            loop.on_hand(hand(k + lead, [0.02, 0.0, 0.0]), 0)
        assert len(sent.by_robot.get(0, [])) == max(k, 0)  # robot 1's state k is missing
        loop.on_state(plant_state(k), 1)
        if k >= 1:
            assert len(sent.by_robot[0]) == k  # and its feedback of k-1
            loop.on_feedback(feedback(k, k - 1, 0.0), 0, 1)
        assert len(sent.by_robot[0]) == len(sent.by_robot[1]) == k + 1
    driven, idle = sent.by_robot[0][-1], sent.by_robot[1][-1]
    assert driven["device_p_m"][0] == pytest.approx(0.02, abs=5e-4)
    assert np.all(idle["device_p_m"] == 0.0) and np.all(idle["device_v_m_s"] == 0.0)
    assert int(idle["tick"]) == int(driven["tick"]) == 299
    assert int(idle["buttons"]) == Button.NONE  # robot 1 was never driven: nothing held
    assert loop.summary()["robot_switches"] == []


def test_the_handle_switches_robot_only_in_its_deadband():
    """A hand input on robot 1's keys moves the handle to robot 1 once the handle rests
    within the rate deadband; until then the hand still drives robot 0. Robot 0 then
    holds a centred handle with the buttons it had (the gripper stays closed)."""
    loop, sent = make_two_robot_loop()
    lead = loop.hand_schedule.lead_ticks
    switch_from = 200

    def step(k: int) -> None:
        for robot in (0, 1):
            loop.on_state(plant_state(k), robot)
            if k >= 1:
                loop.on_feedback(feedback(k, k - 1, 0.0), 0, robot)

    for k in range(600):
        if k % lead == 0:
            # Robot 0: the handle out 2 cm, gripper closed; from switch_from on the hand
            # means robot 1, the handle back at the centre.
            if k + lead < switch_from:
                loop.on_hand(hand(k + lead, [0.02, 0.0, 0.0]), 0)
            else:
                loop.on_hand(hand(k + lead, [0.0, 0.0, 0.0], Button.NONE), 1)
        step(k)
    switches = loop.summary()["robot_switches"]
    assert len(switches) == 1 and switches[0]["robot"] == 1
    switched_at = switches[0]["tick"]
    assert switched_at > switch_from  # the handle had to come back first
    assert loop.summary()["switch_deferred_steps"] == switched_at - switch_from
    for rec in sent.by_robot[0][switched_at:]:  # robot 0, no longer driven
        assert np.all(rec["device_p_m"] == 0.0)
        assert int(rec["buttons"]) == Button.GRIPPER_CLOSE
    offset_m = np.linalg.norm(sent.by_robot[0][switched_at - 1]["device_p_m"])
    assert offset_m <= loop.deadband_m
    assert np.all(sent.by_robot[1][switched_at - 1]["device_p_m"] == 0.0)  # idle before


def test_a_finished_robot_leaves_the_clock():
    """Robot 0's plant finished (its FINISHED): ticks go on with robot 1's state and
    feedback alone, and robot 0 gets no more samples."""
    loop, sent = make_two_robot_loop()
    lead = loop.hand_schedule.lead_ticks
    for k in range(100):
        for robot in (0, 1):
            loop.on_state(plant_state(k), robot)
            if k >= 1:
                loop.on_feedback(feedback(k, k - 1, 0.0), 0, robot)
        if k % lead == 0:
            loop.on_hand(hand(k + lead, [0.0, 0.0, 0.0]), 0)
    loop.on_finished(0)
    for k in range(100, 200):
        loop.on_state(plant_state(k), 1)
        loop.on_feedback(feedback(k, k - 1, 0.0), 0, 1)
        if k % lead == 0:
            loop.on_hand(hand(k + lead, [0.0, 0.0, 0.0]), 0)
    assert len(sent.by_robot[1]) == 200 and len(sent.by_robot[0]) == 100


def test_a_stale_spell_says_how_long_the_feedback_was_missing_and_how_long_it_was_felt():
    """The feedback stops after a model received at 0 (1 ms renders): stale from 20 ms,
    faded out by 40 ms; the spell ends when fresh feedback comes at 500 ms."""
    ms = 1_000_000
    hold, spells = FeedbackHold(stale_after_s=0.020, fade_s=0.020), StaleSpells()
    push = LocalContactModel.constant(np.array([0.0, 0.0, 2.0]))
    hold.receive(push, 0)
    handle = np.zeros(3)
    for t in range(0, 501 * ms, ms):
        if t == 500 * ms:
            hold.receive(push, t)  # the link back
        model, stale, received = hold.model_at(t)
        spells.render(t, stale, received, float(np.linalg.norm(model.force_at(handle))))
    assert spells.count == 1 and not spells.open
    [spell] = spells.summary()["spells"]
    assert spell["missing_ms"] == pytest.approx(499.0)
    assert 20.0 < spell["felt_ms"] < 40.0  # faded out after 20 ms, not held
    assert spells.felt_max_ms == spell["felt_ms"]
