"""The plant's loop as pure code: MuJoCo stepped at 1 kHz in realtime or lockstep.

:class:`PlantLoop` takes the JOINT_COMMAND records the plant service receives, steps the
:class:`teleop.sim.plant.Plant`, and hands every record it fills (PLANT_STATE, TOOL_POSE,
OBJECT_POSES, RUN_EVENT) to :class:`PlantOutputs`. Time comes from an injected
:class:`teleop.core.clock.Clock`, so a test drives it on a fake clock without Zenoh;
``services/plant.py`` is the bus adapter around it. One code path, three pacings:

- realtime, plant tick: a :class:`LoopTimer` paces the steps, one per period on average,
  after a stall skipping ticks, never bursting; each step applies the newest command.
- realtime, apply on arrival (teleoperation with ``plant.apply_on_arrival``): each command
  enters a step the moment it arrives, in the Zenoh callback; the steps follow the haptic
  device's clock, one per device period (:class:`DeviceClockGrid`), so a command never
  waits for the plant's tick, and a period without a command is stepped with the last one.
- lockstep: the plant publishes a state and steps when the command that answers it
  (``state_seq``) arrives, inside the command callback, so a cycle costs no thread
  hand-off: deterministic, as fast as plant + controller allow.

In both realtime pacings one :class:`Watchdog` decides: it brakes (holds the arm where it
is) when the command to apply answers a state older than ``plant.watchdog_s``, and
resumes as soon as a fresh command arrives.

Published every step: PLANT_STATE, one record that also carries the contact on the
gripper and the closest obstacle. In teleoperation those are computed every step (they
feed the 1 kHz force feedback); otherwise only every ``1 / scene_rate_hz`` (their cost),
and ``interaction_step`` says when. Every ``1 / scene_rate_hz``: TOOL_POSE,
OBJECT_POSES. On start, finish, grasp, release and watchdog changes: RUN_EVENT.
"""

from __future__ import annotations

import collections
import enum
import functools
import logging
import math
import threading
import time
from dataclasses import asdict, dataclass, field
from typing import Any, NamedTuple, Protocol

import numpy as np

from teleop.bus.messages import OBJECT_POSES, PLANT_STATE, RUN_EVENT, TOOL_POSE, Event, Flag, Stage
from teleop.bus.session import Latest
from teleop.bus.stamps import Inbound
from teleop.core.clock import NS_PER_S, Clock, LoopTimer
from teleop.core.config import LOCKSTEP_RESEND_S, Config
from teleop.sim.checkpoint import (
    FRESH_HEADER,
    SLOT_COMMAND_SEQ,
    SLOT_FINISH_TICK,
    SLOT_STATE_NS,
    SLOT_STATE_SEQ,
    CheckpointError,
    CheckpointStore,
    Progress,
    Snapshot,
    model_id,
)
from teleop.sim.contact import finger_bodies, held_mass_kg, held_object
from teleop.sim.plant import Plant, initial_configuration
from teleop.sim.proximity import FAR_DISTANCE_M, ObstacleProximity, ProximitySample

logger = logging.getLogger(__name__)


class Abort(enum.IntEnum):
    """Why the plant ended a run on a failure: the value of its ABORTED event."""

    RESUME_FAILED = 1  # restarted, but its checkpoint could not be resumed
    LOCKSTEP_TIMEOUT = 2  # lockstep: no answer to the pending state within the bound


# Apply on arrival: a device period whose command has not come this many periods after
# the period began is stepped without it (with the last command, or braking). A command
# normally reaches the plant well within a period or two of its handle sample (see
# docs/latency.md); one that comes after its period was stepped is merged into the next
# step instead of taking one of its own.
OWN_STEP_AFTER_PERIODS = 2
# Apply on arrival: periods stepped back to back at most to catch up (periods before a
# command that got none, or the run thread after a stall); older ones are skipped, never
# run in a burst.
CATCH_UP_MAX_PERIODS = 2
# Apply on arrival: a command this many periods away from the plant's next one (either
# way) means the device's clock started over (a restarted haptic service): re-lock to it.
RELOCK_PERIODS = 1000


class DeviceClockGrid:
    """The realtime plant's steps on the haptic device's clock (times in ns, monotonic).

    The device samples the handle on absolute deadlines ``t0 + k * period`` of the host's
    monotonic clock, and each teleoperation command carries the deadline of the period
    whose sample it answers (``device_deadline_ns``). The plant takes exactly one step
    per device period, as a fieldbus slave follows the master's distributed clock:
    ``next_ns`` is the period of the next step. A command for that period steps at once;
    one for a later period first steps the periods in between, which got no command
    (shed upstream or skipped by the device), with the last command; one for a period
    already stepped is late and only becomes the command held for the next step. A
    period without a command is stepped by the plant's own thread
    ``OWN_STEP_AFTER_PERIODS`` periods after it began. So commands never wait for a
    window, sim time stays on the device's clock (no drift either way), and the plant
    still keeps wall-clock time when no command comes at all.

    Before the first command the grid runs from ``start_ns``; :meth:`lock` puts the
    next step on the first command's period. Pure arithmetic, no clock of its own.
    """

    def __init__(self, period_ns: int, start_ns: int) -> None:
        if period_ns <= 0:
            raise ValueError(f"period_ns must be > 0, got {period_ns}")
        self.period_ns = period_ns
        self.next_ns = start_ns  # start of the device period the next step covers
        self.skipped = 0  # periods never stepped (stalls longer than the catch-up)
        self.locks = 0  # times the grid (re-)locked to a command's period

    @property
    def locked(self) -> bool:
        return self.locks > 0

    def lock(self, deadline_ns: int) -> None:
        """The next step covers the device period that starts at ``deadline_ns``."""
        self.next_ns = deadline_ns
        self.locks += 1

    def periods_ahead(self, deadline_ns: int) -> int:
        """Periods from the next step's to the one starting at ``deadline_ns`` (negative:
        already stepped)."""
        return round((deadline_ns - self.next_ns) / self.period_ns)

    @property
    def own_step_ns(self) -> int:
        """When the plant steps the next period itself if no command came for it."""
        return self.next_ns + OWN_STEP_AFTER_PERIODS * self.period_ns

    def stepped(self) -> None:
        """The next period was stepped."""
        self.next_ns += self.period_ns

    def skip(self, periods: int) -> None:
        """Give up ``periods`` periods without stepping them (a stall)."""
        self.skipped += periods
        self.next_ns += periods * self.period_ns


