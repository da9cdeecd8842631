"""The plant's protective stop (teleop.sim.protective): the bookkeeping alone, then the
MuJoCo plant pressed into the table by the teleoperation controller, then the step
core's events and summary."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from teleop.bus.messages import Event, Flag
from teleop.core.clock import FakeClock
from teleop.core.config import Config, ConfigError, load_config
from teleop.sim.protective import ProtectiveStop, StopCause, allowed_approach_m_s
from teleop.sim.stepping import PlantStepCore
from tests.unit.test_feedback import GraspRig
from tests.unit.test_stepping import Recorded, command

LIMIT_N, SPEED_STOP_M_S, RELEASE_M_S = 8.0, 0.33, 0.01
# The press: straight down onto the table, slowly (m/s), as a person leaning on the handle.
PRESS_SPEED_M_S = 0.03


def test_trips_on_either_limit_holds_while_commanded_and_releases_on_still_commands():
    stop = ProtectiveStop(LIMIT_N, SPEED_STOP_M_S, RELEASE_M_S, release_steps=2)
    assert not stop.measure(1, LIMIT_N, SPEED_STOP_M_S)  # at the limits: not beyond
    assert not stop.holds(2, 0.2)  # nothing tripped: commands go through
    assert stop.measure(2, LIMIT_N + 0.1, 0.0)
    assert stop.latched and not stop.measure(3, 100.0, 1.0)  # latched: no second trip
    assert stop.holds(3, 0.2) and stop.holds(4, RELEASE_M_S + 1e-6)  # still pushing
    stop.held()  # a watchdog brake meanwhile counts as held too
    assert stop.holds(6, RELEASE_M_S)  # still: one command in a row, not yet two
    assert stop.holds(7, 0.2)  # moving again: the count starts over
    assert stop.holds(8, 0.0)
    assert not stop.holds(9, RELEASE_M_S)  # two still commands in a row: released
    assert not stop.latched
    assert stop.measure(10, 0.0, SPEED_STOP_M_S + 0.01)  # then too fast
    transitions = [(t.stop.cause, t.released) for t in stop.take_transitions()]
    assert transitions == [
        (StopCause.CONTACT_FORCE, False),
        (StopCause.CONTACT_FORCE, True),
        (StopCause.TOOL_SPEED, False),
    ]
    assert stop.take_transitions() == []
    summary = stop.summary(0.001)
    assert (summary["count"], summary["steps_held"]) == (2, 6)
    assert summary["stops"][0] == {
        "cause": "contact_force", "t_s": 0.002, "measured": LIMIT_N + 0.1,
        "released_t_s": 0.009, "steps_held": 6,
    }  # fmt: skip
    assert summary["stops"][1]["cause"] == "tool_speed"
    assert summary["stops"][1]["released_t_s"] is None


def test_the_stop_speed_must_lie_above_the_command_limit():
    with pytest.raises(ConfigError, match="tool_speed_stop_m_s > plant.tool_speed_limit"):
        load_config(None, ["plant.tool_speed_stop_m_s=0.2"])
    with pytest.raises(ConfigError, match="contact_force_limit_n > 0"):
        load_config(None, ["plant.contact_force_limit_n=0"])


def ticks(config: Config, seconds: float) -> int:
    """The plant ticks (bus periods, one controller cycle each) in ``seconds``."""
    return round(seconds / config.tick_s)


def physics_steps(config: Config, seconds: float) -> int:
    """The plant's physics steps (what the protective stop counts) in ``seconds``."""
    return round(seconds / config.plant.timestep_s)


def press(rig: GraspRig, steps: int, speed_m_s: float = PRESS_SPEED_M_S) -> list[float]:
    """The handle held down: ``steps`` ticks commanding the tool down at ``speed_m_s``;
    the largest net contact force over each tick's physics steps (N)."""
    forces = []
    for _ in range(steps):
        sample = rig.plant.sample()
        v_ref = np.array([0.0, 0.0, -speed_m_s])
        out = rig.ctl.update(sample.q_rad, sample.qd_rad_s, v_ref, None, 1.0)
        rig.plant.step(out.qd_ref_rad_s, out.gripper_cmd)
        forces.append(rig.plant.tick_peak_contact_force_n)
    return forces


