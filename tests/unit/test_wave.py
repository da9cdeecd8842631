"""Wave variables (teleop.control.wave): the transforms, the channel's passivity under
delay, and a rate-controlled stiff contact across a round trip, on the emulated handle."""

from __future__ import annotations

import collections

import numpy as np
import pytest

from teleop.control.wave import (
    RobotWavePort,
    WaveEnergyBank,
    handle_rate_m_s,
    handle_resistance_n,
    handle_wave,
)
from teleop.core.config import load_config
from teleop.devices.haptic.device import EmulatedDevice, HandInput, saturate_force
from teleop.devices.haptic.passivity import PassivityControl

DT_S = 0.001
B = 10.0  # N s/m, the default teleop.wave_impedance_n_s_m


def test_the_waves_carry_the_power_each_side_puts_in():
    """r e = (u^2 - v^2) / 2 on both sides, axis by axis (the robot's e with its matching
    damper b r)."""
    rng = np.random.default_rng(0)
    port = RobotWavePort(B, DT_S, 0.02)
    for i in range(100):
        rate, v = rng.normal(0, 0.1, 3), rng.normal(0, 1.0, 3)
        u = handle_wave(rate, v, B)
        e = handle_resistance_n(rate, v, B)
        assert np.allclose(rate * e, (u * u - v * v) / 2)
        port.resist(rng.normal(0, 3.0, 3))
        robot_rate = port.rate(u, i * DT_S)
        back = port.wave_back()
        matched_n = port.resistance_n + B * robot_rate
        assert np.allclose(robot_rate * matched_n, (u * u - back * back) / 2)


def test_in_free_motion_the_robot_takes_the_handles_rate_and_the_handle_feels_nothing():
    """Through a 100-tick delay each way, nothing resisting: one trip after the handle
    set its rate the robot moves at it, and the handle feels the matching damper b r,
    nothing more (no wave comes back from free motion)."""
    delay = 100
    forward = collections.deque([np.zeros(3)] * delay)
    back = collections.deque([np.zeros(3)] * delay)
    port = RobotWavePort(B, DT_S, 0.02)
    rate = np.array([0.05, 0.0, -0.02])
    resistance = []
    for i in range(6 * delay):
        v = back.popleft()
        resistance.append(handle_resistance_n(rate, v, B))
        forward.append(handle_wave(rate, v, B))
        port.resist(np.zeros(3))
        robot_rate = port.rate(forward.popleft(), i * DT_S)
        back.append(port.wave_back())
    assert np.allclose(robot_rate, rate)
    assert np.allclose(np.array(resistance), B * rate)


def test_the_channel_gives_back_no_energy_it_was_not_given_whatever_the_delay():
    """Any rate at the handle, any resistance at the robot, 150 ticks each way: the
    energy put in at the handle minus what came out at the robot (its resistance with
    the matching damper) never falls below zero: it is in flight."""
    rng = np.random.default_rng(1)
    delay = 150
    forward = collections.deque([np.zeros(3)] * delay)
    back = collections.deque([np.zeros(3)] * delay)
    port = RobotWavePort(B, DT_S, 0.02)
    handle_in_j, robot_out_j, least_j = 0.0, 0.0, 0.0
    for i in range(5000):
        rate = rng.normal(0, 0.1, 3)
        v = back.popleft()
        handle_in_j += float(rate @ handle_resistance_n(rate, v, B)) * DT_S
        forward.append(handle_wave(rate, v, B))
        port.resist(rng.normal(0, 4.0, 3))
        robot_rate = port.rate(forward.popleft(), i * DT_S)
        robot_out_j += float(robot_rate @ (port.resistance_n + B * robot_rate)) * DT_S
        back.append(port.wave_back())
        least_j = min(least_j, handle_in_j - robot_out_j)
    assert least_j >= -1e-9


def jittered_deliveries(rng: np.random.Generator, samples: int, period: int, jitter: int):
    """Ticks at which samples sent every ``period`` ticks arrive over a link whose delay
    varies by up to ``jitter`` ticks (in order: a late one holds back the next)."""
    ticks, newest = [], 0
    for k in range(samples):
        newest = max(newest, k * period + int(rng.integers(0, jitter + 1)))
        ticks.append(newest)
    return ticks


def replay_at_the_receiver(waves, arrivals, period, bank: WaveEnergyBank | None):
    """Each tick the newest wave that arrived is passed on (held), through ``bank`` or
    as it is; returns (energy passed on, energy that had arrived) after each tick (J)."""
    held, passed_j, arrived_j, out = np.zeros(3), 0.0, 0.0, []
    nxt = 0
    for tick in range(arrivals[-1] + period):
        while nxt < len(arrivals) and arrivals[nxt] <= tick:
            held = waves[nxt]
            arrived_j += 0.5 * float(held @ held) * period * DT_S
            if bank is not None:
                bank.receive(held)
            nxt += 1
        passed = bank.pass_on(held, DT_S) if bank is not None else held
        passed_j += 0.5 * float(passed @ passed) * DT_S
        out.append((passed_j, arrived_j))
    return np.array(out)