# Lockstep cycle breakdown: the newest cycles kept (a ring; 60 s of lockstep fits).
CYCLE_STATS_CAPACITY = 1 << 16
# Checkpoint writes whose duration the summary keeps (the newest ones).
CHECKPOINT_COST_SAMPLES = 1000


class LockstepCycleStats:
    """Where a lockstep cycle's wall time goes, from the stamps the records carry.

    One cycle: the plant sends state k (``PLANT_STATE_TX``), the controller receives
    it and answers (``CONTROLLER_RX``, ``CONTROLLER_TX``), the plant receives the
    command (``PLANT_RX``), steps (``PLANT_APPLIED``) and sends state k + 1 + d (d:
    ``plant.lockstep_delay_steps``). All stamps are this host's monotonic clock, so the
    segments are exact and add up to the cycle. With d states in flight besides the
    pending one, the plant's ``period`` (between two states sent) is about the cycle
    divided by d + 1 when neither plant nor controller is the bottleneck.
    """

    SEGMENTS = ("to_controller", "controller", "to_plant", "plant_rx", "plant_step")

    def __init__(self, capacity: int = CYCLE_STATS_CAPACITY) -> None:
        self._stamps_ns = np.zeros((capacity, len(self.SEGMENTS) + 1), dtype=np.int64)
        self._count = 0

    _STAGES = [Stage.CONTROLLER_RX, Stage.CONTROLLER_TX, Stage.PLANT_RX, Stage.PLANT_APPLIED,
               Stage.PLANT_STATE_TX]  # fmt: skip

    def add(self, answered_state_tx_ns: int, trace_ns: np.ndarray) -> None:
        """Record one cycle from the new state's stamps (they include the command's)."""
        row = self._stamps_ns[self._count % len(self._stamps_ns)]
        row[0] = answered_state_tx_ns
        row[1:] = trace_ns[self._STAGES]
        self._count += 1

    def summary(self) -> dict[str, float]:
        """Median microseconds of each segment and of the whole cycle ({} if none)."""
        rows = self._stamps_ns[: min(self._count, len(self._stamps_ns))]
        rows = rows[(rows > 0).all(axis=1)]
        if not len(rows):
            return {}
        segments_us = np.diff(rows, axis=1) / 1e3
        medians = np.median(segments_us, axis=0)
        result = {name: round(float(m), 1) for name, m in zip(self.SEGMENTS, medians, strict=True)}
        result["cycle"] = round(float(np.median(rows[:, -1] - rows[:, 0]) / 1e3), 1)
        if len(rows) > 1:
            sent_ns = np.sort(rows[:, -1])
            result["period"] = round(float(np.median(np.diff(sent_ns))) / 1e3, 1)
        return result


class Judgement(NamedTuple):
    """The watchdog's word on one step: apply the command or brake, and the event (with
    its value) to announce first, if the watchdog changed its mind."""

    apply: bool
    event: Event | None = None
    value: float = 0.0


# States whose send time the watchdog remembers (a ring): 4 s at 1 kHz, far beyond any
# watchdog limit; a command answering an older state is stale whatever the limit.
STATE_HISTORY = 4096


class Watchdog:
    """The plant's command watchdog: the one brake/resume decision of every realtime step.

    Judged on the plant's own clock and its own state numbering, never on a sender's
    stamps: a command answering state k is fresh while k is the newest state the plant
    sent, or while state k + 1 (the first the sender has not answered) went out less than
    ``limit_ns - period_ns`` ago: at the steady pace, less than ``limit_ns`` after state
    k. A command answering k arrives after k went out, so the plant brakes within
    ``limit_ns`` of the last fresh command (the first step at or past the limit brakes),
    and a plant that stalls itself does not brake on its own delay (k + 1 goes out late).
    A step with a stale command (or none yet) brakes; the first stale step after fresh
    ones announces WATCHDOG_BRAKE with the answered state's age (s), the first fresh one
    after braking WATCHDOG_RESUME.
    """

    def __init__(self, limit_ns: int, period_ns: int, history: int = STATE_HISTORY) -> None:
        if not 0 < period_ns < limit_ns:
            raise ValueError(f"need 0 < period_ns < limit_ns, got {period_ns}, {limit_ns}")
        self.limit_ns = limit_ns
        self.period_ns = period_ns
        self.braking = False
        self.brakes = 0  # times it started braking on a stale command
        self.stale_steps = 0  # steps braked on a stale command (not before the first one)
        self._sent_seq = np.full(history, -1, dtype=np.int64)
        self._sent_ns = np.zeros(history, dtype=np.int64)
        self.newest_seq = -1

    def reset(self) -> None:
        """A new run: not braking (the counters keep counting)."""
        self.braking = False

    def state_sent(self, seq: int, now_ns: int) -> None:
        """The plant sent state ``seq`` at ``now_ns``."""
        slot = seq % len(self._sent_seq)
        self._sent_seq[slot] = seq
        self._sent_ns[slot] = now_ns
        self.newest_seq = seq

    def sent_ns(self, seq: int) -> int | None:
        """When state ``seq`` was sent (None: not sent, or too long ago to remember)."""
        slot = seq % len(self._sent_seq)
        return int(self._sent_ns[slot]) if self._sent_seq[slot] == seq else None

    def overdue_ns(self, answered_seq: int, now_ns: int) -> int:
        """How long the sender of a command answering ``answered_seq`` has had a newer
        state without answering it, plus the period it had to answer the one it did
        (0: it answers the newest)."""
        if answered_seq >= self.newest_seq:
            return 0
        sent_ns = self.sent_ns(answered_seq + 1)
        if sent_ns is None:
            return np.iinfo(np.int64).max
        return now_ns - sent_ns + self.period_ns

    def judge(self, command: np.ndarray | None, now_ns: int) -> Judgement:
        """Apply ``command`` at the step about to be taken at ``now_ns``, or brake?"""
        if command is None:
            return Judgement(False)
        answered = int(command["state_seq"])
        if self.overdue_ns(answered, now_ns) < self.limit_ns:
            if self.braking:
                self.braking = False
                return Judgement(True, Event.WATCHDOG_RESUME)
            return Judgement(True)
        self.stale_steps += 1
        if self.braking:
            return Judgement(False)
        self.braking = True
        self.brakes += 1
        sent_ns = self.sent_ns(answered)
        age_s = (now_ns - sent_ns) / NS_PER_S if sent_ns is not None else math.inf
        return Judgement(False, Event.WATCHDOG_BRAKE, age_s)


