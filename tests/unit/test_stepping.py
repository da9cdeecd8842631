"""The plant's step core without a bus or a pacer: watchdog, admission, step, publish."""

from __future__ import annotations

import numpy as np
import pytest

from teleop.bus.messages import JOINT_COMMAND, Event, Flag, Stage
from teleop.core.clock import FakeClock
from teleop.core.config import load_config
from teleop.sim.stepping import Abort, PlantStepCore, Watchdog

PERIOD_NS = 1_000_000


class Recorded:
    """PlantOutputs that keep every record (decoded copies) by stream, and every re-send."""

    def __init__(self) -> None:
        self.records: dict[str, list[np.ndarray]] = {}
        self.resent: list[tuple[str, bytes]] = []
        self.flushes = 0

    def put(self, stream: str, rec: np.ndarray) -> bytes:
        self.records.setdefault(stream, []).append(rec.copy())
        return rec.tobytes()

    def put_bytes(self, stream: str, data: bytes) -> None:
        self.resent.append((stream, data))

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


def make_core(*overrides: str) -> tuple[PlantStepCore, Recorded, FakeClock]:
    """A core at the start of a run, its first state published."""
    config = load_config(None, ['run.mode="realtime"', *overrides])
    outputs, clock = Recorded(), FakeClock(start_ns=10**12)
    core = PlantStepCore(config, outputs, clock)
    core.begin_run(None)
    core.publish_state()
    return core, outputs, clock


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
    assert dog.episodes == [[120 * ms, 122 * ms]]  # when it braked and resumed
    # A state too old to remember (or never sent) is stale.
    assert not dog.judge(command(3, state_seq=0, now_ns=0), 122 * ms).apply
    with pytest.raises(ValueError):
        Watchdog(0, ms)
    with pytest.raises(ValueError):
        Watchdog(ms, ms)


def test_the_core_admits_answers_to_states_it_sent_and_sheds_only_when_asked():
    core, out, clock = make_core()
    # A command answering a state not sent yet is rejected before anything else.
    assert not core.admit(command(1, state_seq=5, now_ns=clock.now_ns()), shed=False)
    assert core.commands_future_state == 1 and core.commands_received == 1
    for seq in (2, 3, 4):  # the link's pace: an age is the time beyond its fastest records
        assert core.admit(command(seq, state_seq=0, now_ns=clock.now_ns()), shed=True)
    old = command(5, state_seq=0, now_ns=clock.now_ns() - 10 * core.command_in.shed_age_ns)
    assert core.admit(old, shed=False)  # the watchdog judges its age at the step
    older = command(6, state_seq=0, now_ns=clock.now_ns() - 10 * core.command_in.shed_age_ns)
    assert not core.admit(older, shed=True)  # applied on arrival, a backlog is shed
    assert core.command_in.shed == 1 and core.commands_received == 6
    assert not core.admit(command(5, state_seq=0, now_ns=clock.now_ns()), shed=False)
    assert core.command_in.seq.reordered == 1  # not newer than the last admitted


def test_a_command_held_over_several_steps_is_counted_and_traced_once():
    core, out, clock = make_core()
    held = command(1, state_seq=0, now_ns=clock.now_ns())
    for _ in range(3):
        clock.advance(PERIOD_NS)
        assert core.step(held, clock.now_ns())
    states = out.records["plant_state"][1:]
    assert core.commands_applied == 1
    assert [int(s["cmd_seq_applied"]) for s in states] == [1, 1, 1]
    assert states[0]["trace_ns"][Stage.CONTROLLER_TX] == held["trace_ns"][Stage.CONTROLLER_TX]
    assert not states[1]["trace_ns"][Stage.CONTROLLER_TX]  # only held: nothing to trace
    # Told it entered the step first hand (a device period's own command), it is traced.
    clock.advance(PERIOD_NS)
    core.step(held, clock.now_ns(), traced=True)
    assert out.records["plant_state"][-1]["trace_ns"][Stage.PLANT_RX] == clock.now_ns()


def test_a_brake_that_lasts_the_limit_ends_the_run_in_one_line():
    """Realtime, the commands stop (the link to the operator's site cut): the watchdog
    brakes and holds the arm; a fresh command within plant.brake_limit_s resumes, a
    brake that lasts the limit aborts the run (no more steps) saying why."""
    core, out, clock = make_core("plant.brake_limit_s=1.0")
    fresh = command(1, state_seq=core.state_seq, now_ns=clock.now_ns())
    clock.advance(core.period_ns)
    assert core.step(fresh, 0)
    while not core.watchdog.braking:  # no fresh command since: braked within watchdog_s
        clock.advance(core.period_ns)
        core.step(fresh, 0)
    for _ in range(round(0.9 / core.config.tick_s)):  # 0.9 s braked
        clock.advance(core.period_ns)
        assert not core.step(fresh, 0)
    assert not core.aborted and core.should_step()
    again = command(2, state_seq=core.state_seq, now_ns=clock.now_ns())
    clock.advance(core.period_ns)
    assert core.step(again, 0)  # back within the limit: the run goes on
    while not core.aborted:
        clock.advance(core.period_ns)
        core.step(again, 0)
        if core.watchdog.braking:
            assert clock.now_ns() - core.watchdog.braking_since_ns <= 1e9 + core.period_ns
    assert not core.should_step()
    assert "no fresh command for 1.0 s (plant.brake_limit_s = 1)" in core.failure
    [aborted] = [r for r in out.records["plant_events"] if r["event"] == Event.ABORTED]
    assert aborted["value"] == Abort.BRAKE_LIMIT


@pytest.mark.parametrize("scene_rate_hz", [100.0, 125.0, 60.0])
def test_the_scene_goes_out_at_its_rate_exactly_whether_or_not_it_divides_the_bus_rate(
    scene_rate_hz,
):
    core, out, clock = make_core(f"plant.scene_rate_hz={scene_rate_hz}")
    ticks_per_s = round(1.0 / core.config.tick_s)
    sent_before = len(out.records["tool_pose"])
    for _ in range(ticks_per_s):
        clock.advance(core.period_ns)
        core.step(None, 0)
    poses = out.records["tool_pose"][sent_before:]
    assert len(poses) == round(scene_rate_hz)
    assert len(out.records["objects"]) == len(out.records["tool_pose"])
    gaps = np.diff([int(p["sim_time_ns"]) for p in poses]) / core.period_ns
    assert gaps.max() == core.scene.gap_ticks


def test_a_tool_pose_says_whether_the_plant_braked_since_the_one_before():
    """TOOL_POSE comes at the scene rate; its BRAKING flag covers every step since the
    previous one, so an operator watching the tool knows it was held."""
    core, out, clock = make_core()
    every = core.scene.gap_ticks
    for _ in range(every):  # no command yet: every step brakes
        clock.advance(PERIOD_NS)
        assert not core.step(None, 0)
    assert out.records["tool_pose"][-1]["flags"] == Flag.BRAKING
    for seq in range(1, 2 * every + 1):  # a fresh command every step: none brakes
        fresh = command(seq, state_seq=core.state_seq, now_ns=clock.now_ns())
        clock.advance(PERIOD_NS)
        assert core.step(fresh, 0)
    assert out.records["tool_pose"][-1]["flags"] == Flag.NONE
    assert out.records["plant_state"][-1]["flags"] == Flag.NONE
    assert out.events() == []  # braking before the first command announces nothing
