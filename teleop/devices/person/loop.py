"""The operator service of a person at the controls, as pure code: when hand inputs go
out, and the task's phases read from the world.

:class:`PersonLoop` takes what the service receives (the plant's STARTED, GRASP and
RELEASE events, TOOL_POSE and OBJECT_POSES), asks a device for the person's
:class:`teleop.devices.person.intent.HandIntent` and hands HAND_INPUT and RUN_EVENT decisions to
:class:`PersonOutputs`. Clock-injected: each call takes the time;
:mod:`teleop.devices.person.service` is the bus adapter.

When hand inputs go out (:meth:`PersonLoop.due`), on the grid of sample ticks the
haptic device expects (teleop.core.ticks: ``operator.decision_rate_hz``, each valid from
its sample tick plus one decision period):

- lockstep: the haptic device steps tick ``k`` only once the input that applies at ``k``
  is in, so this loop paces the run by the person's clock. The input of sample tick
  ``s`` goes out once ``s`` plant periods of wall time have passed since the run started,
  and never more than ``MAX_AHEAD_S`` ahead of the newest tick seen: the run goes no
  faster than real time, slows down with a busy machine rather than braking, and a key
  takes effect in the next input, at most a decision period and the run's lag later.
- realtime: once per decision period of wall time, valid from the newest tick seen plus
  one decision period (the haptic device takes the newest input that applies).

The hand holds what it carries. The emulated hand is a spring
(``haptic.hand_stiffness_n_per_m``) that the rendered force pushes aside by ``f / k``. A
person on a haptic handle holds a carried object's weight up without thinking; one at a
keyboard cannot feel it, and its 1 N alone would push the handle past the rate control's
dead band and sink the tool. So the hand's target leans up by the rendered weight's
``f / k`` (the weight component of the controller's batched FORCE_FEEDBACK, constant
while the object is held). Every other force (the table's, the bin's and the obstacles'
push-back, contact) moves the handle as it moves a hand that does not resist it: it
slows the motion toward what pushes back, as it is meant to; leaning into those too
would chase a force that changes with the motion it causes. The force is shown as well.

The task's phases come from the world, not from a script (:class:`WorldTask`): reach
(nothing held), carry (the plant's GRASP), placed (released with the object over the
bin); the task is done once the object has rested in the bin for ``PLACED_SETTLE_S``,
or when the person ends it (not a success).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from teleop.bus.messages import Button, Event
from teleop.core.clock import NS_PER_S
from teleop.core.config import Config
from teleop.core.summary import PhaseTime
from teleop.core.ticks import hand_schedule
from teleop.devices.person.intent import HandIntent, hand_command
from teleop.devices.scripted.routing import SceneKnowledge
from teleop.sim.proximity import BIN_BODY

logger = logging.getLogger(__name__)

# Lockstep: inputs go out at most this far (sim s) ahead of the newest tick seen (a run
# slower than real time does not let a key wait behind a queue of older inputs).
MAX_AHEAD_S = 0.02
# The object counts as placed once it has lain in the bin, not held, this long (sim s).
PLACED_SETTLE_S = 0.5
# A grasp or release counts once it has held this long (sim s): fingers that close on or
# open from an object touch and leave it several times within milliseconds.
HOLD_SETTLE_S = 0.05
# TASK_DONE names a tick this far ahead of the tick that ends the task: the plant ends the
# run there (the same margin as the scripted operator's).
TASK_DONE_AHEAD_TICKS = 100
# After a robot switch the hand asks for no motion this long (sim s): the handle comes to
# rest, where the haptic device makes the switch (teleop.devices.haptic.loop), before the
# person's motion goes out; motion sooner would still move the robot left behind.
SWITCH_SETTLE_S = 0.25

# Where the task's events go: (event, tick, step, value) as the RUN_EVENT record has them.
Emit = Callable[[Event, int, int, float], None]

REACH, CARRY, PLACED = 0, 1, 2
PHASES = ("reach", "carry", "placed")


class PersonOutputs(Protocol):
    """Where the loop's decisions go (the bus adapter publishes them)."""

    def put_hand(self, valid_from_tick: int, target_p_m: np.ndarray, buttons: Button) -> None: ...

    def event(self, event: Event, tick: int, step: int, value: float) -> None: ...