class PlantOutputs(Protocol):
    """Where :class:`PlantLoop` sends its records (the service: the bus)."""

    def put(self, stream: str, rec: np.ndarray) -> bytes:
        """Send ``rec`` on ``stream`` (a Topics attribute: plant_state, tool_pose,
        objects, plant_events); the bytes sent."""
        ...

    def put_bytes(self, stream: str, data: bytes) -> None:
        """Send bytes already encoded (a lockstep re-send) on ``stream``."""
        ...

    def flush(self) -> None:
        """The run's last states are out: hand observers what is still batched."""
        ...


@dataclass
class PlantFigures:
    """Figures of merit over the run (world frame, SI)."""

    max_contact_force_n: float = 0.0
    min_obstacle_clearance_m: float = math.inf
    max_tool_speed_m_s: float = 0.0


@dataclass
class ArrivalCounts:
    """What happened to the commands of the apply-on-arrival pacing."""

    steps_on_arrival: int = 0  # steps a command started the moment it arrived
    steps_without_command: int = 0  # device periods stepped without a new command
    stalls: int = 0  # times the plant fell behind by more than the catch-up (skipped)
    commands_late: int = 0  # came after their period was stepped: merged into the next
    commands_stale: int = 0  # arrived too old to apply (the watchdog brakes instead)


@dataclass
class CheckpointCost:
    """What the checkpoints cost the plant's steps."""

    taken: int = 0
    failed: int = 0
    step_us: list[float] = field(default_factory=list)  # the newest ones

    def add(self, duration_ns: int) -> None:
        self.taken += 1
        self.step_us.append(duration_ns / 1e3)
        del self.step_us[:-CHECKPOINT_COST_SAMPLES]

    def summary(self, steps: int, store: CheckpointStore | None) -> dict[str, Any]:
        """Checkpoints taken (and failed), bytes each, the time each took from its step
        (p50 / max, us) and that time spread over every step (us)."""
        times = np.array(self.step_us) if self.step_us else np.zeros(1)
        return {
            "taken": self.taken,
            "failed": self.failed,
            "bytes_per_checkpoint": store.bytes_per_write if store is not None else 0,
            "us_p50": round(float(np.median(times)), 1),
            "us_max": round(float(times.max()), 1),
            "us_per_step": round(float(times.mean()) * self.taken / max(steps, 1), 3),
        }


