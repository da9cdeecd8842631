"""The scripted operator's decision loop on sim time, and the station that drives several
robots with one hand.

:class:`ScriptedLoop` is the whole operator minus the bus (``services/operator.py``
feeds it and publishes what it sends): decisions at ``operator.decision_rate_hz`` on the
plant's ticks, each from what :class:`teleop.devices.scripted.operator.ScriptedOperator`
saw a reaction time before. :class:`ScriptedStation` plays each robot's task in turn.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple, Protocol

from teleop.bus.messages import Event
from teleop.core.config import (
    Config,
    ConfigError,
)
from teleop.core.summary import PhaseTime
from teleop.core.ticks import hand_schedule, head_schedule, scene_schedule
from teleop.devices.scripted.operator import HandCommand, ObservationBuffer, ScriptedOperator
from teleop.devices.scripted.routing import SceneKnowledge
from teleop.devices.scripted.scenario import Scenario

logger = logging.getLogger(__name__)

# --- The decision loop, on sim time --------------------------------------------------------

# TASK_DONE names a tick this far ahead of the arrival that ends the task: the plant
# (in lockstep, waiting at that arrival's tick at most) finishes the run there exactly.
TASK_DONE_AHEAD_TICKS = 100
# Lockstep: longest wait for an observation's samples before deciding with what is there (s).
LOCKSTEP_INPUT_WAIT_S = 1.0


class ScriptedOutputs(Protocol):
    """Where :class:`ScriptedLoop` sends what it decides (the service: its publishers)."""

    def hand(self, valid_from_tick: int, command: HandCommand) -> None:
        """A HAND_INPUT that applies from ``valid_from_tick``."""

    def event(self, event: Event, tick: int, step: int, value: float) -> None:
        """A RUN_EVENT decided at ``tick``; ``step`` is the tick it names (see Event)."""


class ScriptedLoop:
    """The scripted operator on plant ticks: which decisions a TOOL_POSE arrival triggers,
    what they publish, and the run boundaries. No bus and no thread of its own.

    The arrival of the TOOL_POSE of tick ``m`` (:meth:`on_arrival`, in arrival order)
    triggers one decision for every sample tick ``s`` of the operator's clock
    (:func:`teleop.core.ticks.is_sample_tick` at ``decision_rate_hz``) in ``(previous
    arrival, m]``, sent with ``valid_from_tick = s + lead_ticks`` (``lead_ticks = 1 /
    (rate timestep)``): exactly the records the haptic device waits for. A decision rate
    above the scene rate would need a record before the TOOL_POSE that triggers it exists,
    which deadlocks lockstep, so it is a config error.

    Lockstep determinism: a decision uses only tick-stamped samples, the newest at or before
    ``s - reaction_delay`` (:class:`ObservationBuffer`, filled by the caller). Before
    deciding it waits (event driven, at most ``LOCKSTEP_INPUT_WAIT_S``) until that
    observation is complete: the OBJECT_POSES of the observed tool tick and, once an HMD is
    known to be in the run (:meth:`hmd_seen`), the HEAD_POSE whose ``valid_from_tick``
    applies at the observed tick. Without an HMD the view yaw is ``hmd.head_yaw_rad``.

    A new run (a TOOL_POSE at tick 0, or :meth:`on_started` for the plant's STARTED
    event) resets the operator; a tick not newer than the last one is a plant re-send and
    is ignored.

    An operator whose first TOOL_POSE is past tick 0 joined a run under way (it was
    restarted): its first look takes the task up where the world is
    (:func:`resume_phase`), and until it has seen anything (one reaction delay) it sends
    no hand input: the haptic device holds the handle still with its predecessor's
    buttons meanwhile (``haptic.hand_input_stale_s``), where a guess would open the
    gripper. Lockstep decisions do not wait for observations older than its first pose.

    ``scene``: what the operator knows of the scene's fixed geometry (default: read from
    the config's scene file and ``scene.*`` placements, as the plant places them).
    """

    def __init__(
        self,
        config: Config,
        scenario: Scenario,
        outputs: ScriptedOutputs,
        *,
        lockstep: bool,
        scene: SceneKnowledge | None = None,
    ) -> None:
        # Across an emulated link (site.emulated_round_trip_ms) the robot's site's scene
        # comes its way back later: the operator sees it that much later, and its hand
        # takes the gain of the longer delay, as a person slows down to a late picture.
        _, back_ticks = config.link_delay_ticks()
        if back_ticks:
            seen_s = config.operator.reaction_delay_s + back_ticks * config.tick_s
            config = dataclasses.replace(
                config, operator=dataclasses.replace(config.operator, reaction_delay_s=seen_s)
            )
        self.tick_s = config.tick_s
        self.hand_schedule = hand_schedule(config)
        rate_hz = self.hand_schedule.rate_hz
        if rate_hz > config.plant.scene_rate_hz:
            raise ConfigError(
                f"operator.decision_rate_hz ({rate_hz:g}) above plant.scene_rate_hz "
                f"({config.plant.scene_rate_hz:g}): decisions are driven by TOOL_POSE arrivals"
            )
        self.lockstep = lockstep
        # Lockstep: how far the newest TOOL_POSE can be ahead of the last one decided while
        # the haptic device waits for this operator's hand inputs (a hand input applies
        # for a decision period from a decision period ahead, and poses come every scene
        # period), with a scene period to spare. A pose further ahead means the run went
        # on without this operator (a restart, or the device gave up waiting for it).
        scene_ticks = scene_schedule(config).gap_ticks
        self.lockstep_lag_ticks = 3 * self.hand_schedule.lead_ticks + 2 * scene_ticks
        # Realtime: poses that stopped coming for longer than the device keeps a hand
        # input (a link cut, a stalled plant) froze the view; see on_arrival.
        self.frozen_view_ticks = round(config.haptic.hand_input_stale_s / self.tick_s)
        self.delay_ticks = round(config.operator.reaction_delay_s / self.tick_s)
        self.head_schedule = head_schedule(config)
        self.scenario = scenario
        self.outputs = outputs
        self.operator = ScriptedOperator(
            scenario,
            config.operator,
            config.teleop,
            config.haptic,
            self.tick_s,
            scene=scene if scene is not None else SceneKnowledge.from_config(config),
        )
        self.buffer = ObservationBuffer(
            config.robot.object_bodies, self.delay_ticks, config.hmd.head_yaw_rad
        )
        self._hmd_present = threading.Event()  # set from any thread, read by the loop's
        self._last_tick: int | None = None  # newest TOOL_POSE tick handled in this run
        self._phase_reported = -1
        self._done_reported = False
        self.runs = 0
        self.decisions = 0
        self.late_observations = 0  # lockstep waits that timed out
        self.duplicate_poses = 0  # TOOL_POSE re-sends (same tick) ignored
        self._joined_tick: int | None = None  # first TOOL_POSE tick of a run joined late
        self.withheld_inputs = 0  # joined: decisions made before anything was seen
        self.skipped_decisions = 0  # realtime: sample ticks a late operator skipped
        self.frozen_views = 0  # realtime: poses that came after a frozen view
        self.phase_times: list[PhaseTime] = []

    def hmd_seen(self) -> None:
        """An HMD is in the run (its liveliness token or a HEAD_POSE): lockstep decisions
        wait for its head pose from now on."""
        self._hmd_present.set()

    def on_started(self) -> None:
        """The plant's STARTED event: a new run, unless this run's first pose came first."""
        if self._last_tick not in (None, 0):
            self._new_run()

    def _new_run(self) -> None:
        self.operator.reset()
        self._joined_tick = None
        self._last_tick = None
        self._phase_reported = -1
        self._done_reported = False
        self.phase_times = []
        self.runs += 1
        logger.info("new run: operator reset")

    @property
    def done_reported(self) -> bool:
        """Whether this run's TASK_DONE has gone out."""
        return self._done_reported

    def take_over(self, tick: int) -> None:
        """Take the hand over after tick ``tick`` (another robot's last decided pose, in
        a run of several robots driven in turn): the next arrival decides from the
        sample tick after ``tick`` on, this task starting at phase 0 then. What this
        operator decides on was observed meanwhile (its buffer is filled all along)."""
        self._last_tick = tick

    def left_behind(self, m: int) -> bool:
        """Whether the TOOL_POSE of tick ``m`` shows the run going on without this
        operator: realtime, always decide on the newest pose; lockstep, only once a pose
        is further ahead of the last one decided than a device waiting for this
        operator lets the plant go (``lockstep_lag_ticks``: never in a run the device
        waited through, so lockstep stays deterministic)."""
        if not self.lockstep:
            return True
        return self._last_tick is not None and m - self._last_tick > self.lockstep_lag_ticks

    def on_arrival(self, m: int, catch_up: bool = False) -> None:
        """The TOOL_POSE of tick ``m`` is in the buffer: decide every sample tick up to it.

        ``catch_up`` (a late operator whose caller skipped the poses queued before this
        one, see :meth:`left_behind`): decide only the newest sample tick, never a burst
        of decisions whose hand inputs would all be late (see
        ScriptedOperator._after_hold). The same in realtime after a frozen view (no pose
        for longer than ``frozen_view_ticks``: the link was cut, the plant stalled): a
        person who saw nothing new decided nothing meanwhile, and a burst over the frozen
        stretch would judge the tool's progress on a picture that did not move."""
        if m == 0 and self._last_tick != 0:
            self._new_run()
        elif self._last_tick is not None and m <= self._last_tick:
            self.duplicate_poses += 1  # a plant re-send of a state nobody answered yet
            return
        if self._last_tick is None:
            first = self.hand_schedule.last_sample(m)
            if m > 0 and self.operator.phase < 0 and not self.operator.done:
                self._joined_tick = m
                self.operator.joining = True
                logger.info("joined a run under way at tick %d (a restart)", m)
        elif catch_up or (not self.lockstep and m - self._last_tick > self.frozen_view_ticks):
            if not catch_up:
                self.frozen_views += 1
            first = max(self._last_tick + 1, self.hand_schedule.last_sample(m))
            self.skipped_decisions += sum(
                self.hand_schedule.is_sample(s) for s in range(self._last_tick + 1, first)
            )
        else:
            first = self._last_tick + 1
        self._last_tick = m
        for s in range(first, m + 1):
            if self.hand_schedule.is_sample(s):
                self._decide(s, m)

    def _decide(self, s: int, m: int) -> None:
        """One decision at sample tick ``s`` (triggered by the TOOL_POSE of tick ``m``)."""
        seen = s - self.delay_ticks
        unseen = self._joined_tick is not None and seen < self._joined_tick
        if self.lockstep and not unseen:
            head_from = None
            if self._hmd_present.is_set() and seen >= 0:
                head_from = self.head_schedule.valid_from_for(seen)
            if not self.buffer.wait_ready(s, head_from, LOCKSTEP_INPUT_WAIT_S):
                self.late_observations += 1
        command = self.operator.decide(s, self.buffer.observe(s))
        self.decisions += 1
        if unseen and command.phase < 0:
            self.withheld_inputs += 1  # nothing of this run seen yet: no hand to give
            return
        self.outputs.hand(s + self.hand_schedule.lead_ticks, command)
        if command.phase != self._phase_reported and command.phase >= 0:
            self._phase_reported = command.phase
            name = self.scenario.phases[command.phase].name
            self.phase_times.append(PhaseTime(command.phase, name, s * self.tick_s))
            self.outputs.event(Event.PHASE, s, s, float(command.phase))
        for event, value in self.operator.events:
            self.outputs.event(event, s, s, value)
        self.operator.events.clear()
        if command.done and not self._done_reported:
            self._done_reported = True
            finish_tick = m + TASK_DONE_AHEAD_TICKS
            self.outputs.event(Event.TASK_DONE, s, finish_tick, float(command.success))
            logger.info(
                "task done at %.2f s: %s %s",
                s * self.tick_s,
                "success" if command.success else "gave up",
                self.operator.failure,
            )

    def summary(self) -> dict[str, Any]:
        """The task's outcome, phase times and decision counters (JSON-ready)."""
        op = self.operator
        duration_s = None
        if op.task_start_tick is not None and op.done_tick is not None:
            duration_s = (op.done_tick - op.task_start_tick) * self.tick_s
        return {
            "scenario": self.scenario.source,
            "phases": [phase.to_json() for phase in self.phase_times],
            "task_done": op.done,
            "success": op.success if op.done else None,
            "failure": op.failure,
            "routes": op.routes,
            "task_duration_s": duration_s,
            "gain_per_s": op.gain_per_s,
            "decisions": self.decisions,
            "late_observations": self.late_observations,
            "duplicate_poses": self.duplicate_poses,
            "runs": self.runs,
            "resumed": op.resumed,  # a restarted operator: where it took the task up
            "withheld_inputs": self.withheld_inputs,
            "skipped_decisions": self.skipped_decisions,
            "frozen_views": self.frozen_views,
            "hand_holds": op.hand_holds,
            "device_gone_decisions": op.device_gone_decisions,
        }


