"""The plant's loop without a bus: watchdog, device-clock grid, lockstep, on a fake clock."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from teleop.bus.messages import JOINT_COMMAND, PLANT_STATE, RUN_EVENT, Event, Flag, Stage
from teleop.core.clock import FakeClock
from teleop.core.config import load_config
from teleop.sim.stepping import (
    CATCH_UP_MAX_PERIODS,
    OWN_STEP_AFTER_PERIODS,
    RELOCK_PERIODS,
    DeviceClockGrid,
    PlantLoop,
    Watchdog,
)

PERIOD_NS = 1_000_000


class Recorded:
    """PlantOutputs that keep every record (decoded copies) by stream."""

    def __init__(self) -> None:
        self.records: dict[str, list[np.ndarray]] = {}
        self.resent: list[str] = []
        self.flushes = 0

    def put(self, stream: str, rec: np.ndarray) -> bytes:
        self.records.setdefault(stream, []).append(rec.copy())
        return rec.tobytes()

    def put_bytes(self, stream: str, data: bytes) -> None:
        self.resent.append(stream)

    def flush(self) -> None:
        self.flushes += 1

    def events(self) -> list[Event]:
        return [Event(int(r["event"])) for r in self.records.get("plant_events", [])]


def command(seq: int, state_seq: int, now_ns: int, deadline_ns: int = 0, qd: float = 0.1):
    rec = JOINT_COMMAND.new()
    rec["seq"] = seq
    rec["state_seq"] = state_seq
    rec["n_joints"] = 6
    rec["qd_ref_rad_s"][:6] = qd
    rec["gripper_cmd"] = 1.0
    rec["device_deadline_ns"] = deadline_ns
    rec["trace_ns"][Stage.HAPTIC_SAMPLE] = now_ns
    rec["trace_ns"][Stage.CONTROLLER_TX] = now_ns
    return rec


def make_loop(*overrides: str) -> tuple[PlantLoop, Recorded, FakeClock]:
    config = load_config(None, overrides)
    outputs, clock = Recorded(), FakeClock(start_ns=10**12)
    return PlantLoop(config, outputs, clock), outputs, clock


def test_watchdog_judges_on_the_plants_clock_and_state_numbering():
    ms = 1_000_000
    dog = Watchdog(limit_ns=20 * ms, period_ns=ms)
    assert dog.judge(None, 0) == (False, None, 0.0)  # nothing yet: hold, no event
    for seq in range(101):  # states 0..100 sent 1 ms apart
        dog.state_sent(seq, seq * ms)
    cmd = command(1, state_seq=100, now_ns=0)
    assert dog.judge(cmd, 500 * ms).apply  # answers the newest state: fresh however late
    dog.state_sent(101, 101 * ms)
    # The command answering state 100 came after 100 ms: the step at 120 ms, 20 ms after
    # state 100, is the first that brakes.
    assert dog.judge(cmd, 120 * ms - 1).apply
    brake = dog.judge(cmd, 120 * ms)
    assert not brake.apply and brake.event is Event.WATCHDOG_BRAKE
    assert brake.value == pytest.approx(0.020, abs=1e-6)  # the answered state's age (s)
    assert dog.judge(cmd, 122 * ms) == (False, None, 0.0)  # still braking: no second event
    resume = dog.judge(command(2, state_seq=101, now_ns=0), 122 * ms)
    assert resume.apply and resume.event is Event.WATCHDOG_RESUME
    assert (dog.brakes, dog.stale_steps) == (1, 2)
    # A state too old to remember (or never sent) is stale.
    assert not dog.judge(command(3, state_seq=0, now_ns=0), 122 * ms).apply
    with pytest.raises(ValueError):
        Watchdog(0, ms)
    with pytest.raises(ValueError):
        Watchdog(ms, ms)


def test_device_clock_grid_steps_each_device_period_once():
    grid = DeviceClockGrid(PERIOD_NS, start_ns=0)
    assert not grid.locked and grid.own_step_ns == OWN_STEP_AFTER_PERIODS * PERIOD_NS
    deadline_ns = 10_000_000  # the device's period, not the arrival time
    grid.lock(deadline_ns)
    assert grid.periods_ahead(deadline_ns) == 0
    grid.stepped()
    # The next device period is the next step's, whatever the arrival jitter.
    assert grid.periods_ahead(deadline_ns + PERIOD_NS) == 0
    # A command of a period already stepped is late; one two periods on has a gap.
    assert grid.periods_ahead(deadline_ns) == -1
    assert grid.periods_ahead(deadline_ns + 3 * PERIOD_NS) == 2
    # Without a command, the plant steps the period itself a fixed time after it began.
    assert grid.own_step_ns == deadline_ns + (1 + OWN_STEP_AFTER_PERIODS) * PERIOD_NS
    grid.skip(3)  # a stall
    assert grid.skipped == 3 and grid.periods_ahead(deadline_ns + 4 * PERIOD_NS) == 0
    with pytest.raises(ValueError):
        DeviceClockGrid(0, 0)


def test_plant_tick_pacing_brakes_on_a_stale_command_and_resumes():
    loop, out, clock = make_loop('run.mode="realtime"')
    loop.begin_run(None)
    loop.publish_initial_state()
    limit_ms = round(loop.config.plant.watchdog_s * 1000)
    loop.tick()  # no command yet: braking, no event
    assert out.records["plant_state"][-1]["flags"] == Flag.BRAKING and out.events() == []
    loop.on_command(command(1, state_seq=1, now_ns=clock.now_ns()), clock.now_ns())
    # Applied while state 1 (the one answered) went out less than the limit ago.
    for _ in range(limit_ms - 1):
        clock.advance(PERIOD_NS)
        loop.tick()
    assert loop.commands_applied == 1 and out.events() == []
    assert out.records["plant_state"][-1]["flags"] == Flag.NONE
    clock.advance(PERIOD_NS)
    loop.tick()  # the command now answers a state sent the limit ago
    assert out.events() == [Event.WATCHDOG_BRAKE]
    assert out.records["plant_state"][-1]["flags"] == Flag.BRAKING
    fresh = command(2, state_seq=loop.state_seq, now_ns=clock.now_ns())
    loop.on_command(fresh, clock.now_ns())
    loop.tick()
    assert out.events() == [Event.WATCHDOG_BRAKE, Event.WATCHDOG_RESUME]
    assert out.records["plant_state"][-1]["cmd_seq_applied"] == 2
    summary = loop.summary()
    assert (summary["stale_commands"], summary["commands_applied"]) == (1, 2)


def test_a_tool_pose_says_whether_the_plant_braked_since_the_one_before():
    """TOOL_POSE comes at the scene rate; its BRAKING flag covers every step since the
    previous one, so an operator watching the tool knows it was held."""
    loop, out, clock = make_loop('run.mode="realtime"')
    loop.begin_run(None)
    loop.publish_initial_state()
    every = loop.scene_every_steps
    for _ in range(every):  # no command yet: every step brakes
        clock.advance(PERIOD_NS)
        loop.tick()
    assert out.records["tool_pose"][-1]["flags"] == Flag.BRAKING
    for seq in range(1, 2 * every + 1):  # a fresh command every step: none brakes
        loop.on_command(command(seq, state_seq=loop.state_seq, now_ns=clock.now_ns()), 0)
        clock.advance(PERIOD_NS)
        loop.tick()
    assert out.records["tool_pose"][-1]["flags"] == Flag.NONE
    assert out.records["plant_state"][-1]["flags"] == Flag.NONE


def test_apply_on_arrival_steps_once_per_device_period_and_never_runs_ahead():
    """Commands step at once; a late one merges, a gap is filled, sim time = device time."""
    loop, out, clock = make_loop('run.scenario="grasp"', 'run.mode="realtime"')
    assert loop.apply_on_arrival
    loop.begin_run(None)
    loop.publish_initial_state()
    loop.begin_on_arrival()
    t0_ns = clock.now_ns()

    def arrive(seq: int, periods: int) -> None:
        deadline_ns = t0_ns + periods * PERIOD_NS
        rec = command(seq, max(loop.state_seq, 0), clock.now_ns(), deadline_ns=deadline_ns)
        loop.on_command(rec, clock.now_ns())

    arrive(1, 0)
    assert loop.plant.step_count == 1 and loop.arrival.steps_on_arrival == 1
    arrive(2, 1)  # the next period's command: one more step, on arrival
    assert loop.plant.step_count == 2
    arrive(3, 1)  # late (its period was stepped): no step of its own, held for the next
    assert loop.plant.step_count == 2 and loop.arrival.commands_late == 1
    arrive(4, 3)  # two periods on: the period in between (no command) is stepped first
    assert loop.plant.step_count == 4 and loop.arrival.steps_without_command == 1
    arrive(5, 20)  # after a long gap only CATCH_UP_MAX_PERIODS are stepped back to back
    assert loop.plant.step_count == 5 + CATCH_UP_MAX_PERIODS
    assert loop.grid.skipped == 20 - 4 - CATCH_UP_MAX_PERIODS
    assert loop.grid.periods_ahead(t0_ns + 21 * PERIOD_NS) == 0  # sim time = device time
    arrive(6, 2 * RELOCK_PERIODS)  # a restarted device: the grid re-locks to its clock
    assert loop.grid.locks == 2
    arrive(6, 2 * RELOCK_PERIODS + 1)  # not newer than the last: dropped, counted
    assert loop.command_in.seq.reordered == 1
    summary = loop.summary()["arrival"]
    assert summary["commands_late"] == 1 and summary["commands_reordered"] == 1


def test_apply_on_arrival_steps_periods_without_commands_itself_and_skips_stalls():
    loop, out, clock = make_loop('run.scenario="grasp"', 'run.mode="realtime"')
    loop.begin_run(None)
    loop.begin_on_arrival()
    assert loop.own_step_due(clock.now_ns()) == OWN_STEP_AFTER_PERIODS * PERIOD_NS
    clock.advance(OWN_STEP_AFTER_PERIODS * PERIOD_NS)
    loop.own_step(clock.now_ns())
    assert loop.plant.step_count == 1 and loop.arrival.stalls == 0
    clock.advance(50 * PERIOD_NS)  # a stall: skip, never burst
    loop.own_step(clock.now_ns())
    assert loop.plant.step_count == 2 and loop.arrival.stalls == 1
    assert loop.own_step_due(clock.now_ns()) > -CATCH_UP_MAX_PERIODS * PERIOD_NS


def test_a_command_older_than_the_shed_age_is_shed_and_its_loop_logged():
    loop, out, clock = make_loop('run.scenario="grasp"', 'run.mode="realtime"')
    loop.begin_run(None)
    loop.publish_initial_state()
    loop.begin_on_arrival()
    old = command(1, 0, clock.now_ns() - 10 * loop.command_in.shed_age_ns)
    loop.on_command(old, clock.now_ns())
    assert loop.plant.step_count == 0 and loop.command_in.shed == 1
    assert len(loop.command_in.shed_log) == 1


def test_lockstep_steps_only_on_the_answer_to_the_pending_state():
    loop, out, clock = make_loop('run.mode="lockstep"', "plant.lockstep_delay_steps=0")
    stop = threading.Event()
    runner = threading.Thread(target=loop.run, args=(stop, 3))
    runner.start()
    try:
        while loop.state_seq < 0:  # state 0 published
            clock.advance(1)
        # a command answering a state not sent yet is rejected before anything else
        loop.on_command(command(1, state_seq=5, now_ns=clock.now_ns()), clock.now_ns())
        assert loop.plant.step_count == 0 and loop.commands_future_state == 1
        for seq in range(3):
            loop.on_command(command(seq + 2, loop.state_seq, clock.now_ns()), clock.now_ns())
        runner.join(timeout=30)
        assert not runner.is_alive()
    finally:
        stop.set()
        runner.join(timeout=30)
    assert loop.finished and loop.plant.step_count == 3 and loop.commands_applied == 3
    assert out.events() == [Event.STARTED, Event.FINISHED]
    assert [int(r["seq"]) for r in out.records["plant_state"]] == [0, 1, 2, 3]
    assert out.flushes == 1
    assert PLANT_STATE.size and RUN_EVENT.size  # the records' layouts are the bus's