def test_a_varying_delay_gives_out_energy_unless_the_receiver_banks_the_waves():
    """Waves sent every 4 ms over a link whose delay varies by up to 6 ms: held as they
    come, a late wave is passed on longer than it was sent for and the receiver gives
    out more than arrived; through a :class:`WaveEnergyBank` never more. Under a
    constant delay the bank passes every wave on whole."""
    rng = np.random.default_rng(2)
    period, samples = 4, 3000
    waves = [rng.normal(0, 1.0, 3) * rng.choice([0.1, 3.0]) for _ in range(samples)]
    jittered = jittered_deliveries(rng, samples, period, jitter=6)
    plain = replay_at_the_receiver(waves, jittered, period, None)
    assert np.max(plain[:, 0] - plain[:, 1]) > 0.01
    bank = WaveEnergyBank(period * DT_S)
    banked = replay_at_the_receiver(waves, jittered, period, bank)
    assert np.all(banked[:, 0] <= banked[:, 1] * (1 + 1e-9))
    assert bank.scaled_passes > 0 and bank.withheld_j > 0
    steady = WaveEnergyBank(period * DT_S)
    constant = [k * period + 3 for k in range(samples)]
    in_step = replay_at_the_receiver(waves, constant, period, steady)
    assert steady.scaled_passes == 0
    assert in_step[-1, 0] == pytest.approx(in_step[-1, 1], rel=1e-9)


def test_the_robot_end_spends_a_wave_for_as_long_as_it_was_in_force():
    """A handle's wave that the next one follows late was in force longer than it brought
    energy for: the robot's end passes the next one on scaled down (the debt), and a
    silence longer than the plant's hold costs no more than the hold."""
    port = RobotWavePort(B, 0.004, 0.02)
    u = np.array([1.0, 0.0, 0.0])
    port.resist(np.zeros(3))
    assert port.rate(u, 0.0) == pytest.approx(u * np.sqrt(2 * B) / (2 * B))
    assert port.rate(u, 0.004)[0] == pytest.approx(port.rate_m_s[0])
    assert port.bank.scaled_passes == 0
    late = port.rate(u, 0.004 + 0.010)  # held 10 ms on 4 ms of energy: 6 ms owed
    assert late[0] == 0.0 and port.bank.scaled_passes == 1
    port.reset()
    port.rate(u, 0.0)
    port.rate(u, 5.0)  # the hold ends at the plant's watchdog, not 5 s later
    # two waves brought 4 ms each, the first was in force for 20 ms (the hold): owed
    assert port.bank.banked_j == pytest.approx(2 * 0.5 * 0.004 - 0.5 * 0.020)


def test_the_handles_rate_is_the_rate_controls():
    cfg = load_config().teleop
    assert np.all(handle_rate_m_s(np.array([0.003, 0.0, 0.0]), False, cfg) == 0.0)  # deadband
    rate = handle_rate_m_s(np.array([0.0, 0.014, 0.0]), False, cfg)
    assert rate == pytest.approx([0.0, cfg.rate_gain_per_s * 0.010, 0.0])
    assert np.all(handle_rate_m_s(np.array([0.0, 0.014, 0.0]), True, cfg) == 0.0)  # clutch
    assert np.linalg.norm(handle_rate_m_s(np.array([0.0, 0.0, 0.5]), False, cfg)) == (
        pytest.approx(cfg.max_tool_speed_m_s)
    )


class UndampedPort(RobotWavePort):
    """The robot's end without its passivity controller."""

    MAX_DAMPING_PER_B = 0.0


