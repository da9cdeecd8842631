"""The plant service: MuJoCo at 1 kHz on the bus, in realtime or lockstep.

One code path, two timing modes:

- realtime: a :class:`LoopTimer` paces the steps on absolute wall-clock deadlines;
  each step applies the newest valid command. The watchdog brakes (holds the arm
  where it is) when the newest command answers a state older than
  ``plant.watchdog_s``, and resumes as soon as fresh commands arrive.
- lockstep: the plant publishes a state and steps when the command that answers it
  (``state_seq``) arrives, inside the command callback, so a cycle costs no thread
  hand-off: deterministic, as fast as plant + controller allow.

Published every step: JOINT_STATE, and in teleoperation CONTACT and
OBSTACLE_PROXIMITY (they feed the 1 kHz force feedback; otherwise they go at the scene
rate). Every ``1 / scene_rate_hz``: TOOL_POSE, OBJECT_POSES. On start, finish and
watchdog changes: RUN_EVENT.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import numpy as np

from teleop.bus import Latest, Publisher, subscribe
from teleop.clock import NS_PER_S, LoopTimer, MonotonicClock
from teleop.experiments import initial_configuration
from teleop.feedback import finger_bodies, held_mass_kg, held_object
from teleop.messages import (
    CONTACT,
    JOINT_COMMAND,
    JOINT_STATE,
    OBJECT_POSES,
    OBSTACLE_PROXIMITY,
    RUN_EVENT,
    TOOL_POSE,
    DecodeError,
    Event,
    Flag,
    Kind,
    Reason,
    Stage,
)
from teleop.plant import Plant
from teleop.proximity import ObstacleProximity
from teleop.service import Service

logger = logging.getLogger(__name__)

# Lockstep: re-send the pending state if no command answers it within this time (s).
LOCKSTEP_RESEND_S = 1.0
# Lockstep cycle breakdown: the newest cycles kept (a ring; 60 s of lockstep fits).
CYCLE_STATS_CAPACITY = 1 << 16


class LockstepCycleStats:
    """Where a lockstep cycle's wall time goes, from the stamps the records carry.

    One cycle: the plant sends state k (``PLANT_STATE_TX``), the controller receives
    it and answers (``CONTROLLER_RX``, ``CONTROLLER_TX``), the plant receives the
    command (``PLANT_RX``), steps (``PLANT_APPLIED``) and sends state k + 1. All stamps
    are this host's monotonic clock, so the segments are exact and add up to the cycle.
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
        # otherwise only the recorder reads them, at the scene rate (measured: two fewer
        # messages per tick speed lockstep path following up, see README).
        teleoperated = self.config.run.scenario == "grasp"
        self.interaction_every_steps = 1 if teleoperated else self.scene_every_steps
        self.watchdog_steps = int(self.config.plant.watchdog_s / self.config.plant.timestep_s)
        declare = self.session
        topics = self.topics
        self.state_pub = self.keep(Publisher.declare(declare, topics.joint_state, JOINT_STATE))
        self.tool_pub = self.keep(Publisher.declare(declare, topics.tool_pose, TOOL_POSE))
        self.contact_pub = self.keep(Publisher.declare(declare, topics.contact, CONTACT))
        self.objects_pub = self.keep(Publisher.declare(declare, topics.objects, OBJECT_POSES))
        self.events_pub = self.keep(Publisher.declare(declare, topics.events, RUN_EVENT))
        self.proximity_pub = self.keep(
            Publisher.declare(declare, topics.obstacle_proximity, OBSTACLE_PROXIMITY)
        )
        self.proximity = ObstacleProximity(self.plant.model, self.plant.data, self.config.robot)
        self._fingers = finger_bodies(self.plant.model, self.config.robot)
        self._held_body = -1
        self.keep(subscribe(self.session, topics.events, RUN_EVENT, self._on_event, self.drops))
        self.commands = Latest()
        self.keep(
            subscribe(
                self.session, topics.joint_command, JOINT_COMMAND, self._on_command, self.drops
            )
        )
        self._state = JOINT_STATE.new()
        self._tool = TOOL_POSE.new()
        self._contact = CONTACT.new()
        self._objects = OBJECT_POSES.new()
        self._event = RUN_EVENT.new()
        self._proximity = OBSTACLE_PROXIMITY.new()
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
        else:
            self.commands(rec.copy(), rx_ns)

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

    def _publish_state(self, command: np.ndarray | None, rx_ns: int, applied_ns: int) -> None:
        sample = self.plant.sample()
        n = self.plant.n_joints
        rec = self._state
        self.state_seq += 1
        rec["seq"] = self.state_seq
        rec["flags"] = Flag.BRAKING if self.plant.braking else Flag.NONE
        rec["sim_time_ns"] = sample.sim_time_ns
        rec["step"] = sample.step
        rec["n_joints"] = n
        rec["q_rad"][:n] = sample.q_rad
        rec["qd_rad_s"][:n] = sample.qd_rad_s
        rec["gripper_opening_m"] = sample.gripper_opening_m
        if command is not None:
            rec["cmd_seq_applied"] = command["seq"]
            rec["trace_ns"][:] = command["trace_ns"]
            rec["trace_ns"][Stage.PLANT_RX] = rx_ns
            rec["trace_ns"][Stage.PLANT_APPLIED] = applied_ns
        now_ns = time.monotonic_ns()
        rec["t_source_ns"] = now_ns
        rec["trace_ns"][Stage.PLANT_STATE_TX] = now_ns
        self.state_pub.put(rec)
        if sample.step % self.interaction_every_steps == 0:
            self._publish_proximity(sample.step, sample.sim_time_ns, now_ns)
            self._publish_contact(sample.sim_time_ns, now_ns)
        if sample.step % self.scene_every_steps == 0:
            self._publish_scene(sample.sim_time_ns, now_ns)
        self.max_tool_speed_m_s = max(self.max_tool_speed_m_s, self.plant.tool_speed_m_s())

    def _publish_proximity(self, tick: int, sim_time_ns: int, now_ns: int) -> None:
        closest = self.proximity.closest()
        self.min_obstacle_clearance_m = min(self.min_obstacle_clearance_m, closest.distance_m)
        rec = self._proximity
        rec["seq"] += 1
        rec["t_source_ns"] = now_ns
        rec["sim_time_ns"] = sim_time_ns
        rec["tick"] = tick
        rec["distance_m"] = closest.distance_m
        rec["world_p_arm_m"] = closest.world_p_arm_m
        rec["world_p_obstacle_m"] = closest.world_p_obstacle_m
        rec["world_n_away"] = closest.world_n_away
        rec["arm_body"] = closest.arm_body
        rec["obstacle_geom"] = closest.obstacle
        self.proximity_pub.put(rec)

    def _publish_contact(self, sim_time_ns: int, now_ns: int) -> None:
        """Contact force on the gripper every step: it is rendered at 1 kHz as feedback."""
        force_n, count = self.plant.gripper_contact_force()
        self.max_contact_force_n = max(self.max_contact_force_n, float(np.linalg.norm(force_n)))
        model, data = self.plant.model, self.plant.data
        held = held_object(model, data, self._fingers, self.plant.object_bodies) if count else -1
        if (held >= 0) != (self._held_body >= 0):
            self._publish_event(Event.GRASP if held >= 0 else Event.RELEASE, float(max(held, 0)))
        self._held_body = held
        rec = self._contact
        rec["held_body"] = held
        rec["held_mass_kg"] = held_mass_kg(model, held, 0.0)
        rec["seq"] += 1
        rec["t_source_ns"] = now_ns
        rec["sim_time_ns"] = sim_time_ns
        rec["world_f_contact_n"] = force_n
        rec["n_contacts"] = count
        self.contact_pub.put(rec)

    def _publish_scene(self, sim_time_ns: int, now_ns: int) -> None:
        position, quat = self.plant.tool_pose()
        for rec in (self._tool, self._objects):
            rec["seq"] += 1
            rec["t_source_ns"] = now_ns
            rec["sim_time_ns"] = sim_time_ns
        self._tool["world_p_tool_m"] = position
        self._tool["world_q_tool_wxyz"] = quat
        self.tool_pub.put(self._tool)
        positions, quats = self.plant.object_poses()
        n = len(positions)
        self._objects["n_objects"] = n
        self._objects["world_p_m"][:n] = positions
        self._objects["world_q_wxyz"][:n] = quats
        self.objects_pub.put(self._objects)

    # -- the run -------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        if not self.wait_for_peers(stop):
            return
        self.plant.reset(initial_configuration(self.config))
        self.finish_tick = None
        self._held_body = -1
        steps = None
        if not self.options.continuous:
            steps = round(self.config.run.duration_s / self.config.plant.timestep_s)
        self._publish_event(Event.STARTED)
        self._publish_state(None, 0, 0)
        start_ns = time.monotonic_ns()
        if self.config.run.mode == "lockstep":
            self._run_lockstep(stop, steps)
        else:
            self._run_realtime(stop, steps)
        self.wall_s = (time.monotonic_ns() - start_ns) / NS_PER_S
        if not stop.is_set():
            self.finished = True
            self._publish_event(Event.FINISHED)
            logger.info("run finished: %s", self.summary())
            stop.wait()  # hold (no stepping) until stopped: supervisord must not restart us

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
                if int(command["seq"]) != last_applied_seq:
                    self.commands_applied += 1
                    last_applied_seq = int(command["seq"])
                self._publish_state(command, rx_ns, applied_ns)
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

    def _run_lockstep(self, stop: threading.Event, steps: int | None) -> None:
        """Let the command callback drive the steps; re-send the state if it goes unanswered."""
        self._lockstep_steps = steps
        self._lockstep_running = True
        try:
            last_step = -1
            while not stop.is_set() and not self._lockstep_done.wait(LOCKSTEP_RESEND_S):
                with self._lock:
                    if self.plant.step_count == last_step:
                        self.state_seq -= 1  # same seq: a controller that has it ignores it
                        self._publish_state(None, 0, 0)
                    last_step = self.plant.step_count
        finally:
            with self._lock:
                self._lockstep_running = False

    def _lockstep_cycle(self, command: np.ndarray, rx_ns: int) -> None:
        """Apply the command answering the pending state, step, publish the next state."""
        with self._lock:
            if not self._lockstep_running or self._lockstep_done.is_set():
                return
            if int(command["state_seq"]) != self.state_seq:
                self.unanswered_commands += 1
                return
            applied_ns = time.monotonic_ns()
            self.plant.step(
                command["qd_ref_rad_s"][: self.plant.n_joints], float(command["gripper_cmd"])
            )
            self.commands_applied += 1
            if not self._should_step(self._lockstep_steps):
                self._lockstep_done.set()
            answered_tx_ns = int(self._state["trace_ns"][Stage.PLANT_STATE_TX])
            self._publish_state(command, rx_ns, applied_ns)
            self.cycle_stats.add(answered_tx_ns, self._state["trace_ns"])

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
            "object_poses_m": {
                name: self.plant.data.xpos[body].tolist()
                for name, body in zip(
                    self.config.robot.object_bodies, self.plant.object_bodies, strict=True
                )
            },
        }