def above_the_table(config) -> GraspRig:
    """The open gripper moved above a free spot of the table (away from the cube and the
    bin), 10 cm up."""
    rig = GraspRig(config)
    above = rig.plant.tool_pose()[0] + [0.0, -0.15, 0.0]
    above[2] = 0.10
    rig.move(above, 1.0, ticks(config, 2.5))
    assert rig.plant.contact_force_n.tolist() == [0.0, 0.0, 0.0]
    return rig


@pytest.fixture(scope="module")
def pressed():
    """The gripper above the table pressed down onto it until well after the stop; the
    rig, the forces of the press, and what the stop judged: (physics step, scene force)
    as the plant measured it after each."""
    config = load_config()
    rig = above_the_table(config)
    judged: list[tuple[int, float]] = []
    measure = rig.plant.protective.measure

    def judging(step: int, contact_force_n: float, tool_speed_m_s: float) -> bool:
        judged.append((step, contact_force_n))
        return measure(step, contact_force_n, tool_speed_m_s)

    rig.plant.protective.measure = judging
    forces = press(rig, ticks(config, 0.15 / PRESS_SPEED_M_S))  # 15 cm: far into the table
    rig.plant.protective.measure = measure
    return rig, forces, judged


def test_pressed_into_the_table_the_plant_stops_and_holds_while_pushed(pressed):
    rig, forces, judged = pressed
    config = load_config()
    stops = rig.plant.protective.stops
    assert [s.cause for s in stops] == [StopCause.CONTACT_FORCE]  # one stop, on force
    tripped = stops[0].step  # a physics step
    # Judged after every physics step of the press's ticks, and tripped by the first
    # beyond the limit (not at the end of its tick).
    steps = [step for step, _ in judged]
    assert steps == list(range(steps[0], steps[0] + len(forces) * config.physics_steps_per_tick))
    assert tripped == next(step for step, force_n in judged if force_n > LIMIT_N)
    assert max(forces) <= 1.1 * LIMIT_N  # the approach limit makes it a touch, not an impact
    assert forces[-1] > 0  # still touching, still reported (the operator feels it)
    assert rig.plant.protective.latched and rig.plant.braking  # the handle still pushes
    # Held: the tool no longer goes down, the force settles below the limit.
    z_held = rig.plant.tool_pose()[0][2]
    after = press(rig, ticks(config, 0.2))
    assert rig.plant.tool_pose()[0][2] == pytest.approx(z_held, abs=1e-4)
    assert max(after) < config.plant.contact_force_limit_n
    # Held on every physics step since it tripped (0.2 s of them at least).
    held_min = physics_steps(config, 0.2)
    assert stops[0].steps_held > held_min and rig.plant.physics_steps - tripped > held_min
    assert stops[0].steps_held == rig.plant.physics_steps - tripped
    # Unguarded (no stop, no approach limit), the same press goes on pushing: tens of
    # newtons.
    free_config = replace_limits(config, contact_force_limit_n=1e9, approach_time_s=0.0)
    free = press(above_the_table(free_config), len(forces))
    assert max(free[-ticks(config, 0.2) :]) > 3 * config.plant.contact_force_limit_n


@pytest.mark.parametrize("approach_limit", [True, False], ids=["approach-limit", "none"])
def test_a_fast_press_meets_the_table_slowly_enough_for_the_force_limit(approach_limit):
    """Straight down at the tool's speed limit: with the approach limit the gripper
    meets the table at plant.approach_touch_m_s and the force stays within the limit's
    10 %; without it the impact alone is tens of times the limit."""
    config = load_config()
    if not approach_limit:
        config = replace_limits(config, approach_time_s=0.0)
    rig = above_the_table(config)
    forces = press(rig, ticks(config, 1.5), speed_m_s=config.plant.tool_speed_limit_m_s)
    assert forces[-1] > 0  # it reached the table
    if approach_limit:
        assert max(forces) <= 1.1 * LIMIT_N
        assert rig.plant.approach_slowed_steps > 0
    else:
        assert max(forces) > 10 * LIMIT_N
        assert rig.plant.approach_slowed_steps == 0


def test_the_allowed_approach_speed_falls_with_the_separation_to_the_touch_speed():
    assert allowed_approach_m_s(0.0, 0.004, 0.1) == 0.004
    assert allowed_approach_m_s(-0.001, 0.004, 0.1) == 0.004  # touching: no faster
    assert allowed_approach_m_s(0.01, 0.004, 0.1) == pytest.approx(0.104)
    assert allowed_approach_m_s(0.03, 0.004, 0.1) > 0.30  # the whole range: not slowed