@dataclass
class WorldView:
    """What the person's screen shows: the newest of the world, as the services sent it."""

    tick: int = -1
    tool_p_m: np.ndarray | None = None  # world frame
    tool_speed_m_s: float = 0.0
    objects_p_m: dict[str, np.ndarray] | None = None
    holding: bool = False
    device_f_n: np.ndarray | None = None  # the force the handle renders, device frame
    phase: int = -1
    done: bool = False
    success: bool = False

    @property
    def force_n(self) -> float:
        """The magnitude of the force the handle renders (N; 0 before the first)."""
        return 0.0 if self.device_f_n is None else float(np.linalg.norm(self.device_f_n))

    @property
    def phase_name(self) -> str | None:
        """The task's phase by name (None before the run starts)."""
        return PHASES[self.phase] if 0 <= self.phase < len(PHASES) else None


class WorldTask:
    """The pick-and-place task's phases from the world: what is held (the plant's GRASP
    and RELEASE) and where the objects are (OBJECT_POSES)."""

    def __init__(self, scene: SceneKnowledge, object_names: Sequence[str], tick_s: float) -> None:
        self.scene = scene
        self.object_names = tuple(object_names)
        self.movable = tuple(name for name in object_names if name != BIN_BODY)
        self.tick_s = tick_s
        self.reset()

    def reset(self) -> None:
        self.phase = -1
        self.holding = False
        self.done = False
        self.success = False
        self._placed_since_tick: int | None = None
        self._objects: dict[str, np.ndarray] | None = None
        self._hold_change: tuple[bool, int] | None = None  # (holding, since tick), pending
        self.phase_times: list[PhaseTime] = []
        self.start_tick: int | None = None
        self.done_tick: int | None = None

    def _enter(self, phase: int, tick: int, emit: Emit) -> None:
        if phase == self.phase:
            return
        self.phase = phase
        if self.start_tick is None:
            self.start_tick = tick
        self.phase_times.append(PhaseTime(phase, PHASES[phase], tick * self.tick_s))
        emit(Event.PHASE, tick, tick, float(phase))

    def start(self, tick: int, emit: Emit) -> None:
        """The run started: the person reaches for the object."""
        self._enter(REACH, tick, emit)

    def on_hold(self, holding: bool, tick: int) -> None:
        """The plant's GRASP (``holding``) or RELEASE at ``tick``: it counts once it has
        held for HOLD_SETTLE_S (:meth:`on_objects` sees to it)."""
        self._hold_change = (holding, tick)

    def _settle_hold(self, tick: int, emit: Emit) -> None:
        change = self._hold_change
        if change is None or (tick - change[1]) * self.tick_s < HOLD_SETTLE_S:
            return
        self._hold_change = None
        holding, since = change
        if holding == self.holding:
            return
        self.holding = holding
        if self.done or self.phase < 0:
            return
        self._placed_since_tick = None
        if holding:
            self._enter(CARRY, since, emit)
        # Released: placed if over the bin (it falls in: settled below), else dropped.
        elif not any(self._over_bin(name, inside=False) for name in self.movable):
            self._enter(REACH, since, emit)
        else:
            self._enter(PLACED, since, emit)

    def _over_bin(self, name: str, *, inside: bool) -> bool:
        """Whether object ``name`` is over the bin's floor, seen from above; ``inside``:
        and below the top of its walls."""
        objects = self._objects
        if objects is None or name not in objects or self.scene.bin_high_m is None:
            return False
        bin_p_m = objects.get(BIN_BODY)
        if bin_p_m is None or not self.scene.in_bin(objects[name], bin_p_m):
            return False
        return not inside or objects[name][2] <= bin_p_m[2] + self.scene.bin_high_m[2]

    def on_objects(self, tick: int, objects_p_m: dict[str, np.ndarray], emit: Emit) -> None:
        """OBJECT_POSES at ``tick``: a grasp or release that has held counts; a placed
        object that rests in the bin ends the task."""
        self._objects = objects_p_m
        self._settle_hold(tick, emit)
        if self.done or self.phase < 0 or self.holding or self._hold_change is not None:
            return
        if not any(self._over_bin(name, inside=True) for name in self.movable):
            self._placed_since_tick = None
            return
        if self.phase != PLACED:
            self._enter(PLACED, tick, emit)
        if self._placed_since_tick is None:
            self._placed_since_tick = tick
        elif (tick - self._placed_since_tick) * self.tick_s >= PLACED_SETTLE_S:
            self.finish(True, tick, emit)

    def finish(self, success: bool, tick: int, emit: Emit) -> None:
        """The task ends (placed, or the person ended it): TASK_DONE, once."""
        if self.done:
            return
        self.done, self.success, self.done_tick = True, success, tick
        emit(Event.TASK_DONE, tick, tick + TASK_DONE_AHEAD_TICKS, 1.0 if success else 0.0)


