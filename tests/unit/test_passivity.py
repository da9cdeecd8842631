"""Time-domain passivity at the haptic device (teleop.devices.haptic.passivity): the energy
account, the controller's damping, then the emulated handle (teleop.devices.haptic.device)
pushed by the hand into a wall rendered 100 ms late."""

from __future__ import annotations

import collections

import numpy as np
import pytest

from teleop.core.config import ConfigError, load_config
from teleop.devices.haptic.device import EmulatedDevice, HandInput
from teleop.devices.haptic.passivity import PassivityControl, max_stable_damping_n_s_m

DT_S = 0.001
X = np.array([1.0, 0.0, 0.0])


def test_the_observer_splits_the_energy_into_what_went_in_and_what_came_out():
    pc = PassivityControl(False, 20.0, DT_S)
    pc.observe(2.0 * X, -0.5 * X)  # the hand pushes against the force: 1 W into it
    pc.observe(2.0 * X, 0.25 * X)  # the force pushes the hand along: 0.5 W out
    assert pc.energy_in_j == pytest.approx(1e-3) and pc.energy_out_j == pytest.approx(5e-4)
    assert pc.observed_j == pytest.approx(5e-4)
    pc.observe(2.0 * X, 1.0 * X)  # 2 W out: more than ever went in
    assert pc.observed_j == pytest.approx(-1.5e-3) and pc.observer_min_j == pytest.approx(-1.5e-3)
    assert pc.summary("none")["energy_out_j"] == pytest.approx(2.5e-3)
    pc.reset()
    assert pc.observed_j == pc.energy_in_j == pc.observer_min_j == 0.0


def test_without_the_controller_the_force_is_rendered_as_it_comes():
    pc = PassivityControl(False, 20.0, DT_S)
    pc.observe(np.zeros(3), 1.0 * X)
    force = 5.0 * X
    assert pc.control(force) is force
    assert pc.active_steps == 0


def test_the_controller_damps_only_what_would_give_energy_out():
    pc = PassivityControl(True, 20.0, DT_S)
    pc.observe(-1.0 * X, 0.1 * X)  # 0.1 mJ absorbed: W = 1e-4 J
    opposing = -3.0 * X  # against the motion: absorbs, untouched
    assert pc.control(opposing) is opposing
    along = 3.0 * X  # along the motion: would give 0.3 mJ out, 0.1 mJ is in store
    out = pc.control(along)
    assert float(np.dot(out, X)) == pytest.approx(1.0)  # exactly the energy in store
    assert pc.active_steps == 1 and pc.dissipated_j == pytest.approx(2e-4)
    pc.observe(out, 0.1 * X)
    assert pc.observed_j == pytest.approx(0.0, abs=1e-12)  # never below zero


def test_damping_beyond_the_force_is_capped_at_what_the_handle_renders_stably():
    pc = PassivityControl(True, 20.0, DT_S)
    pc.observe(50.0 * X, 1.0 * X)  # W = -50 mJ: would take 50 N s/m to restore at once
    out = pc.control(np.zeros(3))
    assert float(np.dot(out, X)) == pytest.approx(-20.0 * 1.0)  # the cap, times v
    assert max_stable_damping_n_s_m(0.15, DT_S) == pytest.approx(300.0)


def test_the_stabiliser_is_one_of_the_known():
    assert load_config(None, ['teleop.stabiliser="tdpa"']).teleop.stabiliser == "tdpa"
    with pytest.raises(ConfigError, match="teleop.stabiliser: one of none, tdpa, wave"):
        load_config(None, ['teleop.stabiliser="lqr"'])


def press_into_a_late_wall(enabled: bool, delay_s: float = 0.1, stiffness_n_m: float = 600.0):
    """The emulated handle, the hand pulling it 2 cm into a wall at the centre whose
    force comes back ``delay_s`` late (a round trip: the position goes out, the force
    comes back), for 6 s; the controller and the handle's positions (m)."""
    config = load_config()
    device = EmulatedDevice(config.haptic, DT_S)
    pc = PassivityControl(enabled, config.teleop.tdpa_max_damping_n_s_m, DT_S)
    in_flight = collections.deque([0.0] * round(delay_s / DT_S))
    hand = HandInput(np.array([0.02, 0.0, 0.0]))
    positions = []
    for _ in range(6000):
        remote_x = in_flight.popleft()
        wall_n = -stiffness_n_m * remote_x if remote_x > 0 else 0.0
        device.send_force(pc.control(wall_n * X))
        sample = device.next_sample(hand)
        pc.observe(sample.f_n, sample.v_m_s)
        in_flight.append(float(sample.p_m[0]))
        positions.append(float(sample.p_m[0]))
    return pc, np.array(positions)


@pytest.mark.parametrize("delay_s", [0.05, 0.1, 0.2])
def test_a_wall_felt_late_oscillates_and_gives_energy_out_unless_the_controller_damps_it(
    delay_s,
):
    """Round trips of 50-200 ms against a 600 N/m wall: rendered as it comes, the handle
    rattles against it for good (centimetres, the observer at joules below zero: the
    delayed wall pushes the hand); with tdpa the observer stays at zero (within the one
    period the controller acts late) and the handle settles on the wall."""
    free, free_x = press_into_a_late_wall(False, delay_s)
    damped, damped_x = press_into_a_late_wall(True, delay_s)
    last_s = slice(-1000, None)
    assert free.observer_min_j < -1.0
    assert np.ptp(free_x[last_s]) > 0.01  # still oscillating after 5 s
    assert damped.observer_min_j > -0.01
    assert np.ptp(damped_x[last_s]) < 0.001
    assert damped.dissipated_j > 0 and damped.active_steps > 0
    print(f"{delay_s * 1e3:.0f} ms: observer min {free.observer_min_j:.3g} J, last second "
          f"{np.ptp(free_x[last_s]) * 1e3:.1f} mm (none); {damped.observer_min_j:.3g} J, "
          f"{np.ptp(damped_x[last_s]) * 1e3:.2f} mm (tdpa)")  # fmt: skip


def test_the_controller_takes_a_push_out_on_its_own_axis_only():
    """A push along z on a handle moving up, its velocity estimate noisy across: the
    controller takes the push out of z and puts nothing into x or y (a damper along the
    whole noisy velocity would move it sideways: 3-4 N seen on the whole stack)."""
    pc = PassivityControl(True, 20.0, DT_S)
    v_m_s = np.array([0.02, -0.01, 0.03])
    pc.observe(np.zeros(3), v_m_s)
    push_n = np.array([0.0, 0.0, 8.0])  # along the motion: energy out
    rendered = pc.control(push_n)
    assert rendered[0] == 0.0 and rendered[1] == 0.0
    assert rendered[2] == pytest.approx(0.0, abs=1e-12)
    pc.observe(rendered, v_m_s)
    assert pc.observed_j == 0.0 and pc.observer_min_j == 0.0
    # A push against the motion is passive: rendered unchanged.
    assert np.array_equal(pc.control(-push_n), -push_n)