class PlantLoop:
    """The plant's stepping, pacing and publishing, driven by commands and a clock.

    Thread safety: the realtime tick pacing runs on the caller's thread only; the
    apply-on-arrival and lockstep pacings step from the command callback too, under
    ``cond`` / ``lock`` (held by :meth:`on_command` and the run loops).

    With a ``store`` (teleop.sim.checkpoint) the loop checkpoints itself every
    ``plant.checkpoint_s`` of sim time and marks its progress every step; a run that
    finds a checkpoint there resumes from it (:meth:`resume`) instead of starting over,
    or, if it cannot, ends at once with an ABORTED event (:attr:`failure` says why).
    """

    def __init__(
        self,
        config: Config,
        outputs: PlantOutputs,
        clock: Clock,
        store: CheckpointStore | None = None,
    ) -> None:
        self.config = config
        self.outputs = outputs
        self.clock = clock
        plant_cfg = config.plant
        self.plant = Plant(config)
        self.period_ns = self.plant.timestep_ns
        self.scene_every_steps = max(
            1, round(1.0 / (plant_cfg.scene_rate_hz * plant_cfg.timestep_s))
        )
        # Contact and obstacle proximity feed the 1 kHz force feedback of teleoperation;
        # otherwise only the recorder reads them, at the scene rate (computing them costs
        # the plant a contact scan and a narrow-phase distance query per step).
        teleoperated = config.run.scenario == "grasp"
        self.interaction_every_steps = 1 if teleoperated else self.scene_every_steps
        self.lockstep = config.run.mode == "lockstep"
        # In teleoperation the haptic device's clock paces the commands; in path following
        # each command answers the plant's own state, so the plant's tick is the loop's only
        # clock and the newest command is the one to apply.
        self.apply_on_arrival = plant_cfg.apply_on_arrival and teleoperated and not self.lockstep
        # Realtime: the control-free half of the next step while the command is on its way.
        # Not in lockstep: there the state's send would wait behind it.
        self.prepare_ahead = not self.lockstep
        self.watchdog = Watchdog(round(plant_cfg.watchdog_s * NS_PER_S), self.period_ns)
        # Step k applies the command answering state k - delay_steps (PlantConfig).
        self.delay_steps = plant_cfg.lockstep_delay_steps
        self.proximity = ObstacleProximity(self.plant.model, self.plant.data, config.robot)
        self._fingers = finger_bodies(self.plant.model, config.robot)
        self._state = PLANT_STATE.new()
        self._state["held_body"] = -1  # nothing held, no obstacle in reach (until computed)
        self._state["obstacle_geom"] = -1
        self._state["arm_body"] = -1
        self._state["distance_m"] = FAR_DISTANCE_M
        self._tool = TOOL_POSE.new()
        # A step braked since the last TOOL_POSE: the next one carries Flag.BRAKING (the
        # operator, who sees the tool at the scene rate, then knows it was held).
        self._braked_since_scene = False
        self._objects = OBJECT_POSES.new()
        self._event = RUN_EVENT.new()
        self.figures = PlantFigures()
        self.arrival = ArrivalCounts()
        # JOINT_COMMAND order, age and shed log; every command is admitted here first
        self.command_in = Inbound(Stage.CONTROLLER_TX, name="joint_command")
        self._admit_lock = threading.Lock()  # commands come on Zenoh's threads
        self.commands_received = 0
        self.commands_future_state = 0  # answering a state the plant has not sent
        self._warned_future_state = False
        self.commands = Latest()  # realtime tick pacing: the newest command
        self.cycle_stats = LockstepCycleStats()
        self.timer: LoopTimer | None = None
        self.grid: DeviceClockGrid | None = None
        # Lockstep: what was sent for each state in flight (stream, bytes), for a re-send.
        self._sent_ticks: collections.deque[list[tuple[str, bytes]]] | None = None
        if self.lockstep:
            self._sent_ticks = collections.deque(maxlen=self.delay_steps + 1)
        self.lock = threading.Lock()  # lockstep: the run thread and the command callback
        self.cond = threading.Condition()  # apply on arrival: likewise
        self.state_seq = -1
        self.commands_applied = 0
        self.unanswered_commands = 0  # lockstep: commands answering another state
        self.finish_tick: int | None = None  # the operator's TASK_DONE (None: duration)
        self.finished = False
        self.wall_s = 0.0
        self._steps: int | None = None  # the run's length in steps (None: until stopped)
        self._closest: tuple[int, ProximitySample | None] = (-1, None)  # (step, ahead)
        self._held_body = -1
        self._held_command: np.ndarray | None = None
        self._last_applied_seq = -1
        self._lockstep_running = False
        self._lockstep_done = threading.Event()
        self._last_step_ns = 0  # lockstep: when the plant last stepped (the wait's bound)
        self._lockstep_timeout_ns = round(plant_cfg.lockstep_timeout_s * NS_PER_S)
        self._arrival_running = False
        # Checkpoints and the progress marks (teleop.sim.checkpoint); in memory without a store.
        self.store = store
        self.marks = store.marks if store is not None else np.array(FRESH_HEADER, dtype=np.int64)
        self.checkpoint_every_steps = 0
        if store is not None and plant_cfg.checkpoint_s > 0:
            period_steps = round(plant_cfg.checkpoint_s / plant_cfg.timestep_s)
            self.checkpoint_every_steps = max(1, period_steps)
        self.checkpoint_cost = CheckpointCost()
        self.resumes: list[dict[str, Any]] = []  # one per restart this run went through
        self._run_start_ns = 0  # the run's start (host monotonic clock, across restarts)
        self.aborted = False
        self.failure: str | None = None  # why the run was aborted

    @functools.cached_property
    def model_id(self) -> str:
        """The compiled model's hash: a checkpoint resumes only into the same model."""
        return model_id(self.plant.model)

    # -- inputs --------------------------------------------------------------------------
    def on_command(self, rec: np.ndarray, rx_ns: int) -> None:
        """A JOINT_COMMAND for this arm arrived at ``rx_ns``: admitted (:meth:`admit`),
        then stepped with now (lockstep, apply on arrival) or kept for the next tick."""
        if not self.admit(rec):
            return
        if self._lockstep_running:
            self._lockstep_cycle(rec, rx_ns)
        elif self._arrival_running:
            self._arrival_command(rec, rx_ns)
        else:
            self.commands(rec, rx_ns)

    def admit(self, rec: np.ndarray) -> bool:
        """Whether a command may steer the arm at all, whatever its sender claims: it
        answers a state this plant has sent (``state_seq``), its send stamp is not in this
        host's future, its ``seq`` is in order within the window (a restarted controller
        is taken up, :class:`teleop.bus.stamps.SeqCheck`), and, applied on arrival, it is
        not a backlog (older than the shed age). Every rejection is counted."""
        with self._admit_lock:
            self.commands_received += 1
            if int(rec["state_seq"]) > self.state_seq:
                self.commands_future_state += 1
                if not self._warned_future_state:
                    self._warned_future_state = True
                    logger.warning(
                        "rejected a command answering state %d (newest sent: %d); further "
                        "ones are only counted",
                        int(rec["state_seq"]),
                        self.state_seq,
                    )
                return False
            now_ns = self.clock.now_ns()
            # Tick and lockstep pacings: no shedding (the watchdog judges the age; lockstep
            # waits for its answer however long it takes).
            if not self.command_in.accept(rec, now_ns, shed=self._arrival_running):
                return False
            self.marks[SLOT_COMMAND_SEQ] = int(rec["seq"])
            return True

    def on_task_done(self, step: int) -> None:
        """The operator's TASK_DONE: the run ends at tick ``step``."""
        self.finish_tick = step
        self.marks[SLOT_FINISH_TICK] = step
        logger.info("task done: the run ends at tick %d", step)

    def should_step(self) -> bool:
        """False once the run's duration, or the tick the operator asked for, is reached."""
        if self._steps is not None and self.plant.step_count >= self._steps:
            return False
        return self.finish_tick is None or self.plant.step_count < self.finish_tick

    # -- the run -------------------------------------------------------------------------
    def run(self, stop: threading.Event, steps: int | None) -> None:
        """One run of ``steps`` steps (None: until stopped) from the initial configuration,
        or from the store's checkpoint if there is one (a restart: :meth:`resume`);
        ``finished`` says whether it ran to its end (not stopped, not aborted)."""
        resumed = self._start_or_resume(steps)
        if self.aborted:
            return
        if self.finished:  # restarted after the end: the run stays over
            self.publish_event(Event.FINISHED)
            return
        start_ns = self.clock.now_ns()
        if self.lockstep:
            self._start_lockstep(braking=resumed)
            self._run_lockstep(stop)
        else:
            self.publish_initial_state()
            if self.apply_on_arrival:
                self._run_on_arrival(stop)
            else:
                self._run_realtime(stop)
        end_ns = self.clock.now_ns()
        self.wall_s = (end_ns - (self._run_start_ns if resumed else start_ns)) / NS_PER_S
        self.outputs.flush()  # the observers get the run's last states now
        if not stop.is_set() and not self.aborted:
            self.finished = True
            self.publish_event(Event.FINISHED)
            if self.store is not None:
                self.save_checkpoint(end_ns)  # a restart after the end finds it over

    def _start_or_resume(self, steps: int | None) -> bool:
        """Begin the run, or resume it from the store's checkpoint; whether it resumed.
        A restart that cannot resume aborts the run (never a silent fresh start)."""
        snapshot: Snapshot | None = None
        previous: Progress | None = None
        if self.store is not None and self.store.found:  # a previous incarnation's file
            previous = self.store.progress()
            try:
                snapshot = self.store.load(self.model_id)
            except CheckpointError as exc:
                self.abort(Abort.RESUME_FAILED, f"restarted, cannot resume: {exc}")
                return False
            if snapshot is None and previous.state_seq >= 0:
                self.abort(
                    Abort.RESUME_FAILED,
                    f"restarted after state {previous.state_seq} with no checkpoint to "
                    "resume from (plant.checkpoint_s = 0?)",
                )
                return False
        if snapshot is None:  # a fresh run (or a restart before the first state)
            self.marks[:] = FRESH_HEADER
            self.begin_run(steps)
            self.publish_event(Event.STARTED)
            return False
        self.resume(snapshot, previous, steps)
        return True

    def abort(self, reason: Abort, text: str) -> None:
        """End the run on a failure: no more steps, an ABORTED event, the reason kept."""
        self.aborted = True
        self.failure = text
        logger.error("run aborted: %s", text)
        self.publish_event(Event.ABORTED, float(reason))

    def begin_run(self, steps: int | None) -> None:
        """The plant back in the run's initial configuration, nothing held or pending."""
        self.plant.reset(initial_configuration(self.config))
        self._run_start_ns = self.clock.now_ns()
        self._steps = steps
        self._closest = (-1, None)
        self.finish_tick = None
        self._held_body = -1
        self._held_command = None
        self._last_applied_seq = -1
        self.watchdog.reset()

    def snapshot(self, now_ns: int) -> Snapshot:
        """Everything a restarted plant needs to go on from here (teleop.sim.checkpoint)."""
        plant = self.plant
        return Snapshot(
            model_id=self.model_id,
            step=plant.step_count,
            t_ns=now_ns,
            mujoco_state=plant.integration_state(),
            hold_q_rad=plant.hold_q_rad,
            loop={
                "state_seq": self.state_seq,
                "finish_tick": -1 if self.finish_tick is None else self.finish_tick,
                "finished": self.finished,
                "gripper_cmd": plant.gripper_cmd,
                "held_body": int(self._held_body),
                "run_start_ns": self._run_start_ns,
                "counts": {
                    "commands_received": self.commands_received,
                    "commands_applied": self.commands_applied,
                    "commands_future_state": self.commands_future_state,
                    "unanswered_commands": self.unanswered_commands,
                    "clamped_steps": plant.clamped_steps,
                    "watchdog_brakes": self.watchdog.brakes,
                    "stale_steps": self.watchdog.stale_steps,
                },
                "figures": asdict(self.figures),
                "resumes": self.resumes,
            },
        )

    def save_checkpoint(self, now_ns: int) -> None:
        """Put :meth:`snapshot` in the store, timing what it costs the step; a failure is
        logged (the first) and counted, and the run goes on."""
        assert self.store is not None
        start_ns = time.perf_counter_ns()  # its own cost, whatever the loop's clock
        try:
            self.store.save(self.snapshot(now_ns))
        except CheckpointError as exc:
            self.checkpoint_cost.failed += 1
            if self.checkpoint_cost.failed == 1:
                logger.error("checkpoint not taken: %s", exc)
            return
        self.checkpoint_cost.add(time.perf_counter_ns() - start_ns)

    def resume(self, snapshot: Snapshot, previous: Progress | None, steps: int | None) -> None:
        """Go on with the run of ``snapshot`` after a restart.

        The physics is the checkpoint's (the arm, the gripper, the objects as they were
        at its step); the stream goes on from where the previous incarnation stopped
        (``previous``, its progress mark): the next state has the next ``seq``, its step
        and sim time continue without a jump, so no receiver sees a restart or a gap.
        The steps sent after the checkpoint are lost physics (the world is set back by
        that much): the RESUMED event says how many.
        """
        loop = snapshot.loop
        last_seq = max(int(loop["state_seq"]), previous.state_seq if previous else -1)
        steps_lost = max(last_seq - snapshot.step, 0)
        step = last_seq + 1  # the resumed state is published as the next one
        self.plant.restore(
            snapshot.mujoco_state, step, float(loop["gripper_cmd"]), snapshot.hold_q_rad
        )
        self.plant.clamped_steps = int(loop["counts"]["clamped_steps"])
        self.state_seq = last_seq
        self._steps = steps
        finish = max(int(loop["finish_tick"]), previous.finish_tick if previous else -1)
        self.finish_tick = finish if finish >= 0 else None
        self.marks[SLOT_FINISH_TICK] = finish
        self.finished = bool(loop["finished"])
        self._held_body = int(loop["held_body"])
        self._state["held_body"] = self._held_body
        self._closest = (-1, None)
        self._held_command = None
        self._last_applied_seq = -1
        counts = loop["counts"]
        self.commands_received = int(counts["commands_received"])
        self.commands_applied = int(counts["commands_applied"])
        self.commands_future_state = int(counts["commands_future_state"])
        self.unanswered_commands = int(counts["unanswered_commands"])
        self.watchdog.brakes = int(counts["watchdog_brakes"])
        self.watchdog.stale_steps = int(counts["stale_steps"])
        self.watchdog.reset()
        self.figures = PlantFigures(**loop["figures"])
        if previous is not None and previous.command_seq >= 0:
            self.command_in.seq.last_seq = previous.command_seq  # its commands go on too
        self._run_start_ns = int(loop["run_start_ns"])
        now_ns = self.clock.now_ns()
        gap_ns = now_ns - previous.state_ns if previous and previous.state_ns else None
        record = {
            "step": step,
            "sim_time_s": step * self.config.plant.timestep_s,
            "checkpoint_step": snapshot.step,
            "steps_lost": steps_lost,
            "wall_gap_s": None if gap_ns is None else gap_ns / NS_PER_S,
        }
        self.resumes = [*loop["resumes"], record]
        logger.warning(
            "restarted: resuming the run at step %d from the checkpoint of step %d "
            "(%d steps of physics lost, %s s since the last state sent)",
            step,
            snapshot.step,
            steps_lost,
            "?" if gap_ns is None else f"{gap_ns / NS_PER_S:.3f}",
        )
        self.publish_event(Event.RESUMED, float(steps_lost))

    def publish_initial_state(self) -> None:
        """Realtime: send the run's first state, the one the first command answers."""
        self._publish_state(None, 0, 0)

    def _run_realtime(self, stop: threading.Event) -> None:
        self.timer = LoopTimer(self.period_ns, self.clock)
        while not stop.is_set() and self.should_step():
            self.timer.wait()
            self.tick()

    def tick(self) -> None:
        """One step of the plant-tick pacing, with the newest command."""
        latest = self.commands.get()
        command, rx_ns = latest if latest is not None else (None, 0)
        self._step_with(command, rx_ns)

    def _step_with(
        self, command: np.ndarray | None, rx_ns: int, traced: bool | None = None
    ) -> bool:
        """One realtime step with ``command`` (None: none yet), or braking if the watchdog
        says so; whether it was applied. ``traced``: the command entered this step first
        hand (its stamps go on in the state); None: if it was not applied before."""
        judgement = self.watchdog.judge(command, self.clock.now_ns())
        if judgement.event is not None:
            self.publish_event(judgement.event, judgement.value)
        if not judgement.apply:
            self.plant.step_braking()
            self._publish_state(None, 0, 0)
            return False
        assert command is not None
        applied_ns = self.clock.now_ns()
        self.plant.step(
            command["qd_ref_rad_s"][: self.plant.n_joints], float(command["gripper_cmd"])
        )
        new_command = int(command["seq"]) != self._last_applied_seq
        if new_command:
            self.commands_applied += 1
            self._last_applied_seq = int(command["seq"])
        self._publish_state(
            command, rx_ns, applied_ns, traced=new_command if traced is None else traced
        )
        return True

    # -- realtime, apply on arrival -----------------------------------------------------
    def _run_on_arrival(self, stop: threading.Event) -> None:
        """Step each command on arrival (in its callback); this thread steps the device
        periods no command came for (see :class:`DeviceClockGrid`)."""
        with self.cond:
            self.begin_on_arrival()
            try:
                while not stop.is_set() and self.should_step():
                    now_ns = self.clock.now_ns()
                    wait_ns = self.own_step_due(now_ns)
                    if wait_ns > 0:
                        self.cond.wait(wait_ns / NS_PER_S)
                    else:
                        self.own_step(now_ns)
            finally:
                self._arrival_running = False

    def begin_on_arrival(self) -> None:
        """From now on, commands step the plant as they arrive (in their callback), on a
        new device clock grid. The caller holds ``cond``, or is a test or benchmark
        driving the loop directly."""
        self.grid = DeviceClockGrid(self.period_ns, self.clock.now_ns())
        self._held_command = None
        self._last_applied_seq = -1
        self.watchdog.reset()
        self.command_in.restart()
        self._arrival_running = True

    def own_step_due(self, now_ns: int) -> int:
        """Nanoseconds until this loop steps the next period itself (<= 0: now)."""
        assert self.grid is not None
        return self.grid.own_step_ns - now_ns

    def own_step(self, now_ns: int) -> None:
        """Step the next device period without a new command; after a stall, skip the
        periods beyond the catch-up instead of bursting through them."""
        grid = self.grid
        assert grid is not None
        behind = (now_ns - grid.own_step_ns) // self.period_ns
        if behind > CATCH_UP_MAX_PERIODS:
            self.arrival.stalls += 1
            grid.skip(int(behind) - CATCH_UP_MAX_PERIODS)
        self._arrival_step(None, 0)

    def _arrival_command(self, command: np.ndarray, rx_ns: int) -> None:
        """A command arrived: step its device period now (after any before it that got
        no command), or hold it for the next step if its period is past."""
        with self.cond:
            grid = self.grid
            if not self._arrival_running or grid is None:
                return
            deadline_ns = int(command["device_deadline_ns"])
            ahead = 0  # a command not paced by a device steps the next period
            if deadline_ns > 0:
                if not grid.locked or abs(grid.periods_ahead(deadline_ns)) > RELOCK_PERIODS:
                    grid.lock(deadline_ns)
                ahead = grid.periods_ahead(deadline_ns)
            if ahead < 0:  # its period was stepped without it: the next step applies it
                self.arrival.commands_late += 1
                self.command_in.log_dropped(command)
                self._held_command = command
                return
            if ahead > CATCH_UP_MAX_PERIODS:  # the periods before it are too far behind
                self.arrival.stalls += 1
                grid.skip(ahead - CATCH_UP_MAX_PERIODS)
                ahead = CATCH_UP_MAX_PERIODS
            for _ in range(ahead):
                if self.should_step():
                    self._arrival_step(None, 0)
            if self.should_step():
                self.arrival.steps_on_arrival += 1
                self._arrival_step(command, rx_ns)
            self.cond.notify_all()  # the run thread's next own step moved

    def _arrival_step(self, command: np.ndarray | None, rx_ns: int) -> None:
        """Step the grid's next device period with ``command`` (None: with the one held,
        braking if that is stale); the caller holds ``cond``."""
        assert self.grid is not None
        if command is not None:
            self._held_command = command
        else:
            self.arrival.steps_without_command += 1
        applied = self._step_with(self._held_command, rx_ns, traced=command is not None)
        if not applied and command is not None:
            self.arrival.commands_stale += 1
            self.command_in.log_dropped(command)
        self.grid.stepped()

    # -- lockstep ------------------------------------------------------------------------
    def _start_lockstep(self, *, braking: bool = False) -> None:
        """Publish the first state, then take the first ``lockstep_delay_steps`` steps,
        which no command answers (holding still; ``braking``: held by the brake, as after
        a restart, where the arm may be moving); the command callback may step from then on.

        All under the lock, with the callback already enabled: an answer that comes back
        while these steps run waits for the lock instead of finding lockstep not started
        (it would be lost, and the run would wait for it forever).
        """
        with self.lock:
            self._lockstep_done.clear()
            self._lockstep_running = True
            self._publish_state(None, 0, 0)
            for _ in range(self.delay_steps):
                if not self.should_step():
                    break
                if braking:
                    self.plant.step_braking()
                else:
                    self.plant.step_before_commands()
                self._publish_state(None, 0, 0)
            self._last_step_ns = self.clock.now_ns()
            if not self.should_step():
                self._lockstep_done.set()  # the steps before commands were the whole run

    def _run_lockstep(self, stop: threading.Event) -> None:
        """Let the command callback drive the steps; re-send the state if it goes
        unanswered, end the run if it stays so (:meth:`lockstep_waited`)."""
        try:
            last_step = -1
            while not stop.is_set() and not self._lockstep_done.wait(LOCKSTEP_RESEND_S):
                if not self.lockstep_waited(last_step):
                    break
                last_step = self.plant.step_count
        finally:
            with self.lock:
                self._lockstep_running = False

    def lockstep_waited(self, last_step: int) -> bool:
        """Lockstep, every LOCKSTEP_RESEND_S without the run ending: if the plant has not
        stepped since ``last_step``, re-send the pending state, or, once it has waited
        ``plant.lockstep_timeout_s`` for the answer, abort the run (False)."""
        with self.lock:
            if self.plant.step_count != last_step:
                return True
            waited_ns = self.clock.now_ns() - self._last_step_ns
            if waited_ns < self._lockstep_timeout_ns:
                self.republish_pending()
                # The controller went silent for a whole re-send period: if it was
                # restarted, its commands number afresh and it answers each state once,
                # too few for the sequence check to take it up by itself. The next
                # command answering the pending state is taken as is.
                with self._admit_lock:
                    self.command_in.restart()
                return True
            self._lockstep_running = False  # a late answer steps nothing now
            self._lockstep_done.set()  # the run thread's wait ends
            self.abort(
                Abort.LOCKSTEP_TIMEOUT,
                f"lockstep: no answer to state {self.state_seq - self.delay_steps} for "
                f"{waited_ns / NS_PER_S:.1f} s (plant.lockstep_timeout_s = "
                f"{self.config.plant.lockstep_timeout_s:g}): the controller is gone or stuck",
            )
            return False

    def republish_pending(self) -> None:
        """Send the records of the states in flight again, byte for byte (same seq and
        stamps; a state carries its tick's contact and proximity): the pending tick's
        and, with a lockstep delay, those whose answers the plant still needs.

        A controller that has them ignores them (or its tick barrier drops them); one
        that missed them (e.g. not yet subscribed) gets the whole tick; a recorder logs
        the same samples at the same times.
        """
        for records in self._sent_ticks or ():
            for stream, data in records:
                self.outputs.put_bytes(stream, data)

    def _lockstep_cycle(self, command: np.ndarray, rx_ns: int) -> None:
        """Apply the command answering the pending state, step, publish the next state."""
        with self.lock:
            if not self._lockstep_running or self._lockstep_done.is_set():
                return
            if int(command["state_seq"]) != self.state_seq - self.delay_steps:
                self.unanswered_commands += 1
                return
            applied_ns = self.clock.now_ns()
            self._last_step_ns = applied_ns
            self.plant.step(
                command["qd_ref_rad_s"][: self.plant.n_joints], float(command["gripper_cmd"])
            )
            self.commands_applied += 1
            if not self.should_step():
                self._lockstep_done.set()
            answered_tx_ns = int(command["trace_ns"][Stage.PLANT_STATE_TX])  # its state's
            self._publish_state(command, rx_ns, applied_ns)
            self.cycle_stats.add(answered_tx_ns, self._state["trace_ns"])

    # -- publishing ----------------------------------------------------------------------
    def publish_event(self, event: Event, value: float = 0.0) -> None:
        rec = self._event
        rec["seq"] += 1
        rec["t_source_ns"] = self.clock.now_ns()
        rec["sim_time_ns"] = self.plant.step_count * self.period_ns
        rec["step"] = self.plant.step_count
        rec["event"] = event
        rec["value"] = value
        self.outputs.put("plant_events", rec)
        logger.info("event %s at step %d", event.name, self.plant.step_count)

    def _publish_state(
        self, command: np.ndarray | None, rx_ns: int, applied_ns: int, *, traced: bool = True
    ) -> None:
        """Publish the state after a step; ``traced``: the command entered it first-hand
        (its stamps continue in this state), else it was only held from an earlier step."""
        sample = self.plant.sample()
        n = self.plant.n_joints
        rec = self._state
        if self._sent_ticks is not None:
            self._sent_ticks.append([])
        self.state_seq += 1
        rec["seq"] = self.state_seq
        rec["flags"] = Flag.BRAKING if self.plant.braking else Flag.NONE
        self._braked_since_scene |= self.plant.braking
        rec["sim_time_ns"] = sample.sim_time_ns
        rec["step"] = sample.step
        rec["n_joints"] = n
        rec["q_rad"][:n] = sample.q_rad
        rec["qd_rad_s"][:n] = sample.qd_rad_s
        rec["qd_ref_applied_rad_s"][:n] = self.plant.applied_qd_ref_rad_s()
        rec["gripper_cmd_applied"] = self.plant.gripper_cmd
        rec["gripper_opening_m"] = sample.gripper_opening_m
        grasp_event = None
        if sample.step % self.interaction_every_steps == 0:
            grasp_event = self._sample_interaction(sample.step)
        if command is not None:
            rec["cmd_seq_applied"] = command["seq"]
        if command is not None and traced:
            rec["trace_ns"][:] = command["trace_ns"]
            rec["trace_ns"][Stage.PLANT_RX] = rx_ns
            rec["trace_ns"][Stage.PLANT_APPLIED] = applied_ns
        else:
            rec["trace_ns"][:] = 0  # no command entered this step: nothing to trace
        now_ns = self.clock.now_ns()
        rec["t_source_ns"] = now_ns
        rec["trace_ns"][Stage.PLANT_STATE_TX] = now_ns
        self._put("plant_state", rec)
        self.watchdog.state_sent(self.state_seq, now_ns)
        marks = self.marks
        marks[SLOT_STATE_SEQ] = self.state_seq
        marks[SLOT_STATE_NS] = now_ns
        if self.checkpoint_every_steps and sample.step % self.checkpoint_every_steps == 0:
            self.save_checkpoint(now_ns)
        if grasp_event is not None:
            self.publish_event(grasp_event, float(max(int(rec["held_body"]), 0)))
        if sample.step % self.scene_every_steps == 0:
            self._publish_scene(sample.sim_time_ns, now_ns)
        figures = self.figures
        figures.max_tool_speed_m_s = max(figures.max_tool_speed_m_s, self.plant.tool_speed_m_s())
        if self.prepare_ahead:
            self._prepare_next_step(sample.step + 1)

    def _prepare_next_step(self, step: int) -> None:
        """While the command is on its way: the control-free half of the next physics step
        (:meth:`Plant.prepare_step`) and, when that step's state carries them, the closest
        obstacle, which depends on the positions only (the same numbers as after the step:
        a step's collision geometry is that of the state it starts from)."""
        self.plant.prepare_step()
        if step % self.interaction_every_steps == 0:
            self._closest = (step, self.proximity.closest())

    def _sample_interaction(self, step: int) -> Event | None:
        """Fill the state record's contact and proximity fields from the plant as it is.

        Returns GRASP or RELEASE when the held object changed (the caller announces it
        after the state, so the event follows the state that shows it), else None.
        """
        rec = self._state
        rec["interaction_step"] = step
        prepared_step, closest = self._closest
        if prepared_step != step or closest is None:
            closest = self.proximity.closest()
        figures = self.figures
        figures.min_obstacle_clearance_m = min(figures.min_obstacle_clearance_m, closest.distance_m)
        closest.write_to(rec)
        force_n, count = self.plant.gripper_contact_force()
        figures.max_contact_force_n = max(
            figures.max_contact_force_n, math.hypot(*force_n.tolist())
        )
        model, data = self.plant.model, self.plant.data
        held = held_object(model, data, self._fingers, self.plant.object_bodies) if count else -1
        event = None
        if (held >= 0) != (self._held_body >= 0):
            event = Event.GRASP if held >= 0 else Event.RELEASE
        self._held_body = held
        rec["held_body"] = held
        rec["held_mass_kg"] = held_mass_kg(model, held, 0.0)
        rec["world_f_contact_n"] = force_n
        rec["n_contacts"] = count
        return event

    def _publish_scene(self, sim_time_ns: int, now_ns: int) -> None:
        position, quat = self.plant.tool_pose()
        for rec in (self._tool, self._objects):
            rec["seq"] += 1
            rec["t_source_ns"] = now_ns
            rec["sim_time_ns"] = sim_time_ns
        self._tool["world_p_tool_m"] = position
        self._tool["world_q_tool_wxyz"] = quat
        self._tool["flags"] = Flag.BRAKING if self._braked_since_scene else Flag.NONE
        self._braked_since_scene = False
        self._put("tool_pose", self._tool)
        positions, quats = self.plant.object_poses()
        n = len(positions)
        self._objects["n_objects"] = n
        self._objects["world_p_m"][:n] = positions
        self._objects["world_q_wxyz"][:n] = quats
        self._put("objects", self._objects)

    def _put(self, stream: str, rec: np.ndarray) -> None:
        """Publish one record of the current tick (kept for a lockstep re-send)."""
        data = self.outputs.put(stream, rec)
        if self._sent_ticks is not None:
            self._sent_ticks[-1].append((stream, data))

    # -- summary -------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """The run's figures (the plant service's summary, less the service's own)."""
        plant_cfg = self.config.plant
        sim_time_s = self.plant.step_count * plant_cfg.timestep_s
        timer = self.timer.summary() if self.timer is not None else {}
        figures = self.figures
        summary: dict[str, Any] = {
            "mode": self.config.run.mode,
            "finished": self.finished,
            "steps": self.plant.step_count,
            "sim_time_s": sim_time_s,
            "wall_s": self.wall_s,
            "realtime_factor": sim_time_s / self.wall_s if self.wall_s > 0 else None,
            "overrun_fraction": timer.get("overrun_fraction", 0.0),
            "skipped_ticks": timer.get("skipped", 0),
            "loop": timer,
            "commands_received": self.commands_received,
            "commands_applied": self.commands_applied,
            "commands_clamped": self.plant.clamped_steps,
            "command_stream": {
                **self.command_in.counts(),
                "future_state": self.commands_future_state,
            },
            "stale_commands": self.watchdog.brakes,
            "stale_steps": self.watchdog.stale_steps,
            "unanswered_commands": self.unanswered_commands,
            "lockstep_cycle_us": self.cycle_stats.summary(),
            "final_state_sha256": self.plant.state_sha256(),
            "max_contact_force_n": figures.max_contact_force_n,
            "obstacle_min_clearance_m": figures.min_obstacle_clearance_m,
            "tool_speed_max_m_s": figures.max_tool_speed_m_s,
            "object_in_box": self.plant.object_in_bin(),
            "rate_hz": self.plant.step_count / self.wall_s if self.wall_s > 0 else None,
            "aborted": self.aborted,
            "failure": self.failure,
            "resumes": self.resumes,
            "checkpoint": self.checkpoint_cost.summary(self.plant.step_count, self.store),
        }
        if self.grid is not None:
            steps = max(self.plant.step_count, 1)
            summary["overrun_fraction"] = self.arrival.stalls / steps
            summary["skipped_ticks"] = self.grid.skipped
            summary["arrival"] = {
                **asdict(self.arrival),
                "grid_locks": self.grid.locks,
                "commands_lost": self.command_in.seq.lost,
                "commands_reordered": self.command_in.seq.reordered,
                "commands_shed": self.command_in.shed,
            }
        summary["object_poses_m"] = {
            name: self.plant.data.xpos[body].tolist()
            for name, body in zip(
                self.config.robot.object_bodies, self.plant.object_bodies, strict=True
            )
        }
        return summary
