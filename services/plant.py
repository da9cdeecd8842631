"""The plant service: MuJoCo at 1 kHz on the bus, in realtime or lockstep.

One code path, two timing modes:

- realtime: the plant keeps wall-clock time, one step per period on average, after a
  stall skipping ticks, never bursting. In teleoperation with
  ``plant.apply_on_arrival`` (the default) each command enters a step the moment it
  arrives, in the Zenoh callback: the steps follow the haptic device's clock, one per
  device period (see :class:`DeviceClockGrid`), so a command never waits for the
  plant's tick, and a period without a command is stepped with the last command. Otherwise a
  :class:`LoopTimer` paces the steps and each applies the newest command. The
  watchdog brakes (holds the arm where it is) when the command answers a state older
  than ``plant.watchdog_s``, and resumes as soon as fresh commands arrive.
- lockstep: the plant publishes a state and steps when the command that answers it
  (``state_seq``) arrives, inside the command callback, so a cycle costs no thread
  hand-off: deterministic, as fast as plant + controller allow.

Published every step: PLANT_STATE, one record that also carries the contact on the
gripper and the closest obstacle. In teleoperation those are computed every step (they
feed the 1 kHz force feedback); otherwise only every ``1 / scene_rate_hz`` (their cost),
and ``interaction_step`` says when. Every ``1 / scene_rate_hz``: TOOL_POSE,
OBJECT_POSES. On start, finish, grasp, release and watchdog changes: RUN_EVENT.
"""

from __future__ import annotations

import collections
import logging
import math
import sys
import threading
import time
from typing import Any

import numpy as np

from teleop.bus.messages import (
    JOINT_COMMAND,
    OBJECT_POSES,
    PLANT_STATE,
    RUN_EVENT,
    TOOL_POSE,
    DecodeError,
    Event,
    Flag,
    Kind,
    Reason,
    Stage,
)
from teleop.bus.service import Service, service_main
from teleop.bus.session import BatchPublisher, Latest, Publisher, subscribe
from teleop.bus.stamps import SHED_AGE_NS, SeqCheck, StampLog
from teleop.core.clock import NS_PER_S, LoopTimer, MonotonicClock
from teleop.core.rundir import shed_path
from teleop.sim.contact import finger_bodies, held_mass_kg, held_object
from teleop.sim.plant import Plant, initial_configuration
from teleop.sim.proximity import FAR_DISTANCE_M, ObstacleProximity, ProximitySample

logger = logging.getLogger(__name__)

# Lockstep: re-send the pending state if no command answers it within this time (s).
LOCKSTEP_RESEND_S = 1.0
# Apply on arrival: a device period whose command has not come this many periods after
# the period began is stepped without it (with the last command, or braking). A command
# normally reaches the plant 0.3-1.5 ms after its handle sample (teleop latency, p50-p99,
# 2026-11-22); one that comes after its period was stepped is merged into the next step
# instead of taking one of its own.
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