def push_on_a_late_stiff_wall(
    wave: bool,
    round_trip_ticks: int = 200,
    k_n_per_m: float = 750.0,
    bus_ticks: int = 1,
    wall_lag_ticks: int = 0,
    port_class: type[RobotWavePort] = RobotWavePort,
):
    """The emulated handle in rate control, the hand holding it 1.5 cm down, the tool
    moving at its rate onto a wall 1 cm below where it starts, whose spring (``k`` per m
    of the tool's intrusion, N at the handle) comes back a round trip late: plain, or
    as wave variables. The handle renders every tick (1 ms); the robot's side takes the
    newest of what came and answers every ``bus_ticks``, and its wall pushes back on
    where the tool was ``wall_lag_ticks`` before (a plant a bus period or two behind).
    8 s; the handle's heights (m), the passivity observer and the robot's port."""
    config = load_config()
    device = EmulatedDevice(config.haptic, DT_S)
    observer = PassivityControl(False, 0.0, DT_S)
    half = round_trip_ticks // 2
    forward = collections.deque([np.zeros(3)] * half)  # the handle's rate, or its wave
    back = collections.deque([np.zeros(3)] * half)  # the spring's force, or its wave
    port = port_class(B, bus_ticks * DT_S, 0.02)
    hand = HandInput(np.array([0.0, 0.0, -0.015]))
    tool_z_m, sample = 0.01, device.next_sample(hand)
    past_z_m = collections.deque([tool_z_m] * (wall_lag_ticks + 1), maxlen=wall_lag_ticks + 1)
    heights = []
    tool_rate, answer = np.zeros(3), np.zeros(3)
    for i in range(8000):
        rate = handle_rate_m_s(sample.p_m, False, config.teleop)
        received = back.popleft()
        if wave:
            force = -handle_resistance_n(rate, received, B)
            forward.append(handle_wave(rate, received, B))
        else:
            force = received
            forward.append(rate)
        device.send_force(saturate_force(force, config.haptic.peak_force_n))
        sample = device.next_sample(hand)
        observer.observe(sample.f_n, sample.v_m_s)
        heights.append(float(sample.p_m[2]))
        # The robot's side: the tool moves at the rate it takes, the wall pushes back.
        came = forward.popleft()
        if i % bus_ticks == 0:
            spring_n = np.array([0.0, 0.0, k_n_per_m * max(0.0, -past_z_m[0])])
            if wave:
                port.resist(-spring_n)
                tool_rate = port.rate(came, i * DT_S)
                answer = port.wave_back()
            else:
                tool_rate, answer = came, spring_n
        back.append(answer)
        tool_z_m += float(tool_rate[2]) * DT_S
        past_z_m.append(tool_z_m)
    return np.array(heights), observer, port


def test_a_stiff_contact_across_a_round_trip_rattles_plain_and_settles_as_waves():
    """200 ms round trip, a wall of 750 N/m per m of the tool (the e2e test's contact):
    the plain channel rattles on for good and gives the hand joules out; the waves
    settle on the wall. The handle's observer may still dip in the transient: in rate
    control the channel's port at the handle is its rate, set by the handle's position,
    not the handle's velocity, so the waves keep the channel passive, not that port
    (measured: 1.43 J out plain, 12 mJ as waves)."""
    plain, plain_observer, _ = push_on_a_late_stiff_wall(wave=False)
    waves, wave_observer, _ = push_on_a_late_stiff_wall(wave=True)
    last_s = slice(-1000, None)
    assert np.ptp(plain[last_s]) > 0.005
    assert plain_observer.observer_min_j < -0.05
    assert np.ptp(waves[last_s]) < 0.0005
    assert wave_observer.observer_min_j > -0.05
    print(
        f"plain: last second {np.ptp(plain[last_s]) * 1e3:.1f} mm, observer min "
        f"{plain_observer.observer_min_j:.3g} J; waves: {np.ptp(waves[last_s]) * 1e3:.3f} mm, "
        f"{wave_observer.observer_min_j:.3g} J"
    )


def test_a_stiff_wall_that_lags_the_bus_period_is_held_passive_by_the_robots_port():
    """The robot answering every 4 ms (the bus period) on a 1500 N/m wall that pushes
    back on where the tool was two periods before, 100 ms round trip: the lag makes the
    wall give back more than it took (a negative damper of about k t, beyond the
    matching b), and without its passivity controller the robot's end sends that back
    through the channel: the handle rattles. With it, the series damper dissipates what
    the wall gave out and the handle settles; the port's books nearly balance (what is
    left owing at the end is what a tool at rest on the wall cannot dissipate: under a
    millijoule, against the joules the bare port gives out)."""
    lagging = dict(round_trip_ticks=100, k_n_per_m=1500.0, bus_ticks=4, wall_lag_ticks=8)
    bare, bare_observer, _ = push_on_a_late_stiff_wall(True, port_class=UndampedPort, **lagging)
    held, held_observer, port = push_on_a_late_stiff_wall(True, **lagging)
    last_s = slice(-1000, None)
    print(
        f"undamped: last second {np.ptp(bare[last_s]) * 1e3:.2f} mm, observer min "
        f"{bare_observer.observer_min_j:.3g} J; with the controller: "
        f"{np.ptp(held[last_s]) * 1e3:.3f} mm, {held_observer.observer_min_j:.3g} J, "
        f"{port.summary()}"
    )
    assert np.ptp(bare[last_s]) > 0.002 and bare_observer.observer_min_j < -0.1
    assert np.ptp(held[last_s]) < 0.0005 and held_observer.observer_min_j > -0.05
    assert port.damped_cycles > 0
    assert port.absorbed_j + port.dissipated_j > -0.001