def test_a_command_that_stops_releases_the_stop(pressed):
    rig, _, _ = pressed
    assert rig.plant.protective.latched
    rig.ctl.reset()  # the handle let go: no motion asked for
    for _ in range(ticks(load_config(), 0.06)):
        sample = rig.plant.sample()
        out = rig.ctl.update(sample.q_rad, sample.qd_rad_s, np.zeros(3), None, 1.0)
        rig.plant.step(out.qd_ref_rad_s, out.gripper_cmd)
    assert not rig.plant.protective.latched and not rig.plant.braking
    assert rig.plant.protective.stops[0].released_step is not None


def replace_limits(config, **limits):
    return replace(config, plant=replace(config.plant, **limits))


def test_the_core_announces_each_stop_and_lists_it_in_the_summary():
    config = load_config(None, ['run.mode="realtime"'])
    outputs, clock = Recorded(), FakeClock(start_ns=10**12)
    core = PlantStepCore(config, outputs, clock)
    core.begin_run(None)
    core.publish_state()
    # Tripped through the bookkeeping the plant feeds after a step (a tool this fast).
    core.plant.protective.measure(core.plant.physics_steps, 0.0, 1.0)
    period_ns, per_tick = core.period_ns, config.physics_steps_per_tick
    for seq in range(1, 4):
        clock.advance(period_ns)
        core.step(command(seq, core.state_seq, clock.now_ns(), qd=0.5), clock.now_ns())
    assert Event.PROTECTIVE_STOP in outputs.events()
    assert int(outputs.records["plant_state"][-1]["flags"]) & Flag.BRAKING
    # Commands that ask for no motion (the drives' references that hold the arm against
    # gravity: Plant.limit counts the motion beyond them), plant.protective_release_s
    # of them in a row (physics steps: the ticks that hold them): the last releases it.
    plant = core.plant
    release_steps = round(config.plant.protective_release_s / config.plant.timestep_s)
    release_ticks = -(-release_steps // per_tick)
    for seq in range(4, 4 + release_ticks):
        still = command(seq, core.state_seq, clock.now_ns() + period_ns)
        still["qd_ref_rad_s"][:6] = plant.data.qfrc_bias[plant.dof_index] / plant.kv
        clock.advance(period_ns)
        assert outputs.events()[-1] is Event.PROTECTIVE_STOP  # not yet released
        core.step(still, clock.now_ns())
    assert outputs.events()[-1] is Event.PROTECTIVE_RELEASE
    assert not int(outputs.records["plant_state"][-1]["flags"]) & Flag.BRAKING
    summary = core.plant.protective.summary(config.plant.timestep_s)
    assert summary["count"] == 1 and summary["stops"][0]["cause"] == "tool_speed"
    # Every physics step of the 3 ticks pushing, and of the still ones before the last.
    assert summary["stops"][0]["steps_held"] == 3 * per_tick + release_steps - 1


def test_a_held_cube_braked_hard_is_no_press_on_the_scene():
    """The cube in hand, carried at speed and then braked: its inertia pulls on the
    fingers well past the limit, but that is no contact with the scene: no stop."""
    config = load_config()
    rig = GraspRig(config)
    rig.move(rig.cube_p + [0.0, 0.0, 0.12], 1.0, ticks(config, 1.5))  # above, open
    rig.move(rig.cube_p.copy(), 1.0, ticks(config, 1.0))  # around it
    rig.move(rig.cube_p.copy(), 0.0, ticks(config, 0.5))  # closed on it
    assert rig.held() == rig.cube
    total_n = []
    # Carried off at the speed limit.
    rig.move(rig.cube_p + [0.0, -0.3, 0.15], 0.0, ticks(config, 0.6))
    for _ in range(ticks(config, 0.3)):
        rig.plant.step_braking()  # a hard stop (as the watchdog's)
        total_n.append(rig.plant.tick_peak_contact_force_n)
    assert max(total_n) > config.plant.contact_force_limit_n  # the cube's inertia
    assert rig.plant.protective.stops == [] and rig.held() == rig.cube