class PlantService(Service):
    name = "plant"

    def open(self) -> None:
        super().open()
        assert self.session is not None
        self.plant = Plant(self.config)
        self.period_ns = self.plant.timestep_ns
        self.scene_every_steps = max(
            1, round(1.0 / (self.config.plant.scene_rate_hz * self.config.plant.timestep_s))
        )
        # Contact and obstacle proximity feed the 1 kHz force feedback of teleoperation;
        # otherwise only the recorder reads them, at the scene rate (computing them costs
        # the plant a contact scan and a narrow-phase distance query per step).
        teleoperated = self.config.run.scenario == "grasp"
        self.interaction_every_steps = 1 if teleoperated else self.scene_every_steps
        self.watchdog_steps = int(self.config.plant.watchdog_s / self.config.plant.timestep_s)
        declare = self.session
        topics = self.topics
        self.state_pub = self.keep(Publisher.declare(declare, topics.plant_state, PLANT_STATE))
        self.state_batch = self.keep(
            BatchPublisher.declare(
                declare,
                topics.plant_state_batch,
                PLANT_STATE,
                self.config.bus.observer_batch_records,
            )
        )
        self.tool_pub = self.keep(Publisher.declare(declare, topics.tool_pose, TOOL_POSE))
        self.objects_pub = self.keep(Publisher.declare(declare, topics.objects, OBJECT_POSES))
        self.events_pub = self.keep(Publisher.declare(declare, topics.events, RUN_EVENT))
        self.proximity = ObstacleProximity(self.plant.model, self.plant.data, self.config.robot)
        # (step, closest obstacle) computed ahead for that step's state; step -1: none.
        self._closest: tuple[int, ProximitySample | None] = (-1, None)
        self._fingers = finger_bodies(self.plant.model, self.config.robot)
        self._held_body = -1
        self.keep(subscribe(self.session, topics.events, RUN_EVENT, self._on_event, self.drops))
        self.commands = Latest()
        self.keep(
            subscribe(
                self.session, topics.joint_command, JOINT_COMMAND, self._on_command, self.drops
            )
        )
        self._state = PLANT_STATE.new()
        self._state["held_body"] = -1  # nothing held, no obstacle in reach (until computed)
        self._state["obstacle_geom"] = -1
        self._state["arm_body"] = -1
        self._state["distance_m"] = FAR_DISTANCE_M
        self._tool = TOOL_POSE.new()
        self._objects = OBJECT_POSES.new()
        self._event = RUN_EVENT.new()
        # Figures of merit over the run (world frame, SI).
        self.max_contact_force_n = 0.0
        self.min_obstacle_clearance_m = float("inf")
        self.max_tool_speed_m_s = 0.0
        # The operator's TASK_DONE names the tick at which the run ends (None: duration).
        self.finish_tick: int | None = None
        self.timer: LoopTimer | None = None
        self.state_seq = -1
        self.commands_applied = 0
        self.stale_commands = 0  # watchdog brake events after the first command
        self.stale_steps = 0
        self.unanswered_commands = 0  # lockstep: commands answering an older state
        self.wall_s = 0.0
        self.finished = False
        # Lockstep state, shared by the run thread and the command callback.
        self._lock = threading.Lock()
        self._lockstep_steps: int | None = None
        self._lockstep_running = False
        self._lockstep_done = threading.Event()
        self.cycle_stats = LockstepCycleStats()
        # Step k applies the command answering state k - delay_steps (PlantConfig).
        self.delay_steps = self.config.plant.lockstep_delay_steps
        # Lockstep: what the plant sent for each state in flight (publisher, bytes), for
        # _republish_pending; None in realtime.
        self._sent_ticks: collections.deque[list[tuple[Publisher, bytes]]] | None = None
        # Realtime only: the control-free half of the next step while the command is on
        # its way. In lockstep it made runs slower (lockstep / in-process 0.31-0.36
        # against 0.43 without, 2026-11-22): there the state's send waits behind it.
        self.prepare_ahead = self.config.run.mode == "realtime"
        if self.config.run.mode == "lockstep":
            self._sent_ticks = collections.deque(maxlen=self.delay_steps + 1)
        # Realtime apply-on-arrival state, shared by the run thread and the command
        # callback (which steps the plant itself, see DeviceClockGrid). Only in
        # teleoperation: there the haptic device's clock paces the commands. In path
        # following each command answers the plant's own state, so the plant's tick is
        # the loop's only clock and the newest command is the one to apply.
        self.apply_on_arrival = self.config.plant.apply_on_arrival and teleoperated
        self._arrival_cond = threading.Condition()
        self._arrival_running = False
        self._arrival_steps: int | None = None
        self._grid: DeviceClockGrid | None = None
        self._held_command: np.ndarray | None = None
        self._braking = False
        self._last_applied_seq = -1
        self.command_seq = SeqCheck()  # JOINT_COMMAND gaps and reordering (realtime)
        self.steps_on_arrival = 0  # steps a command started the moment it arrived
        self.steps_without_command = 0  # device periods stepped without a new command
        self.stalls = 0  # times the plant fell behind by more than the catch-up (skipped)
        self.commands_late = 0  # came after their period was stepped: merged into the next
        self.commands_stale = 0  # arrived too old to apply (the watchdog brakes instead)
        self.commands_shed = 0  # older than SHED_AGE_NS on arrival (this service was behind)
        self.shed_log = StampLog(1)  # HAPTIC_SAMPLE stamps of the commands dropped here
        self.announce()

    def _on_event(self, rec: np.ndarray, rx_ns: int) -> None:
        if int(rec["event"]) == Event.TASK_DONE:
            self.finish_tick = int(rec["step"])
            logger.info("task done: the run ends at tick %d", self.finish_tick)

    def _should_step(self, steps: int | None) -> bool:
        """False once the run's duration, or the tick the operator asked for, is reached."""
        if steps is not None and self.plant.step_count >= steps:
            return False
        return self.finish_tick is None or self.plant.step_count < self.finish_tick

    def _on_command(self, rec: np.ndarray, rx_ns: int) -> None:
        """Accept commands for exactly this arm; anything else is counted and dropped."""
        if int(rec["n_joints"]) != self.plant.n_joints:
            detail = f"n_joints={int(rec['n_joints'])}, arm has {self.plant.n_joints}"
            self.drops.record(DecodeError(Kind.JOINT_COMMAND, Reason.COUNT, detail))
            return
        if self._lockstep_running:
            self._lockstep_cycle(rec, rx_ns)
        elif self._arrival_running:
            self._arrival_command(rec, rx_ns)
        else:
            self.commands(rec, rx_ns)

    # -- publishing ----------------------------------------------------------------------
    def _publish_event(self, event: Event, value: float = 0.0) -> None:
        rec = self._event
        rec["seq"] += 1
        rec["t_source_ns"] = time.monotonic_ns()
        rec["sim_time_ns"] = self.plant.step_count * self.period_ns
        rec["step"] = self.plant.step_count
        rec["event"] = event
        rec["value"] = value
        self.events_pub.put(rec)
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
        now_ns = time.monotonic_ns()
        rec["t_source_ns"] = now_ns
        rec["trace_ns"][Stage.PLANT_STATE_TX] = now_ns
        self.state_batch.add(self._put(self.state_pub, rec))
        if grasp_event is not None:
            self._publish_event(grasp_event, float(max(int(rec["held_body"]), 0)))
        if sample.step % self.scene_every_steps == 0:
            self._publish_scene(sample.sim_time_ns, now_ns)
        self.max_tool_speed_m_s = max(self.max_tool_speed_m_s, self.plant.tool_speed_m_s())
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
        if prepared_step != step:
            closest = self.proximity.closest()
        self.min_obstacle_clearance_m = min(self.min_obstacle_clearance_m, closest.distance_m)
        rec["distance_m"] = closest.distance_m
        rec["world_p_arm_m"] = closest.world_p_arm_m
        rec["world_p_obstacle_m"] = closest.world_p_obstacle_m
        rec["world_n_away"] = closest.world_n_away
        rec["arm_body"] = closest.arm_body
        rec["obstacle_geom"] = closest.obstacle
        force_n, count = self.plant.gripper_contact_force()
        self.max_contact_force_n = max(self.max_contact_force_n, math.hypot(*force_n.tolist()))
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
        self._put(self.tool_pub, self._tool)
        positions, quats = self.plant.object_poses()
        n = len(positions)
        self._objects["n_objects"] = n
        self._objects["world_p_m"][:n] = positions
        self._objects["world_q_wxyz"][:n] = quats
        self._put(self.objects_pub, self._objects)

    def _put(self, publisher: Publisher, rec: np.ndarray) -> bytes:
        """Publish one record of the current tick (kept for a lockstep re-send); its bytes."""
        data = publisher.schema.encode(rec)
        publisher.put_bytes(data)
        if self._sent_ticks is not None:
            self._sent_ticks[-1].append((publisher, data))
        return data

    # -- the run -------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        if not self.wait_for_peers(stop):
            return
        self.begin_run()
        steps = None
        if not self.options.continuous:
            steps = round(self.config.run.duration_s / self.config.plant.timestep_s)
        self._publish_event(Event.STARTED)
        start_ns = time.monotonic_ns()
        if self.config.run.mode == "lockstep":
            self._start_lockstep(steps)
            self._run_lockstep(stop)
        else:
            self._publish_state(None, 0, 0)
            if self.apply_on_arrival:
                self._run_on_arrival(stop, steps)
            else:
                self._run_realtime(stop, steps)
        self.wall_s = (time.monotonic_ns() - start_ns) / NS_PER_S
        self.state_batch.flush()  # the observers get the run's last states now
        if not stop.is_set():
            self.finished = True
            self._publish_event(Event.FINISHED)
            logger.info("run finished: %s", self.summary())
            stop.wait()  # hold (no stepping) until stopped: supervisord must not restart us

    def begin_run(self) -> None:
        """The plant back in the run's initial configuration, nothing held or pending."""
        self.plant.reset(initial_configuration(self.config))
        self._closest = (-1, None)
        self.finish_tick = None
        self._held_body = -1

    def _run_realtime(self, stop: threading.Event, steps: int | None) -> None:
        self.timer = LoopTimer(self.period_ns, MonotonicClock())
        braking = False
        last_applied_seq = -1
        while not stop.is_set() and self._should_step(steps):
            self.timer.wait()
            latest = self.commands.get()
            command, rx_ns = latest if latest is not None else (None, 0)
            fresh = (
                command is not None
                and self.state_seq - int(command["state_seq"]) <= self.watchdog_steps
            )
            if fresh:
                if braking:
                    braking = False
                    self._publish_event(Event.WATCHDOG_RESUME)
                applied_ns = time.monotonic_ns()
                self.plant.step(
                    command["qd_ref_rad_s"][: self.plant.n_joints], float(command["gripper_cmd"])
                )
                new_command = int(command["seq"]) != last_applied_seq
                if new_command:
                    self.commands_applied += 1
                    last_applied_seq = int(command["seq"])
                self._publish_state(command, rx_ns, applied_ns, traced=new_command)
            else:
                if command is not None:
                    self.stale_steps += 1
                    if not braking:
                        braking = True
                        self.stale_commands += 1
                        age_s = (self.state_seq - int(command["state_seq"])) * (
                            self.config.plant.timestep_s
                        )
                        self._publish_event(Event.WATCHDOG_BRAKE, age_s)
                self.plant.step_braking()
                self._publish_state(None, 0, 0)

    # -- realtime, apply on arrival -----------------------------------------------------
    def _run_on_arrival(self, stop: threading.Event, steps: int | None) -> None:
        """Step each command on arrival (in its callback); this thread steps the device
        periods no command came for (see :class:`DeviceClockGrid`)."""
        with self._arrival_cond:
            self.begin_on_arrival(steps)
            try:
                while not stop.is_set() and self._should_step(steps):
                    grid = self._grid
                    now_ns = time.monotonic_ns()
                    if now_ns < grid.own_step_ns:
                        self._arrival_cond.wait((grid.own_step_ns - now_ns) / NS_PER_S)
                        continue
                    behind = (now_ns - grid.own_step_ns) // self.period_ns
                    if behind > CATCH_UP_MAX_PERIODS:  # a stall: skip, never burst
                        self.stalls += 1
                        grid.skip(int(behind) - CATCH_UP_MAX_PERIODS)
                    self._arrival_step(None, 0)
            finally:
                self._arrival_running = False

    def begin_on_arrival(self, steps: int | None) -> None:
        """From now on, commands step the plant as they arrive (in their callback), on a
        new device clock grid; ``steps``: the run's length (None: until stopped). The
        caller holds ``_arrival_cond``, or is a benchmark driving the plant directly."""
        self._grid = DeviceClockGrid(self.period_ns, time.monotonic_ns())
        self._held_command = None
        self._braking = False
        self._last_applied_seq = -1
        self.command_seq.restart()
        self._arrival_steps = steps
        self._arrival_running = True

    def _arrival_command(self, command: np.ndarray, rx_ns: int) -> None:
        """A command arrived: step its device period now (after any before it that got
        no command), or hold it for the next step if its period is past."""
        with self._arrival_cond:
            grid = self._grid
            if not self._arrival_running or grid is None:
                return
            if not self.command_seq.accept(int(command["seq"])):
                return
            if time.monotonic_ns() - int(command["trace_ns"][Stage.CONTROLLER_TX]) > SHED_AGE_NS:
                self.commands_shed += 1  # a backlog: a newer command is right behind it
                self._log_shed(command)
                return
            deadline_ns = int(command["device_deadline_ns"])
            ahead = 0  # a command not paced by a device steps the next period
            if deadline_ns > 0:
                if not grid.locked or abs(grid.periods_ahead(deadline_ns)) > RELOCK_PERIODS:
                    grid.lock(deadline_ns)
                ahead = grid.periods_ahead(deadline_ns)
            if ahead < 0:  # its period was stepped without it: the next step applies it
                self.commands_late += 1
                self._log_shed(command)
                self._held_command = command
                return
            if ahead > CATCH_UP_MAX_PERIODS:  # the periods before it are too far behind
                self.stalls += 1
                grid.skip(ahead - CATCH_UP_MAX_PERIODS)
                ahead = CATCH_UP_MAX_PERIODS
            for _ in range(ahead):
                if self._should_step(self._arrival_steps):
                    self._arrival_step(None, 0)
            if self._should_step(self._arrival_steps):
                self.steps_on_arrival += 1
                self._arrival_step(command, rx_ns)
            self._arrival_cond.notify_all()  # the run thread's next own step moved

    def _log_shed(self, command: np.ndarray) -> None:
        sample_ns = int(command["trace_ns"][Stage.HAPTIC_SAMPLE])
        if sample_ns > 0:
            self.shed_log.append((sample_ns,))

    def close(self) -> None:
        if self.options.run_dir is not None and getattr(self, "shed_log", None) is not None:
            with self._arrival_cond:
                self.shed_log.save(shed_path(self.options.run_dir, self.name))
        super().close()

    def _arrival_step(self, command: np.ndarray | None, rx_ns: int) -> None:
        """Step the grid's next device period with ``command`` (None: with the one held,
        or braking if that is stale); the caller holds the condition."""
        grid = self._grid
        assert grid is not None
        if command is not None:
            self._held_command = command
        else:
            self.steps_without_command += 1
        held = self._held_command
        fresh = held is not None and self.state_seq - int(held["state_seq"]) <= self.watchdog_steps
        if fresh:
            assert held is not None
            if self._braking:
                self._braking = False
                self._publish_event(Event.WATCHDOG_RESUME)
            applied_ns = time.monotonic_ns()
            self.plant.step(held["qd_ref_rad_s"][: self.plant.n_joints], float(held["gripper_cmd"]))
            if int(held["seq"]) != self._last_applied_seq:
                self.commands_applied += 1
                self._last_applied_seq = int(held["seq"])
            self._publish_state(held, rx_ns, applied_ns, traced=command is not None)
        else:
            if command is not None:
                self.commands_stale += 1
                self._log_shed(command)
            if held is not None:
                self.stale_steps += 1
                if not self._braking:
                    self._braking = True
                    self.stale_commands += 1
                    age_s = (self.state_seq - int(held["state_seq"])) * self.config.plant.timestep_s
                    self._publish_event(Event.WATCHDOG_BRAKE, age_s)
            self.plant.step_braking()
            self._publish_state(None, 0, 0)
        grid.stepped()

    def _start_lockstep(self, steps: int | None) -> None:
        """Publish state 0, then take the first ``lockstep_delay_steps`` steps, which no
        command answers; the command callback may step from then on.

        All under the lock, with the callback already enabled: an answer that comes back
        while these steps run waits for the lock instead of finding lockstep not started
        (it would be lost, and the run would wait for it forever).
        """
        with self._lock:
            self._lockstep_steps = steps
            self._lockstep_running = True
            self._publish_state(None, 0, 0)
            for _ in range(self.delay_steps):
                if not self._should_step(steps):
                    break
                self.plant.step_before_commands()
                self._publish_state(None, 0, 0)
            if not self._should_step(steps):
                self._lockstep_done.set()  # the steps before commands were the whole run

    def _run_lockstep(self, stop: threading.Event) -> None:
        """Let the command callback drive the steps; re-send the state if it goes unanswered."""
        try:
            last_step = -1
            while not stop.is_set() and not self._lockstep_done.wait(LOCKSTEP_RESEND_S):
                with self._lock:
                    if self.plant.step_count == last_step:
                        self._republish_pending()
                    last_step = self.plant.step_count
        finally:
            with self._lock:
                self._lockstep_running = False

    def _republish_pending(self) -> None:
        """Send the records of the states in flight again, byte for byte (same seq and
        stamps; a state carries its tick's contact and proximity): the pending tick's
        and, with a lockstep delay, those whose answers the plant still needs.

        A controller that has them ignores them (or its tick barrier drops them); one
        that missed them (e.g. not yet subscribed) gets the whole tick; a recorder logs
        the same samples at the same times.
        """
        for records in self._sent_ticks or ():
            for publisher, data in records:
                publisher.put_bytes(data)

    def _lockstep_cycle(self, command: np.ndarray, rx_ns: int) -> None:
        """Apply the command answering the pending state, step, publish the next state."""
        with self._lock:
            if not self._lockstep_running or self._lockstep_done.is_set():
                return
            if int(command["state_seq"]) != self.state_seq - self.delay_steps:
                self.unanswered_commands += 1
                return
            applied_ns = time.monotonic_ns()
            self.plant.step(
                command["qd_ref_rad_s"][: self.plant.n_joints], float(command["gripper_cmd"])
            )
            self.commands_applied += 1
            if not self._should_step(self._lockstep_steps):
                self._lockstep_done.set()
            answered_tx_ns = int(command["trace_ns"][Stage.PLANT_STATE_TX])  # its state's
            self._publish_state(command, rx_ns, applied_ns)
            self.cycle_stats.add(answered_tx_ns, self._state["trace_ns"])

    def _arrival_summary(self) -> dict[str, Any]:
        """Timing figures of the apply-on-arrival realtime loop (empty otherwise)."""
        if self._grid is None:
            return {}
        steps = max(self.plant.step_count, 1)
        return {
            "overrun_fraction": self.stalls / steps,
            "skipped_ticks": self._grid.skipped,
            "arrival": {
                "steps_on_arrival": self.steps_on_arrival,
                "steps_without_command": self.steps_without_command,
                "stalls": self.stalls,
                "grid_locks": self._grid.locks,
                "commands_lost": self.command_seq.lost,
                "commands_reordered": self.command_seq.reordered,
                "commands_late": self.commands_late,
                "commands_stale": self.commands_stale,
                "commands_shed": self.commands_shed,
            },
        }

    def summary(self) -> dict[str, Any]:
        sim_time_s = self.plant.step_count * self.config.plant.timestep_s
        timer = self.timer.summary() if self.timer is not None else {}
        return {
            **super().summary(),
            "mode": self.config.run.mode,
            "finished": self.finished,
            "steps": self.plant.step_count,
            "sim_time_s": sim_time_s,
            "wall_s": self.wall_s,
            "realtime_factor": sim_time_s / self.wall_s if self.wall_s > 0 else None,
            "overrun_fraction": timer.get("overrun_fraction", 0.0),
            "skipped_ticks": timer.get("skipped", 0),
            "loop": timer,
            "commands_applied": self.commands_applied,
            "stale_commands": self.stale_commands,
            "stale_steps": self.stale_steps,
            "unanswered_commands": self.unanswered_commands,
            "lockstep_cycle_us": self.cycle_stats.summary(),
            "final_state_sha256": self.plant.state_sha256(),
            "max_contact_force_n": self.max_contact_force_n,
            "obstacle_min_clearance_m": self.min_obstacle_clearance_m,
            "tool_speed_max_m_s": self.max_tool_speed_m_s,
            "object_in_box": self.plant.object_in_bin(),
            "rate_hz": self.plant.step_count / self.wall_s if self.wall_s > 0 else None,
            **self._arrival_summary(),
            "object_poses_m": {
                name: self.plant.data.xpos[body].tolist()
                for name, body in zip(
                    self.config.robot.object_bodies, self.plant.object_bodies, strict=True
                )
            },
        }


def main() -> int:
    return service_main(PlantService)


if __name__ == "__main__":
    sys.exit(main())
