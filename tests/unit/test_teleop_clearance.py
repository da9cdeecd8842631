"""Teleoperation keeps clear of the table and the operator feels it.

The plant's lockstep loop and the bilateral cycle in one process, records handed from
one to the other (as tests/unit/test_cycle.py does for path following), with the
handle held down for the whole run: the operator drives the tool straight into the
table. The unguarded law (``clearance.avoid=false``) touches it; the guarded one stops
the gripper at its stop distance, and the table's push-back reaches the handle,
upwards. Deterministic: a fake clock, one thread stepping the plant.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import pytest

from teleop.bus.messages import HAPTIC_STATE, HEAD_POSE, Event
from teleop.control.cycle import BilateralCycle
from teleop.control.kinematics import build_arm_model
from teleop.core.clock import FakeClock
from teleop.core.config import load_config
from teleop.sim.plant_loop import PlantLoop
from tests.unit.test_cycle import Wire

# From the home pose (tool at about (0.39, 0.13, 0.40) m) nothing but the table lies
# below the tool: the handle held 3 cm down asks for 0.16 m/s downwards, which reaches
# the table in about 2.5 s.
HANDLE_DOWN_M = (0.0, 0.0, -0.03)
RUN = ['run.mode="lockstep"', 'run.scenario="grasp"', "run.duration_s=4"]
# The cap acts on the next step's approach, and the drives lag the command (m).
MARGIN_TOLERANCE_M = 1e-3


def drive_down(*overrides: str) -> tuple[dict[str, Any], list[np.ndarray]]:
    """The cycle's summary and every FORCE_FEEDBACK it sent, the handle held down."""
    config = load_config(None, [*RUN, *overrides])
    wire, clock = Wire(), FakeClock(start_ns=10**12)
    loop = PlantLoop(config, wire, clock)
    cycle = BilateralCycle(config, build_arm_model(config.robot), wire, clock)
    steps = round(config.run.duration_s / config.tick_s)  # ticks (bus periods)
    stop = threading.Event()
    runner = threading.Thread(target=loop.run, args=(stop, steps))
    runner.start()
    states, commands = wire.queues["plant_state"], wire.queues["joint_command"]
    hmd = config.hmd
    handle = HAPTIC_STATE.new()
    handle["device_p_m"] = HANDLE_DOWN_M
    pose = HEAD_POSE.new()
    pose["predicted_yaw_rad"] = hmd.head_yaw_rad
    try:
        while not states and runner.is_alive():  # state 0 comes from the run's thread
            runner.join(timeout=0.001)
        while states:  # each command steps the plant, which publishes the next state
            state = states.popleft()
            tick = int(state["seq"])
            valid_from = cycle.head_schedule.valid_from_for(tick)
            if valid_from is not None:  # the HMD pose the cycle waits for at this tick
                pose["valid_from_tick"] = valid_from
                cycle.on_head_pose(pose.copy(), clock.now_ns())
            cycle.on_state(state, clock.now_ns())
            handle["seq"] = tick + 1
            handle["tick"] = tick
            cycle.on_haptic(handle.copy(), clock.now_ns())
            while commands:
                loop.on_command(commands.popleft(), clock.now_ns())
        runner.join(timeout=60)
        assert not runner.is_alive()
    finally:
        stop.set()
        runner.join(timeout=60)
    assert loop.core.finished
    assert cycle.missing_head_poses == 0  # the poses sent on the cycle's own schedule
    return cycle.summary(), list(wire.queues["force_feedback"])


@pytest.fixture(scope="module")
def unguarded() -> tuple[dict[str, Any], list[np.ndarray]]:
    return drive_down("clearance.avoid=false")


@pytest.fixture(scope="module")
def guarded() -> tuple[dict[str, Any], list[np.ndarray]]:
    return drive_down()


def test_the_unguarded_law_drives_the_gripper_into_the_table(unguarded):
    summary, feedback = unguarded
    assert summary["arm_contacts"] > 0
    assert Event.CONTACT.name in {e["event"] for e in summary["events"]}
    assert summary["motion_problems"]
    assert all(not rec["world_f_scene_n"].any() for rec in feedback)  # nothing felt


def test_the_guarded_law_stops_before_the_table_and_the_handle_feels_it(guarded):
    summary, feedback = guarded
    config = load_config(None, RUN).clearance
    assert summary["arm_contacts"] == 0
    assert summary["motion_problems"] == []
    assert summary["events"] == []
    assert summary["min_clearance_finger_m"] >= config.finger_stop_m - MARGIN_TOLERANCE_M
    assert summary["min_clearance_scene_m"] >= config.stop_m - MARGIN_TOLERANCE_M
    assert summary["clearance_held_cycles"] > 0
    # At the end the tool rests above the table, pushed up: the table's push-back is up,
    # and so is the force rendered on the handle against the operator's hand.
    last = feedback[-1]
    assert last["world_f_scene_n"][2] > 0.0
    assert summary["max_scene_force_n"] == pytest.approx(
        max(float(np.linalg.norm(rec["world_f_scene_n"])) for rec in feedback)
    )
    assert last["device_f_n"][2] > 0.0