class PersonLoop:
    """Hand inputs from a person's device, paced for the run's mode, and the task's
    phases from the world (see the module docstring)."""

    def __init__(
        self,
        config: Config,
        outputs: PersonOutputs,
        scene: SceneKnowledge,
        *,
        lockstep: bool,
    ) -> None:
        self.config = config
        self.outputs = outputs
        self.lockstep = lockstep
        self.tick_s = config.tick_s
        self.tick_ns = round(self.tick_s * NS_PER_S)
        self.hand_schedule = hand_schedule(config)
        lead = self.hand_schedule.lead_ticks
        self.max_ahead_ticks = max(lead, self.hand_schedule.ticks(MAX_AHEAD_S))
        self.decision_ns = round(NS_PER_S / self.hand_schedule.rate_hz)
        self.hand_stiffness_n_per_m = config.haptic.hand_stiffness_n_per_m
        self.weight_f_n: np.ndarray | None = None  # the held weight the handle renders
        self.task = WorldTask(scene, config.robot.object_bodies, self.tick_s)
        self.view = WorldView()
        self.runs = 0
        self.inputs_sent = 0
        # The buttons of the newest hand input sent: the gripper as the hand left this
        # robot, for a device to take up again when the hand comes back to it.
        self.last_buttons = Button(0)
        self.inputs_held_back = 0  # lockstep: inputs due by the wall clock the run lagged
        self._start_ns: int | None = None
        self._next_sample_tick = 0
        self._next_realtime_ns = 0
        self._held_back_tick = -1
        self.joined_at_tick: int | None = None  # a run joined under way, at this tick
        self._last_tool: tuple[int, np.ndarray] | None = None
        self.tool_start_p_m: np.ndarray | None = None  # the run's first tool pose seen

    # -- what the bus brings -------------------------------------------------------------
    def on_started(self, now_ns: int) -> None:
        """The plant's STARTED: a new run from tick 0."""
        self._begin(0, now_ns)

    def on_tool(self, tick: int, world_p_m: np.ndarray, now_ns: int) -> None:
        """TOOL_POSE at ``tick``, received at ``now_ns``. The first one without a STARTED
        before it is a run under way (this service restarted): the hand inputs take up
        from the newest sample tick, as if the run had started ``tick`` periods ago."""
        if self._start_ns is None:
            self._begin(tick, now_ns)
            self.joined_at_tick = tick
        p = np.array(world_p_m, dtype=np.float64)
        if self._last_tool is not None and tick > self._last_tool[0]:
            dt_s = (tick - self._last_tool[0]) * self.tick_s
            self.view.tool_speed_m_s = float(np.linalg.norm(p - self._last_tool[1])) / dt_s
        self._last_tool = (tick, p)
        if self.tool_start_p_m is None:
            self.tool_start_p_m = p
        self.view.tick = max(self.view.tick, tick)
        self.view.tool_p_m = p

    def _begin(self, tick: int, now_ns: int) -> None:
        """A run from ``tick`` at ``now_ns``: the hand inputs from its newest sample tick,
        the task from reach (what is held shows at the next grasp or release)."""
        self.runs += 1
        self.joined_at_tick = None
        self._start_ns = now_ns - tick * self.tick_ns
        self._next_sample_tick = self.hand_schedule.last_sample(tick)
        self._next_realtime_ns = now_ns
        self._last_tool = None
        self.tool_start_p_m = None
        self.view = WorldView(tick=tick)
        self.task.reset()
        self.task.start(tick, self._emit)
        self.view.phase = self.task.phase

    def on_objects(self, tick: int, objects_p_m: Sequence[np.ndarray]) -> None:
        names = self.config.robot.object_bodies
        pairs = zip(names, objects_p_m, strict=False)  # the record names its first n
        objects = {n: np.array(p, dtype=np.float64) for n, p in pairs}
        self.view.objects_p_m = objects
        self.task.on_objects(tick, objects, self._emit)
        self._sync_view()

    def on_hold(self, holding: bool, tick: int) -> None:
        """The plant's GRASP or RELEASE: shown and counted once settled (WorldTask)."""
        self.task.on_hold(holding, tick)

    def on_force(self, device_f_n: np.ndarray, weight_f_n: np.ndarray) -> None:
        """A FORCE_FEEDBACK's force to render and its held weight's share of it (both as
        the handle renders them, N; the weight is vertical, so the same in the device
        frame as in the world)."""
        self.view.device_f_n = np.array(device_f_n, dtype=np.float64)
        self.weight_f_n = np.array(weight_f_n, dtype=np.float64)

    def end_task(self) -> None:
        """The person ends the run (not a success)."""
        if self._start_ns is not None:
            self.task.finish(False, max(self.view.tick, 0), self._emit)
            self._sync_view()

    def _sync_view(self) -> None:
        task = self.task
        self.view.phase, self.view.done, self.view.success = task.phase, task.done, task.success
        self.view.holding = task.holding

    def _emit(self, event: Event, tick: int, step: int, value: float) -> None:
        self.outputs.event(event, tick, step, value)

    # -- hand inputs ---------------------------------------------------------------------
    def due(self, now_ns: int, intent: HandIntent) -> int:
        """Send the hand inputs due at ``now_ns`` with ``intent``; the time of the next
        one (ns, the clock's), for the caller's wait."""
        if self._start_ns is None:
            return now_ns + self.decision_ns  # no run yet
        target_p_m, buttons = hand_command(intent, self.config.teleop)
        if self.weight_f_n is not None:
            target_p_m = target_p_m - self.weight_f_n / self.hand_stiffness_n_per_m
        if not self.lockstep:
            if now_ns >= self._next_realtime_ns:
                lead = self.hand_schedule.lead_ticks
                self._send(max(self.view.tick, 0) + lead, target_p_m, buttons)
                self._next_realtime_ns += self.decision_ns
                if self._next_realtime_ns <= now_ns:  # a stall: no burst to catch up
                    self._next_realtime_ns = now_ns + self.decision_ns
            return self._next_realtime_ns
        newest = max(self.view.tick, 0)
        while True:
            s = self._next_sample_tick
            due_ns = self._start_ns + s * self.tick_ns
            if due_ns > now_ns:
                return due_ns
            if s + self.hand_schedule.lead_ticks > newest + self.max_ahead_ticks:
                if s != self._held_back_tick:
                    self._held_back_tick = s
                    self.inputs_held_back += 1
                return now_ns + self.decision_ns  # the run lags: wait for its next pose
            self._send(s + self.hand_schedule.lead_ticks, target_p_m, buttons)
            self._next_sample_tick = self.hand_schedule.next_sample(s)

    def _send(self, valid_from_tick: int, target_p_m: np.ndarray, buttons: Button) -> None:
        self.outputs.put_hand(valid_from_tick, target_p_m, buttons)
        self.inputs_sent += 1
        self.last_buttons = buttons

    def take_over(self, previous: PersonLoop) -> None:
        """The hand comes to this robot from ``previous``'s: the hand inputs go on from
        where that loop's left off (its run start, its next sample tick or decision time),
        so the haptic device's stream of hand inputs has no gap and no repeat. A loop
        whose robot's run has not started yet starts with ``previous``'s."""
        if previous._start_ns is None:
            return
        self._start_ns = previous._start_ns
        self._next_sample_tick = previous._next_sample_tick
        self._next_realtime_ns = previous._next_realtime_ns

    def summary(self) -> dict[str, Any]:
        """The task's outcome and phase times, as the scripted operator reports them."""
        task = self.task
        duration_s = None
        if task.start_tick is not None and task.done_tick is not None:
            duration_s = (task.done_tick - task.start_tick) * self.tick_s
        return {
            "phases": [phase.to_json() for phase in task.phase_times],
            "task_done": task.done,
            "success": task.success if task.done else None,
            "failure": "" if task.success or not task.done else "ended by the person",
            "task_duration_s": duration_s,
            "runs": self.runs,
            "joined_at_tick": self.joined_at_tick,
            "hand_inputs_sent": self.inputs_sent,
            "hand_inputs_held_back": self.inputs_held_back,
            # Where the person took the tool (world frame, m): the run's first and last
            # tool poses this operator saw.
            "tool_start_m": _listed(self.tool_start_p_m),
            "tool_end_m": _listed(self.view.tool_p_m),
        }


