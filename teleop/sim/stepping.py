"""The plant's step core as pure code: admit a command, apply it or brake, step, publish.

:class:`PlantStepCore` owns the :class:`teleop.sim.plant.Plant`, the command admission,
the :class:`Watchdog`, the records it fills (PLANT_STATE, TOOL_POSE, OBJECT_POSES,
RUN_EVENT, handed to :class:`PlantOutputs`), the checkpoint and resume of a run, and the
run's summary. When a step happens is not its business: one pacer per timing mode decides
that (:mod:`teleop.sim.pacing`: the plant's tick, the haptic device's clock, lockstep),
and :class:`teleop.sim.plant_loop.PlantLoop` puts the two together. Time comes from an
injected :class:`teleop.core.clock.Clock`, so a test drives the core on a fake clock
without Zenoh; ``services/plant.py`` is the bus adapter around the loop.

In both realtime pacings one :class:`Watchdog` decides every step (:meth:`PlantStepCore.step`):
it brakes (holds the arm where it is) when the command to apply answers a state older than
``plant.watchdog_s``, and resumes as soon as a fresh command arrives. Lockstep applies the
answer to the pending state as it is (:meth:`PlantStepCore.apply`).

A step of the core is one tick (a bus period, ``loop.rate_hz``): the plant's
``Config.physics_steps_per_tick`` physics steps, its limits and protective stop acting
on each. Published every tick: PLANT_STATE, one record that also carries the contact on
the gripper (and its peak over the tick's physics steps) and the closest obstacle. In
teleoperation those are computed every tick (they feed the force feedback); otherwise
only every ``1 / scene_rate_hz`` (their cost), and ``interaction_step`` says when.
Every ``1 / scene_rate_hz``: TOOL_POSE, OBJECT_POSES. On start, finish, grasp, release
and watchdog changes: RUN_EVENT.
"""

from __future__ import annotations

import enum
import functools
import logging
import math
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import numpy as np

from teleop.bus.messages import (
    OBJECT_POSES,
    PLANT_STATE,
    RUN_EVENT,
    TOOL_POSE,
    Event,
    Flag,
    Stage,
    next_run_event,
)
from teleop.bus.stamps import Inbound
from teleop.core.clock import NS_PER_S, Clock
from teleop.core.config import Config
from teleop.core.ticks import scene_schedule
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
from teleop.sim.protective import Stop
from teleop.sim.proximity import FAR_DISTANCE_M, ObstacleProximity, ProximitySample

logger = logging.getLogger(__name__)


class Abort(enum.IntEnum):
    """Why the plant ended a run on a failure: the value of its ABORTED event."""

    RESUME_FAILED = 1  # restarted, but its checkpoint could not be resumed
    LOCKSTEP_TIMEOUT = 2  # lockstep: no answer to the pending state within the bound
    BRAKE_LIMIT = 3  # realtime: braked for want of a fresh command for plant.brake_limit_s


# Checkpoint writes whose duration the summary keeps (the newest ones).
CHECKPOINT_COST_SAMPLES = 1000


class Judgement(NamedTuple):
    """The watchdog's word on one step: apply the command or brake, and the event (with
    its value) to announce first, if the watchdog changed its mind."""

    apply: bool
    event: Event | None = None
    value: float = 0.0


# States whose send time the watchdog remembers (a ring): 4 s at 1 kHz or more, far beyond any
# watchdog limit; a command answering an older state is stale whatever the limit.
STATE_HISTORY = 4096
# Watchdog brakes whose times the summary keeps (the count goes on beyond them).
MAX_EPISODES_KEPT = 64


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
        # The first MAX_EPISODES_KEPT brakes: [began, ended] on the plant's clock (ns; 0:
        # not ended), so a test can place them against what it did to the link.
        self.episodes: list[list[int]] = []
        self.braking_since_ns = 0  # when the brake under way began (braking only)
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
                if self.episodes and not self.episodes[-1][1]:
                    self.episodes[-1][1] = now_ns
                return Judgement(True, Event.WATCHDOG_RESUME)
            return Judgement(True)
        self.stale_steps += 1
        if self.braking:
            return Judgement(False)
        self.braking = True
        self.brakes += 1
        self.braking_since_ns = now_ns
        if len(self.episodes) < MAX_EPISODES_KEPT:
            self.episodes.append([now_ns, 0])
        sent_ns = self.sent_ns(answered)
        age_s = (now_ns - sent_ns) / NS_PER_S if sent_ns is not None else math.inf
        return Judgement(False, Event.WATCHDOG_BRAKE, age_s)