# --- Several robots, one hand ---------------------------------------------------------------


class PoseArrival(NamedTuple):
    """A TOOL_POSE of ``robot`` at plant tick ``tick``, sampled at ``sampled_ns``."""

    robot: int
    tick: int
    sampled_ns: int


class RunStarted(NamedTuple):
    """``robot``'s plant started a run (its STARTED event)."""

    robot: int


Arrival = PoseArrival | RunStarted


class ScriptedStation:
    """One scripted operator's hand over the robots of a run (``run.robots``), one task
    per robot, in turn: :class:`ScriptedLoop` ``loops[i]`` plays robot i's task (its
    outputs go out on robot i's keys). The hand drives robot 0 until its TASK_DONE is
    out, then the next robot's task starts where the last decision left off
    (:meth:`ScriptedLoop.take_over`). Every robot's scene is observed all along (the
    caller fills each loop's buffer); only the driven robot's poses trigger decisions.
    With one robot it is that robot's loop, as the service always was.
    """

    def __init__(self, loops: Sequence[ScriptedLoop]) -> None:
        self.loops = list(loops)
        self.active = 0  # the robot the hand drives

    @property
    def loop(self) -> ScriptedLoop:
        """The driven robot's loop."""
        return self.loops[self.active]

    def take(self, items: Sequence[Arrival], decided: Callable[[int], None] | None = None) -> None:
        """One batch of arrivals, in order: the driven robot's poses decided (``decided``
        gets each one's sample stamp), a new run started over on robot 0, the hand passed
        on once the driven robot's task is done.

        A late operator (realtime: poses queued behind a newer one; lockstep: a run that
        went on without it, :meth:`ScriptedLoop.left_behind`) decides on the newest pose
        only and skips the rest: it catches up by skipping, never by a burst of late hand
        inputs. Lockstep otherwise decides every one (the haptic device waits for each)."""
        loop = self.loop
        poses = [item for item in items if isinstance(item, PoseArrival)]
        driven = [pose for pose in poses if pose.robot == self.active]
        behind = bool(driven) and loop.left_behind(driven[-1].tick)
        catch_up = behind and (len(driven) > 1 or loop.lockstep)
        for i, item in enumerate(items):
            if isinstance(item, RunStarted):
                self.loops[item.robot].on_started()
                if item.robot == 0 and self.active:
                    self.active = 0  # a new run: robot 0's task first again
                    self.take(items[i + 1 :], decided)
                    return
                continue
            if item.robot != self.active:
                continue  # observed (buffered), not driven
            later = items[i + 1 :]
            if behind and any(isinstance(x, PoseArrival) and x.robot == item.robot for x in later):
                continue  # a newer pose is queued behind it
            if decided is not None:
                decided(item.sampled_ns)
            loop.on_arrival(item.tick, catch_up=catch_up)
            if loop.done_reported and self.active + 1 < len(self.loops):
                self.active += 1
                self.loop.take_over(item.tick)
                logger.info("tick %d: the hand moves on to robot %d", item.tick, self.active)
                self.take(later, decided)  # what came after, for the robot driven now
                return

    def summary(self, robot_ids: Sequence[str]) -> dict[str, Any]:
        """The task's outcome (:meth:`ScriptedLoop.summary`): with one robot its loop's;
        with several, one section per robot id under ``robots``."""
        if len(self.loops) == 1:
            return self.loops[0].summary()
        return {
            "robots": {rid: loop.summary() for rid, loop in zip(robot_ids, self.loops, strict=True)}
        }