def _listed(p_m: np.ndarray | None) -> list[float] | None:
    return None if p_m is None else [round(float(v), 6) for v in p_m]


class PersonStation:
    """A person's hand over the robots of a run (``run.robots``), one
    :class:`PersonLoop` per robot (``loops[i]`` plays robot i's task, its outputs
    on robot i's keys): the hand drives one robot at a time, robot 0 first.

    The person switches robots (:meth:`switch`: the device's robot switch); the hand also
    moves on by itself once the driven robot's task is done, to the next robot whose task
    is not (:meth:`move_on`). Either way the device then takes up the gripper as the hand
    last left that robot (:attr:`PersonLoop.last_buttons`), and the hand asks for
    no motion for ``SWITCH_SETTLE_S`` (:attr:`settling`). Hand inputs go out
    from the driven robot's loop only, on the sample-tick grid the previous one left off
    at (:meth:`PersonLoop.take_over`), so the haptic device (which drives the
    robot whose keys the input comes on) sees one unbroken stream. Ending the run ends
    every robot's task. With one robot it is that robot's loop.
    """

    def __init__(self, loops: Sequence[PersonLoop]) -> None:
        if not loops:
            raise ValueError("PersonStation needs a loop per robot")
        self.loops = list(loops)
        self.active = 0  # the robot the hand drives
        self.switches: list[dict[str, int]] = []  # each: the robot left, the one taken, tick
        self._settle_until_tick = -1  # after a switch: no motion before this tick

    @property
    def loop(self) -> PersonLoop:
        """The driven robot's loop."""
        return self.loops[self.active]

    def switch(self) -> bool:
        """The person's robot switch: drive the next robot whose task is not done (in
        order, around). False if there is none other."""
        count = len(self.loops)
        for step in range(1, count):
            robot = (self.active + step) % count
            if not self.loops[robot].task.done:
                self._drive(robot)
                return True
        return False

    def _drive(self, robot: int) -> None:
        previous = self.loop
        tick = max(previous.view.tick, 0)
        self.switches.append({"from": self.active, "to": robot, "tick": tick})
        logger.info("the hand moves from robot %d to robot %d", self.active, robot)
        self.active = robot
        self.loop.take_over(previous)
        self._settle_until_tick = tick + round(SWITCH_SETTLE_S / previous.tick_s)

    @property
    def settling(self) -> bool:
        """After a switch, while the hand asks for no motion (``SWITCH_SETTLE_S``)."""
        return max(self.loop.view.tick, 0) < self._settle_until_tick

    def move_on(self) -> bool:
        """The hand moves on if the driven robot's task is done and another's is not
        (True: it did). Call before reading the device's intent, so the device takes up
        the next robot's gripper first."""
        return self.loop.task.done and self.switch()

    def due(self, now_ns: int, intent: HandIntent) -> int:
        """:meth:`PersonLoop.due` of the driven robot; while :attr:`settling`,
        with the intent's buttons and no motion."""
        if self.settling:
            intent = HandIntent(gripper_closed=intent.gripper_closed, clutch=intent.clutch)
        return self.loop.due(now_ns, intent)

    def end_task(self) -> None:
        """The person ends the run: every robot's task ends (not a success)."""
        for loop in self.loops:
            loop.end_task()

    @property
    def inputs_sent(self) -> int:
        return sum(loop.inputs_sent for loop in self.loops)

    def summary(self, robot_ids: Sequence[str]) -> dict[str, Any]:
        """The task's outcome (:meth:`PersonLoop.summary`): with one robot its
        loop's; with several, a section per robot id under ``robots`` and the switches."""
        if len(self.loops) == 1:
            return self.loops[0].summary()
        return {
            "robots": {
                rid: loop.summary() for rid, loop in zip(robot_ids, self.loops, strict=True)
            },
            "robot_switches": list(self.switches),
        }
