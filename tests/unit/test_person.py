"""A person at the controls, without a bus: key presses into hand intents
(teleop.devices.person.intent), hand inputs paced for each timing mode and the task's phases read
from the world (teleop.devices.person.loop), on a fake clock."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from services.keyboard import KeyboardOperatorService
from teleop.bus.messages import Button, Event
from teleop.core.clock import NS_PER_S
from teleop.core.config import ConfigError, load_config
from teleop.core.summary import PhaseTime
from teleop.core.ticks import expected_valid_from, is_sample_tick, lead_ticks, next_sample_tick
from teleop.devices.person.intent import (
    DEFAULT_KEYS,
    SWITCH,
    TAB,
    UP,
    HandIntent,
    KeyboardIntent,
    hand_command,
    top_offset_m,
)
from teleop.devices.person.loop import (
    CARRY,
    PLACED,
    REACH,
    SWITCH_SETTLE_S,
    TASK_DONE_AHEAD_TICKS,
    PersonLoop,
    PersonStation,
    WorldTask,
)
from teleop.devices.scripted.routing import SceneKnowledge

MS = 1_000_000  # ns
CONFIG = load_config()
TICK_S = CONFIG.tick_s  # one tick: a bus period (loop.rate_hz)
TICK_NS = round(TICK_S * NS_PER_S)
RATE_HZ = CONFIG.operator.decision_rate_hz  # the hand's decisions
SCENE_TICKS = round(1.0 / (CONFIG.plant.scene_rate_hz * TICK_S))  # TOOL_POSE's period
BIN = np.array([0.35, 0.35, 0.0])
SCENE = SceneKnowledge(bin_low_m=(-0.09, -0.09, 0.0), bin_high_m=(0.09, 0.09, 0.08))


class Outputs:
    def __init__(self) -> None:
        self.hands: list[tuple[int, np.ndarray, Button]] = []
        self.events: list[tuple[Event, int, int, float]] = []

    def put_hand(self, valid_from_tick: int, target_p_m: np.ndarray, buttons: Button) -> None:
        self.hands.append((valid_from_tick, np.array(target_p_m), buttons))

    def event(self, event: Event, tick: int, step: int, value: float) -> None:
        self.events.append((event, tick, step, value))


# -- intents and hand commands -------------------------------------------------------------
def test_no_intent_leaves_the_handle_at_its_centre():
    target, buttons = hand_command(HandIntent(), CONFIG.teleop)
    assert np.array_equal(target, np.zeros(3)) and buttons == Button.NONE


def test_a_full_intent_asks_for_the_top_speed_within_the_free_workspace():
    teleop = CONFIG.teleop
    target, _ = hand_command(HandIntent((1.0, 0.0, 0.0)), teleop)
    assert target[0] == pytest.approx(top_offset_m(teleop)) and target[1:].tolist() == [0, 0]
    assert top_offset_m(teleop) <= teleop.workspace_free_m
    # The rate law (v = gain (x - deadband)) gives the fraction of the top speed asked for.
    half, _ = hand_command(HandIntent((0.0, -0.5, 0.0)), teleop)
    top_speed = teleop.rate_gain_per_s * (top_offset_m(teleop) - teleop.deadband_m)
    speed = teleop.rate_gain_per_s * (abs(half[1]) - teleop.deadband_m)
    assert half[1] < 0 and speed == pytest.approx(0.5 * top_speed)


def test_a_diagonal_intent_is_clipped_to_the_top_speed_and_keeps_its_direction():
    target, _ = hand_command(HandIntent((1.0, 1.0, 0.0)), CONFIG.teleop)
    assert np.linalg.norm(target) == pytest.approx(top_offset_m(CONFIG.teleop))
    assert target[0] == pytest.approx(target[1])


def test_gripper_and_clutch_are_the_hand_inputs_buttons():
    assert HandIntent(gripper_closed=True).buttons == Button.GRIPPER_CLOSE
    assert HandIntent(clutch=True, gripper_closed=True).buttons == (
        Button.GRIPPER_CLOSE | Button.CLUTCH
    )


@pytest.mark.parametrize("bad", [(math.nan, 0.0, 0.0), (1.5, 0.0, 0.0), (0.0, 0.0)])
def test_an_intent_out_of_range_is_refused(bad):
    with pytest.raises(ValueError, match="velocity_fraction"):
        HandIntent(bad)


def test_a_key_moves_its_axis_for_the_hold_time_and_a_repeat_extends_it():
    keys = KeyboardIntent(CONFIG.keyboard)
    hold_ns = round(CONFIG.keyboard.hold_s * NS_PER_S)
    speed = CONFIG.keyboard.speed_steps[CONFIG.keyboard.start_speed_step]
    keys.press("w", 0)
    assert keys.intent(1).velocity_fraction == (speed, 0.0, 0.0)
    assert keys.intent(hold_ns).velocity_fraction == (0.0, 0.0, 0.0)  # a tap: one step
    keys.press(UP, hold_ns - 1)  # the same axis by its other key (a repeat)
    assert keys.intent(hold_ns + 100 * MS).velocity_fraction[0] == speed
    keys.press("s", hold_ns + 100 * MS)  # the opposite key takes the axis over
    assert keys.intent(hold_ns + 200 * MS).velocity_fraction[0] == -speed
    keys.press("a", hold_ns + 200 * MS)  # another axis adds to it
    assert keys.intent(hold_ns + 300 * MS).velocity_fraction[:2] == (-speed, speed)
    keys.press(" ", hold_ns + 300 * MS)
    assert not keys.intent(hold_ns + 300 * MS).moving


def test_speed_steps_stop_at_their_ends_and_toggles_flip():
    keys = KeyboardIntent(CONFIG.keyboard)
    for _ in range(10):
        keys.press("+", 0)
    assert keys.speed_fraction == CONFIG.keyboard.speed_steps[-1]
    for _ in range(10):
        keys.press("-", 0)
    assert keys.speed_fraction == CONFIG.keyboard.speed_steps[0]
    keys.press("g", 0)
    keys.press("c", 0)
    assert keys.intent(0).buttons == Button.GRIPPER_CLOSE | Button.CLUTCH
    keys.press("g", 0)
    assert keys.intent(0).buttons == Button.CLUTCH


def test_unknown_keys_are_counted_and_do_nothing():
    keys = KeyboardIntent(CONFIG.keyboard)
    assert keys.press("z", 0) is None and keys.press("", 0) is None
    assert keys.unknown_keys == 2 and keys.presses == 0 and not keys.intent(0).moving
    assert keys.press("q", 0) is not None and keys.quit_requested


def test_every_move_key_names_an_axis_and_a_sign():
    moves = [a for a in DEFAULT_KEYS.values() if a.kind == "move"]
    assert {(a.axis, a.sign) for a in moves} == {
        (axis, sign) for axis in range(3) for sign in (1.0, -1.0)
    }


def test_keyboard_config_is_checked():
    with pytest.raises(ConfigError, match="keyboard.start_speed_step"):
        load_config(None, ["keyboard.start_speed_step=9"])
    with pytest.raises(ConfigError, match="run.operator"):
        load_config(None, ['run.operator="joystick"'])


# -- pacing ----------------------------------------------------------------------------------
def _loop(lockstep: bool) -> tuple[PersonLoop, Outputs]:
    outputs = Outputs()
    return PersonLoop(CONFIG, outputs, SCENE, lockstep=lockstep), outputs


def _sample_ticks(after_ns: int, until_ns: int) -> list[int]:
    """The hand's sample ticks (RATE_HZ on the run's ticks) whose time from the run's
    start is in (``after_ns``, ``until_ns``]."""
    ticks = range(until_ns // TICK_NS + 1)
    return [s for s in ticks if s * TICK_NS > after_ns and is_sample_tick(s, RATE_HZ, TICK_S)]


def test_nothing_goes_out_before_the_run_starts():
    loop, out = _loop(lockstep=True)
    assert loop.due(5 * MS, HandIntent()) > 5 * MS and out.hands == []


def test_lockstep_inputs_follow_the_wall_clock_on_the_grid_the_haptic_device_waits_on():
    loop, out = _loop(lockstep=True)
    lead = loop.hand_schedule.lead_ticks
    t0 = 1_000 * MS
    loop.on_started(t0)
    next_ns = loop.due(t0, HandIntent())
    # Tick 0's input now; the next when the wall clock reaches the next sample tick.
    assert [h[0] for h in out.hands] == [lead]
    assert next_ns == t0 + next_sample_tick(0, RATE_HZ, TICK_S) * TICK_NS
    for tick in range(0, 60 * MS // TICK_NS, SCENE_TICKS):  # the run keeps up: poses come
        loop.on_tool(tick, np.zeros(3), t0)
    loop.due(t0 + 45 * MS, HandIntent())  # the sample ticks of the first 45 ms are due
    sent = [h[0] for h in out.hands]
    due = _sample_ticks(-1, 45 * MS)
    assert len(due) == math.floor(0.045 * RATE_HZ) + 1  # 5: 0, 10, ... 40 ms at 100 Hz
    assert sent == [s + lead for s in due]
    # The haptic device's expected input at every tick up to the last is among them.
    for tick in range(lead, next_sample_tick(due[-1], RATE_HZ, TICK_S) + lead):
        assert expected_valid_from(tick, RATE_HZ, TICK_S, lead) in sent


def test_lockstep_holds_inputs_back_while_the_run_lags_and_never_bursts_past_it():
    loop, out = _loop(lockstep=True)
    loop.on_started(0)
    loop.due(10 * NS_PER_S, HandIntent())  # ten seconds of wall clock, no pose seen yet
    newest = max(h[0] for h in out.hands)
    assert newest <= loop.max_ahead_ticks and loop.inputs_held_back == 1
    loop.on_tool(100, np.zeros(3), 10 * NS_PER_S)
    loop.due(10 * NS_PER_S + MS, HandIntent())
    assert max(h[0] for h in out.hands) <= 100 + loop.max_ahead_ticks
    assert [h[0] for h in out.hands] == sorted({h[0] for h in out.hands})  # in order, once


def test_realtime_sends_one_input_per_decision_period_ahead_of_the_newest_tick():
    loop, out = _loop(lockstep=False)
    loop.on_started(0)
    loop.on_tool(500, np.zeros(3), 0)
    assert loop.due(0, HandIntent()) == 10 * MS
    assert loop.due(5 * MS, HandIntent()) == 10 * MS and len(out.hands) == 1
    assert out.hands[0][0] == 500 + lead_ticks(RATE_HZ, TICK_S)  # a decision period ahead
    loop.due(2 * NS_PER_S, HandIntent())  # after a stall: one input, not two hundred
    assert len(out.hands) == 2


@pytest.mark.parametrize("lockstep", [True, False])
def test_a_restarted_device_takes_up_a_run_under_way_from_its_newest_tick(lockstep):
    loop, out = _loop(lockstep=lockstep)
    now_ns = 500 * NS_PER_S  # no STARTED seen: the run began before this process
    loop.due(now_ns, HandIntent())
    assert out.hands == []
    loop.on_tool(12_340, np.zeros(3), now_ns)
    loop.due(now_ns, HandIntent((0.5, 0.0, 0.0)))
    first = out.hands[0][0]
    assert 12_340 < first <= 12_340 + 10  # the newest sample tick, one decision ahead
    assert out.hands[0][1][0] > 0  # the person's intent, at once
    assert [e[0] for e in out.events] == [Event.PHASE]  # the task's phases from here
    assert loop.summary()["joined_at_tick"] == 12_340 and loop.summary()["runs"] == 1


def test_the_hand_holds_up_what_it_carries_and_yields_to_every_other_force():
    loop, out = _loop(lockstep=False)
    loop.on_started(0)
    weight = np.array([0.0, 0.0, -1.0])  # a held cube's weight on the handle
    loop.on_force(weight + np.array([-1.5, 0.0, 0.0]), weight)  # and the table's push-back
    loop.due(0, HandIntent())
    stiffness = CONFIG.haptic.hand_stiffness_n_per_m
    assert out.hands[0][1].tolist() == pytest.approx([0.0, 0.0, 1.0 / stiffness])


# -- the task's phases, from the world -------------------------------------------------------
class Task:
    def __init__(self) -> None:
        self.events: list[tuple[Event, int, int, float]] = []
        self.task = WorldTask(SCENE, ("cube", "bin"), 0.001)
        self.task.start(0, self.emit)

    def emit(self, event: Event, tick: int, step: int, value: float) -> None:
        self.events.append((event, tick, step, value))

    def objects(self, tick: int, cube: tuple[float, float, float]) -> None:
        self.task.on_objects(tick, {"cube": np.array(cube), "bin": BIN}, self.emit)

    def phases(self) -> list[int]:
        return [int(e[3]) for e in self.events if e[0] == Event.PHASE]


def test_a_grasp_carry_and_placing_end_the_task_a_success():
    t = Task()
    t.objects(10, (0.45, -0.25, 0.025))
    t.task.on_hold(True, 100)
    for tick in range(110, 400, 10):  # carried over the bin
        t.objects(tick, (0.35, 0.35, 0.2))
    assert t.phases() == [REACH, CARRY]
    t.task.on_hold(False, 400)
    for tick in range(410, 1000, 10):  # fallen in and lying there
        t.objects(tick, (0.35, 0.35, 0.03))
    assert t.phases() == [REACH, CARRY, PLACED]
    done = [e for e in t.events if e[0] == Event.TASK_DONE]
    assert len(done) == 1 and done[0][3] == 1.0
    assert done[0][2] == done[0][1] + TASK_DONE_AHEAD_TICKS
    assert t.task.phase_times[1] == PhaseTime(CARRY, "carry", 0.1)


def test_fingers_that_touch_and_leave_within_milliseconds_change_no_phase():
    t = Task()
    for i, tick in enumerate(range(100, 110)):
        t.task.on_hold(i % 2 == 0, tick)  # grasp, release, grasp ... released at last
    for tick in range(110, 300, 10):
        t.objects(tick, (0.45, -0.25, 0.025))
    assert t.phases() == [REACH]


def test_a_cube_dropped_outside_the_bin_is_reached_for_again():
    t = Task()
    t.task.on_hold(True, 100)
    t.objects(200, (0.45, -0.25, 0.1))
    t.task.on_hold(False, 300)
    for tick in range(310, 1500, 10):
        t.objects(tick, (0.45, -0.25, 0.025))
    assert t.phases() == [REACH, CARRY, REACH]
    assert not t.task.done


def test_the_person_ending_the_run_is_no_success_and_said_once():
    loop, out = _loop(lockstep=True)
    loop.on_started(0)
    loop.on_tool(1234, np.zeros(3), 0)
    loop.end_task()
    loop.end_task()
    done = [e for e in out.events if e[0] == Event.TASK_DONE]
    assert done == [(Event.TASK_DONE, 1234, 1234 + TASK_DONE_AHEAD_TICKS, 0.0)]
    summary = loop.summary()
    assert summary["task_done"] and summary["success"] is False
    assert summary["failure"] == "ended by the person"


# -- several robots: one hand, the person's robot switch --------------------------------------
def _station(lockstep: bool, robots: int = 2) -> tuple[PersonStation, list[Outputs]]:
    outputs = [Outputs() for _ in range(robots)]
    loops = [PersonLoop(CONFIG, out, SCENE, lockstep=lockstep) for out in outputs]
    return PersonStation(loops), outputs


def test_the_switch_moves_the_hand_to_the_next_robot_on_one_unbroken_grid():
    station, (out0, out1) = _station(lockstep=True)
    lead = station.loop.hand_schedule.lead_ticks
    poses = range(0, 200 * MS // TICK_NS, SCENE_TICKS)
    for loop in station.loops:
        loop.on_started(0)
        for tick in poses:
            loop.on_tool(tick, np.zeros(3), 0)
    station.due(45 * MS, HandIntent((0.0, 0.0, 0.0), gripper_closed=True))
    before = _sample_ticks(-1, 45 * MS)  # 0, 10, ... 40 ms
    assert [h[0] for h in out0.hands] == [s + lead for s in before] and out1.hands == []
    assert station.switch() and station.active == 1
    station.due(95 * MS, HandIntent())
    # robot 1 takes up the next sample tick: no gap, no repeat, nothing more to robot 0
    after = _sample_ticks(45 * MS, 95 * MS)  # 50, 60, ... 90 ms
    assert [h[0] for h in out1.hands] == [s + lead for s in after]
    assert len(out0.hands) == len(before)
    assert station.loops[0].last_buttons == Button.GRIPPER_CLOSE  # as the hand left it
    assert station.loops[1].last_buttons == Button.NONE
    assert station.switches == [{"from": 0, "to": 1, "tick": poses[-1]}]
    assert station.switch() and station.active == 0  # around


@pytest.mark.parametrize("lockstep", [True, False])
def test_the_hand_moves_on_by_itself_once_the_driven_robots_task_is_done(lockstep):
    station, (out0, out1) = _station(lockstep=lockstep)
    for loop in station.loops:
        loop.on_started(0)
        loop.on_tool(100, np.zeros(3), 0)
    station.due(0, HandIntent())
    assert not station.move_on()  # robot 0's task goes on
    station.loops[0].task.finish(True, 100, station.loops[0]._emit)
    assert station.move_on() and station.active == 1
    station.due(20 * MS, HandIntent())
    assert out1.hands
    assert not station.switch()  # the only other robot's task is done: nowhere to go
    assert not station.move_on() and station.active == 1


def test_ending_the_run_ends_every_robots_task_and_the_summary_has_a_section_each():
    station, outputs = _station(lockstep=True)
    for loop in station.loops:
        loop.on_started(0)
        loop.on_tool(50, np.zeros(3), 0)
    station.end_task()
    for out in outputs:
        assert [e[0] for e in out.events if e[0] == Event.TASK_DONE] == [Event.TASK_DONE]
    summary = station.summary(["arm0", "arm1"])
    assert set(summary["robots"]) == {"arm0", "arm1"}
    assert all(s["failure"] == "ended by the person" for s in summary["robots"].values())
    alone, _ = _station(lockstep=True, robots=1)
    assert "robots" not in alone.summary(["arm0"]) and not alone.switch()


def test_the_keys_take_up_the_robot_the_hand_comes_to():
    keys = KeyboardIntent(CONFIG.keyboard)
    keys.press("w", 0)
    keys.press("g", 0)
    assert keys.press(TAB, 0).kind == SWITCH  # the service switches; the keys then:
    keys.take_robot(Button.NONE)
    intent = keys.intent(1)
    assert intent.velocity_fraction == (0.0, 0.0, 0.0) and not intent.gripper_closed
    keys.take_robot(Button.GRIPPER_CLOSE | Button.CLUTCH)
    assert keys.gripper_closed and keys.clutch


def test_the_hand_moving_on_by_itself_gives_the_keys_the_next_robots_gripper():
    """The keys drove arm1 (it kept the cube, gripper closed), then arm0 until its task
    was done: the move-on to arm1 takes its gripper up before the next input goes out,
    so arm1 is never told to open and drop what it holds."""
    station, (_, out1) = _station(lockstep=False)
    for loop in station.loops:
        loop.on_started(0)
        loop.on_tool(100, np.zeros(3), 0)
    station.loops[1].last_buttons = Button.GRIPPER_CLOSE  # as the hand left arm1
    station.loops[0].task.finish(True, 100, station.loops[0]._emit)
    service = KeyboardOperatorService.__new__(KeyboardOperatorService)
    service.station, service.lock = station, threading.Lock()
    service.keys = KeyboardIntent(CONFIG.keyboard)  # the gripper open, as arm0 left it
    service._wake, service._pending_input_ns = threading.Event(), None
    stop = threading.Event()
    intent = service.intent

    def one_round(now_ns: int) -> HandIntent:
        stop.set()
        return intent(now_ns)

    service.intent = one_round  # type: ignore[method-assign]
    service._pace(stop)
    assert station.active == 1 and service.keys.gripper_closed
    assert out1.hands and out1.hands[0][2] == Button.GRIPPER_CLOSE


def test_after_a_switch_the_hand_asks_for_no_motion_until_the_handle_has_settled():
    station, (_, out1) = _station(lockstep=False)
    for loop in station.loops:
        loop.on_started(0)
        loop.on_tool(1000, np.zeros(3), 0)
    assert station.switch() and station.settling
    moving = HandIntent((1.0, 0.0, 0.0), gripper_closed=True)
    station.due(0, moving)
    settle_ticks = round(SWITCH_SETTLE_S / CONFIG.plant.timestep_s)
    assert not out1.hands[-1][1].any() and out1.hands[-1][2] == Button.GRIPPER_CLOSE
    station.loops[1].on_tool(1000 + settle_ticks, np.zeros(3), 0)
    assert not station.settling
    station.due(20 * MS, moving)
    assert out1.hands[-1][1][0] > 0  # the person's motion, now on robot 1
