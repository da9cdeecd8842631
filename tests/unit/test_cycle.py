"""The controller's cycles without a bus: records in, records out, on a fake clock."""

from __future__ import annotations

import numpy as np
import pytest

from teleop.bus.messages import HAPTIC_STATE, PLANT_STATE, Stage
from teleop.control.cycle import BilateralCycle, PathCycle
from teleop.control.kinematics import build_arm_model
from teleop.core.clock import FakeClock
from teleop.core.config import load_config


class Sent:
    """ControllerOutputs that keep a copy of every record, by stream, in order."""

    def __init__(self) -> None:
        self.log: list[tuple[str, np.ndarray]] = []

    def put(self, stream: str, rec: np.ndarray) -> None:
        self.log.append((stream, rec.copy()))

    def streams(self) -> list[str]:
        return [stream for stream, _ in self.log]

    def last(self, stream: str) -> np.ndarray:
        return [rec for s, rec in self.log if s == stream][-1]


def make(cycle_class, *overrides: str):
    config = load_config(None, overrides)
    arm = build_arm_model(config.robot)
    sent, clock = Sent(), FakeClock(start_ns=10**12)
    return cycle_class(config, arm, sent, clock), sent, clock, config


def state(config, seq: int, now_ns: int, start_ns: int = 1) -> np.ndarray:
    rec = PLANT_STATE.new()
    n = len(config.robot.arm_joints)
    rec["seq"] = seq
    rec["step"] = seq
    rec["n_joints"] = n
    rec["q_rad"][:n] = config.robot.home_q_rad
    rec["sim_time_ns"] = seq * 1_000_000
    rec["t_source_ns"] = start_ns if seq == 0 else now_ns
    rec["obstacle_geom"] = -1
    rec["trace_ns"][Stage.PLANT_STATE_TX] = now_ns
    return rec


def handle(seq: int, tick: int, now_ns: int, device_p_m=(0.03, 0.0, 0.0)) -> np.ndarray:
    rec = HAPTIC_STATE.new()
    rec["seq"] = seq
    rec["tick"] = tick
    rec["device_p_m"] = device_p_m
    rec["device_deadline_ns"] = now_ns
    rec["trace_ns"][Stage.HAPTIC_SAMPLE] = now_ns
    return rec


def test_lockstep_cycle_sends_feedback_then_a_command_that_moves_the_tool():
    cycle, sent, clock, config = make(BilateralCycle, 'run.mode="lockstep"', 'run.scenario="grasp"')
    cycle.on_state(state(config, 0, clock.now_ns()), clock.now_ns())
    assert sent.log == []  # the tick waits for its handle sample
    cycle.on_haptic(handle(1, 0, clock.now_ns()), clock.now_ns())
    assert sent.streams()[:2] == ["force_feedback", "joint_command"]
    command = sent.last("joint_command")
    assert command["state_seq"] == 0 and command["seq"] == 1
    assert np.abs(command["qd_ref_rad_s"]).max() > 0  # the handle's offset asks for motion
    feedback = sent.last("force_feedback")
    assert feedback["tick"] == 0 and np.isfinite(feedback["device_f_n"]).all()
    summary = cycle.summary()
    assert (summary["cycles"], summary["runs"], summary["no_input_cycles"]) == (1, 1, 0)


def test_a_silent_handle_gives_no_motion_and_counts_as_no_input():
    cycle, sent, clock, config = make(BilateralCycle, 'run.mode="realtime"', 'run.scenario="grasp"')
    now = clock.now_ns()
    cycle.on_state(state(config, 0, now), now)  # no handle yet: feedback without input
    assert sent.streams() == ["force_feedback"] and cycle.no_input_cycles == 1
    late_tick = cycle.stale_ticks + 1
    cycle.on_haptic(handle(1, 0, now), now)  # answered on state 0: a command
    command = sent.last("joint_command")
    assert command["device_deadline_ns"] == now and np.abs(command["qd_ref_rad_s"]).max() > 0
    cycle.on_state(state(config, late_tick, now), now)  # the handle's tick is stale now
    assert cycle.no_input_cycles == 2
    # with no input the workspace spring (on the handle's offset) is not rendered
    assert np.allclose(sent.last("force_feedback")["device_f_workspace_n"], 0.0)


def test_realtime_inputs_too_old_or_out_of_order_are_dropped_and_counted():
    cycle, sent, clock, config = make(BilateralCycle, 'run.mode="realtime"', 'run.scenario="grasp"')
    now = clock.now_ns()
    cycle.on_state(state(config, 0, now), now)
    cycle.on_haptic(handle(5, 0, now), now)
    cycle.on_haptic(handle(4, 0, now), now)  # older than the last one: dropped
    old = now - 10 * cycle.haptic_in.shed_age_ns
    cycle.on_haptic(handle(6, 0, old), now)  # sampled too long ago: shed, its loop logged
    stale_state = state(config, 1, old)
    cycle.on_state(stale_state, now)
    summary = cycle.summary()
    assert summary["haptic_reordered"] == 1 and summary["haptic_shed"] == 1
    assert summary["states_shed"] == 1 and summary["cycles"] == 1
    assert len(cycle.shed_log) == 1  # the state carried no sample stamp


def test_the_path_cycle_answers_each_state_once_and_restarts_on_a_new_run():
    cycle, sent, clock, config = make(PathCycle, 'run.mode="lockstep"')
    now = clock.now_ns()
    for seq in (0, 1, 1, 3):  # a re-send of 1, and state 2 never seen
        cycle.on_state(state(config, seq, now), now)
    commands = [rec for s, rec in sent.log if s == "joint_command"]
    assert [int(c["state_seq"]) for c in commands] == [0, 1, 3]
    assert cycle.skipped_states == 1 and cycle.runs == 1
    assert "control_status" in sent.streams()  # step 0 is a status step
    cycle.on_state(state(config, 0, now, start_ns=2), now)  # state 0 of a new run
    assert cycle.runs == 2 and cycle.summary()["cycles"] == 4


@pytest.mark.parametrize("cycle_class", [PathCycle, BilateralCycle])
def test_a_cycle_spends_its_compute_time_on_the_injected_clock(cycle_class):
    cycle, sent, clock, config = make(cycle_class, 'run.mode="lockstep"', 'run.scenario="grasp"')
    cycle.on_state(state(config, 0, clock.now_ns()), clock.now_ns())
    if isinstance(cycle, BilateralCycle):
        cycle.on_haptic(handle(1, 0, clock.now_ns()), clock.now_ns())
    assert cycle.summary()["compute_mean_us"] == 0.0  # a fake clock stands still