class PlantOutputs(Protocol):
    """Where :class:`PlantStepCore` sends its records (the service: the bus)."""

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


@dataclass(frozen=True)
class PacingFigures:
    """What the pacer of the run's mode adds to the plant's summary."""

    overrun_fraction: float = 0.0  # steps late (tick: cycles overrun; device clock: stalls)
    skipped_ticks: int = 0  # periods never stepped (skipped after a stall)
    loop: dict[str, Any] = field(default_factory=dict)  # the tick's LoopTimer summary
    lockstep_cycle_us: dict[str, float] = field(default_factory=dict)  # lockstep's cycle
    arrival: dict[str, Any] | None = None  # the device-clock pacing's counts


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


class PlantStepCore:
    """One plant step at a time: admission, apply or brake, step, publish, checkpoint.

    The pacer of the run's mode (:mod:`teleop.sim.pacing`) calls the stepping methods
    from one thread at a time: its run thread, or, where the command callback steps too,
    either under the pacer's own lock; the core has no lock around them. Admission
    (:meth:`admit`, and every other use of the command stream's bookkeeping) runs on
    Zenoh's threads, under the core's admission lock, which is taken last.

    With a ``store`` (teleop.sim.checkpoint) the core checkpoints itself every
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
        self.period_ns = self.plant.tick_ns  # one step of the core: one bus period
        self.scene = scene_schedule(config)
        # Contact and obstacle proximity feed the force feedback of teleoperation every tick;
        # otherwise only the recorder reads them, at the scene rate (computing them costs
        # the plant a contact scan and a narrow-phase distance query per step).
        self.interaction_every_tick = config.run.teleoperated
        self.watchdog = Watchdog(round(plant_cfg.watchdog_s * NS_PER_S), self.period_ns)
        self._brake_limit_ns = round(plant_cfg.brake_limit_s * NS_PER_S)
        self.proximity = ObstacleProximity(self.plant.model, self.plant.data, config.robot)
        self._fingers = finger_bodies(self.plant.model, config.robot)
        self.state_rec = PLANT_STATE.new()  # the newest state, as published
        self.state_rec["held_body"] = -1  # nothing held, no obstacle in reach (until computed)
        self.state_rec["obstacle_geom"] = -1
        self.state_rec["arm_body"] = -1
        self.state_rec["distance_m"] = FAR_DISTANCE_M
        self._tool = TOOL_POSE.new()
        # A step braked since the last TOOL_POSE: the next one carries Flag.BRAKING (the
        # operator, who sees the tool at the scene rate, then knows it was held).
        self._braked_since_scene = False
        self._objects = OBJECT_POSES.new()
        self._event = RUN_EVENT.new()
        self._event_lock = threading.Lock()  # events come from more than one thread
        self.figures = PlantFigures()
        # JOINT_COMMAND order, age and shed log; every command is admitted here first
        self.command_in = Inbound(Stage.CONTROLLER_TX, name="joint_command")
        self._admit_lock = threading.Lock()  # commands come on Zenoh's threads
        self.commands_received = 0
        self.commands_future_state = 0  # answering a state the plant has not sent
        self._warned_future_state = False
        self.state_seq = -1
        self.commands_applied = 0
        self.unanswered_commands = 0  # admitted, but not the answer the pacer waits for
        self.finish_tick: int | None = None  # the operator's TASK_DONE (None: duration)
        self.finished = False
        self.wall_s = 0.0
        self._steps: int | None = None  # the run's length in steps (None: until stopped)
        self._closest: tuple[int, ProximitySample | None] = (-1, None)  # (step, ahead)
        self._held_body = -1
        self._last_applied_seq = -1
        # Checkpoints and the progress marks (teleop.sim.checkpoint); in memory without a store.
        self.store = store
        self.marks = store.marks if store is not None else np.array(FRESH_HEADER, dtype=np.int64)
        self.checkpoint_every_steps = 0
        if store is not None and plant_cfg.checkpoint_s > 0:
            period_steps = round(plant_cfg.checkpoint_s / config.tick_s)
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
    def admit(self, rec: np.ndarray, *, shed: bool) -> bool:
        """Whether a command may steer the arm at all, whatever its sender claims: it
        answers a state this plant has sent (``state_seq``), its send stamp is not in this
        host's future, its ``seq`` is in order within the window (a restarted controller
        is taken up, :class:`teleop.bus.stamps.SeqCheck`), and, with ``shed`` (the pacer
        applies commands on arrival), it is not a backlog (older than the shed age). Every
        rejection is counted."""
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
            if not self.command_in.accept(rec, self.clock.now_ns(), shed=shed):
                return False
            self.marks[SLOT_COMMAND_SEQ] = int(rec["seq"])
            return True

    def log_dropped(self, rec: np.ndarray) -> None:
        """An admitted command the pacer did not apply after all: into the shed log."""
        with self._admit_lock:
            self.command_in.log_dropped(rec)

    def restart_commands(self) -> None:
        """Take the next command as is (a new pacing, or a sender that went silent and
        may have restarted, numbering its commands afresh)."""
        with self._admit_lock:
            self.command_in.restart()

    def save_shed_log(self, path: Path) -> None:
        """Write the commands shed or dropped this run to ``path``."""
        with self._admit_lock:
            self.command_in.save(path)

    def on_task_done(self, step: int) -> None:
        """The operator's TASK_DONE: the run ends at tick ``step``."""
        self.finish_tick = step
        self.marks[SLOT_FINISH_TICK] = step
        logger.info("task done: the run ends at tick %d", step)

    def should_step(self) -> bool:
        """False once the run's duration, or the tick the operator asked for, is reached,
        or the run aborted."""
        if self.aborted:
            return False
        if self._steps is not None and self.plant.step_count >= self._steps:
            return False
        return self.finish_tick is None or self.plant.step_count < self.finish_tick

    # -- the run's start and end ---------------------------------------------------------
    def start_or_resume(self, steps: int | None) -> bool:
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

    def end_run(self, stop: threading.Event, start_ns: int, resumed: bool) -> None:
        """The pacer is done: the wall time since ``start_ns`` (a resumed run: since the
        run's first start), the observers' last states, and, unless stopped or aborted,
        the run ``finished`` (the FINISHED event, a checkpoint that says so)."""
        end_ns = self.clock.now_ns()
        self.wall_s = (end_ns - (self._run_start_ns if resumed else start_ns)) / NS_PER_S
        self.outputs.flush()  # the observers get the run's last states now
        if not stop.is_set() and not self.aborted:
            self.finished = True
            self.publish_event(Event.FINISHED)
            if self.store is not None:
                self.save_checkpoint(end_ns)  # a restart after the end finds it over

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
                    "joint_range_steps": plant.joint_range_steps,
                    "tool_speed_steps": plant.tool_speed_steps,
                    "approach_slowed_steps": plant.approach_slowed_steps,
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
        counts = loop["counts"]
        self.plant.clamped_steps = int(counts["clamped_steps"])
        self.plant.joint_range_steps = int(counts["joint_range_steps"])
        self.plant.tool_speed_steps = int(counts["tool_speed_steps"])
        self.plant.approach_slowed_steps = int(counts["approach_slowed_steps"])
        self.state_seq = last_seq
        self._steps = steps
        finish = max(int(loop["finish_tick"]), previous.finish_tick if previous else -1)
        self.finish_tick = finish if finish >= 0 else None
        self.marks[SLOT_FINISH_TICK] = finish
        self.finished = bool(loop["finished"])
        self._held_body = int(loop["held_body"])
        self.state_rec["held_body"] = self._held_body
        self._closest = (-1, None)
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
            "sim_time_s": step * self.config.tick_s,
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

    # -- steps ---------------------------------------------------------------------------
    def step(self, command: np.ndarray | None, rx_ns: int, traced: bool | None = None) -> bool:
        """One realtime step with ``command`` (None: none yet), or braking if the watchdog
        says so, and its state published; whether it was applied. ``traced``: the command
        entered this step first hand (its stamps go on in the state); None: if it was not
        applied before."""
        now_ns = self.clock.now_ns()
        judgement = self.watchdog.judge(command, now_ns)
        if judgement.event is not None:
            self.publish_event(judgement.event, judgement.value)
        if not judgement.apply:
            self.plant.step_braking()
            self.publish_state(None, 0, 0)
            braked_ns = now_ns - self.watchdog.braking_since_ns
            if self.watchdog.braking and braked_ns >= self._brake_limit_ns:
                self.abort(
                    Abort.BRAKE_LIMIT,
                    f"no fresh command for {braked_ns / NS_PER_S:.1f} s (plant.brake_limit_s "
                    f"= {self.config.plant.brake_limit_s:g}): the controller, or the "
                    "operator's site behind it, is gone or cut off; the arm is held",
                )
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
        self.publish_state(
            command, rx_ns, applied_ns, traced=new_command if traced is None else traced
        )
        return True

    def apply(self, command: np.ndarray) -> None:
        """One step with ``command`` as it is, no watchdog (lockstep: the answer to the
        pending state); the caller publishes the state."""
        self.plant.step(
            command["qd_ref_rad_s"][: self.plant.n_joints], float(command["gripper_cmd"])
        )
        self.commands_applied += 1

    def step_unanswered(self, *, braking: bool) -> None:
        """One step no command answers, and its state: holding still, or, ``braking``,
        held by the brake (after a restart, where the arm may be moving)."""
        if braking:
            self.plant.step_braking()
        else:
            self.plant.step_before_commands()
        self.publish_state(None, 0, 0)

    def interacts_at(self, step: int) -> bool:
        """Whether the state of ``step`` carries contact and proximity (computed for it)."""
        return self.interaction_every_tick or self.scene.is_sample(step)

    def prepare_next_step(self) -> None:
        """While the command is on its way (realtime): the control-free half of the next
        physics step (:meth:`Plant.prepare_step`) and, when that step's state carries them,
        the closest obstacle, which depends on the positions only (the same numbers as
        after the step: a step's collision geometry is that of the state it starts from).
        Not in lockstep, where the state's send would wait behind it."""
        step = self.plant.step_count + 1
        self.plant.prepare_step()
        if self.interacts_at(step):
            self._closest = (step, self.proximity.closest())

    # -- publishing ----------------------------------------------------------------------
    def publish_event(self, event: Event, value: float = 0.0) -> None:
        """A RUN_EVENT on the plant's stream; from the stepping thread or another one (the
        service's watch on its links)."""
        with self._event_lock:
            step = self.plant.step_count
            rec = next_run_event(self._event, event, self.clock.now_ns(),
                                 step * self.period_ns, step, value)  # fmt: skip
            self.outputs.put("plant_events", rec)
        logger.info("event %s at step %d", event.name, self.plant.step_count)

    def publish_state(
        self,
        command: np.ndarray | None = None,
        rx_ns: int = 0,
        applied_ns: int = 0,
        *,
        traced: bool = True,
    ) -> None:
        """Publish the state after a step (or the run's first); ``command``: the one the
        step applied (None: none, braked or held still), received at ``rx_ns`` and applied
        at ``applied_ns``; ``traced``: the command entered it first-hand (its stamps
        continue in this state), else it was only held from an earlier step."""
        sample = self.plant.sample()
        n = self.plant.n_joints
        rec = self.state_rec
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
        rec["peak_contact_force_n"] = self.plant.tick_peak_contact_force_n
        grasp_event = None
        if self.interacts_at(sample.step):
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
        self.outputs.put("plant_state", rec)
        self.watchdog.state_sent(self.state_seq, now_ns)
        marks = self.marks
        marks[SLOT_STATE_SEQ] = self.state_seq
        marks[SLOT_STATE_NS] = now_ns
        if self.checkpoint_every_steps and sample.step % self.checkpoint_every_steps == 0:
            self.save_checkpoint(now_ns)
        if grasp_event is not None:
            self.publish_event(grasp_event, float(max(int(rec["held_body"]), 0)))
        if self.scene.is_sample(sample.step):
            self._publish_scene(sample.sim_time_ns, now_ns)
        figures = self.figures
        plant = self.plant
        figures.max_tool_speed_m_s = max(figures.max_tool_speed_m_s, plant.tick_peak_tool_speed_m_s)
        figures.max_contact_force_n = max(
            figures.max_contact_force_n, plant.tick_peak_contact_force_n
        )
        for stop, released in self.plant.protective.take_transitions():
            self._announce(stop, released)

    def _announce(self, stop: Stop, released: bool) -> None:
        """A protective stop's transition as a RUN_EVENT, logged."""
        if released:
            logger.info("protective stop released at step %d", stop.released_step)
            self.publish_event(Event.PROTECTIVE_RELEASE, float(stop.cause))
        else:
            logger.warning(
                "protective stop at step %d: %s %.3g beyond its limit; the arm is held "
                "until a command asks for no motion",
                stop.step, stop.cause.name.lower(), stop.measured,
            )  # fmt: skip
            self.publish_event(Event.PROTECTIVE_STOP, float(stop.cause))

    def _sample_interaction(self, step: int) -> Event | None:
        """Fill the state record's contact and proximity fields from the plant as it is.

        Returns GRASP or RELEASE when the held object changed (the caller announces it
        after the state, so the event follows the state that shows it), else None.
        """
        rec = self.state_rec
        rec["interaction_step"] = step
        prepared_step, closest = self._closest
        if prepared_step != step or closest is None:
            closest = self.proximity.closest()
        figures = self.figures
        figures.min_obstacle_clearance_m = min(figures.min_obstacle_clearance_m, closest.distance_m)
        closest.write_to(rec)
        force_n, count = self.plant.contact_force_n, self.plant.n_contacts
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
        self.outputs.put("tool_pose", self._tool)
        positions, quats = self.plant.object_poses()
        n = len(positions)
        self._objects["n_objects"] = n
        self._objects["world_p_m"][:n] = positions
        self._objects["world_q_wxyz"][:n] = quats
        self.outputs.put("objects", self._objects)

    # -- summary -------------------------------------------------------------------------
    def summary(self, pacing: PacingFigures) -> dict[str, Any]:
        """The run's figures (the plant service's summary, less the service's own), with
        the ``pacing`` figures of the run's pacer."""
        plant_cfg = self.config.plant
        sim_time_s = self.plant.step_count * self.config.tick_s
        figures = self.figures
        summary: dict[str, Any] = {
            "mode": self.config.run.mode,
            "finished": self.finished,
            "steps": self.plant.step_count,
            "sim_time_s": sim_time_s,
            "wall_s": self.wall_s,
            "realtime_factor": sim_time_s / self.wall_s if self.wall_s > 0 else None,
            "overrun_fraction": pacing.overrun_fraction,
            "skipped_ticks": pacing.skipped_ticks,
            "loop": pacing.loop,
            "commands_received": self.commands_received,
            "commands_applied": self.commands_applied,
            "commands_clamped": self.plant.clamped_steps,
            "commands_clamped_by_reason": self.plant.clamped_by_reason(),
            "command_stream": {
                **self.command_in.counts(),
                "future_state": self.commands_future_state,
            },
            "stale_commands": self.watchdog.brakes,
            "stale_steps": self.watchdog.stale_steps,
            # Each brake's start and end on the plant's clock, ns (the first 64).
            "watchdog_episodes_ns": self.watchdog.episodes,
            "unanswered_commands": self.unanswered_commands,
            "lockstep_cycle_us": pacing.lockstep_cycle_us,
            "final_state_sha256": self.plant.state_sha256(),
            "max_contact_force_n": figures.max_contact_force_n,
            "obstacle_min_clearance_m": figures.min_obstacle_clearance_m,
            "tool_speed_max_m_s": figures.max_tool_speed_m_s,
            "protective_stop": {
                **self.plant.protective.summary(plant_cfg.timestep_s),
                # Steps whose command the approach limit slowed (speed and separation).
                "approach_slowed_steps": self.plant.approach_slowed_steps,
            },
            "object_in_box": self.plant.object_in_bin(),
            "object_bin_distance_m": self.plant.object_bin_distance_m(),
            "rate_hz": self.plant.step_count / self.wall_s if self.wall_s > 0 else None,
            "aborted": self.aborted,
            "failure": self.failure,
            "resumes": self.resumes,
            "checkpoint": self.checkpoint_cost.summary(self.plant.step_count, self.store),
        }
        if pacing.arrival is not None:
            summary["arrival"] = pacing.arrival
        summary["object_poses_m"] = {
            name: self.plant.data.xpos[body].tolist()
            for name, body in zip(
                self.config.robot.object_bodies, self.plant.object_bodies, strict=True
            )
        }
        return summary
