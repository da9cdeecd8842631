"""The controller's cycles as pure code: plant state (and handle, head pose) in, joint
command, force feedback and status out.

Two tasks (``run.scenario``), one :class:`ControllerCore` each:

- :class:`PathCycle`, path following (paper experiment 1): each PLANT_STATE gives one
  JOINT_COMMAND from the same :class:`PathFollowingController` as the in-process run.
- :class:`BilateralCycle`, bilateral teleoperation (experiment 2): the cycle also needs
  the haptic handle of the same tick (and the HMD view yaw); the contact force and the
  obstacle proximity come in the PLANT_STATE itself. In lockstep a
  :class:`TickBarrier` joins state and handle, so the run is deterministic; each cycle
  sends the FORCE_FEEDBACK first (the haptic device waits for it in lockstep), then the
  JOINT_COMMAND. In realtime the loop is event driven, one half-cycle per arrival (no
  thread hand-off, no waiting for a tick): each HAPTIC_STATE sample becomes one
  JOINT_COMMAND at once (control law on the newest state), and each PLANT_STATE one
  FORCE_FEEDBACK (from its own contact and proximity and the newest handle). A handle
  silent for ``haptic.stale_feedback_s`` (realtime: its newest sample arrived that long
  ago; lockstep: that many ticks behind the state) counts as "no input" (the tool holds
  still, the device gets no force).

Every command names the state it answers (``state_seq``): a controller too slow for the
plant's rate makes its commands stale and the plant's watchdog brakes, the safe failure.
The cores take records as the bus delivers them and hand the records they fill to
:class:`ControllerOutputs`; time comes from an injected :class:`teleop.core.clock.Clock`,
so a test drives them on a fake clock without Zenoh (``services/controller.py`` is the
bus adapter).
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import mujoco
import numpy as np

from teleop.bus.messages import (
    CONTROL_STATUS,
    FORCE_FEEDBACK,
    JOINT_COMMAND,
    N_STAGES,
    RUN_EVENT,
    TELEOP_STATUS,
    Button,
    Flag,
    Stage,
    next_run_event,
)
from teleop.bus.session import Latest
from teleop.bus.stamps import Inbound, SeqCheck, StampLog
from teleop.control.clearance import ClearanceModel
from teleop.control.feedback import (
    FeedbackComponents,
    check_stability,
    device_force,
    feedback_components,
    workspace_stiffness_n_per_m,
)
from teleop.control.kinematics import ArmModel
from teleop.control.path import (
    ControlOutput,
    MotionEvent,
    MotionSafety,
    PathFollowingController,
    PathMetrics,
)
from teleop.control.rate import rate_to_world, teleop_reference
from teleop.control.teleop import (
    JointStateTerms,
    TeleopController,
    TeleopOutput,
)
from teleop.control.wave import RobotWavePort
from teleop.core.clock import NS_PER_S, Clock
from teleop.core.config import Config
from teleop.core.ticks import TickBarrier, TickedInputs, head_schedule, status_schedule
from teleop.sim.proximity import ProximitySample, body_names

# The path-following task keeps the gripper open (fraction of full opening).
GRIPPER_OPEN = 1.0
GRIPPER_CLOSED = 0.0
# Lockstep: how long a cycle waits for the HMD record that applies at its tick (s).
HEAD_POSE_WAIT_S = 1.0
_CLUTCH = int(Button.CLUTCH)
_GRIPPER_CLOSE = int(Button.GRIPPER_CLOSE)
_BRAKING = int(Flag.BRAKING)


class ControllerOutputs(Protocol):
    """Where the controller's cores send their records (the service: the bus)."""

    def put(self, stream: str, rec: np.ndarray) -> None:
        """Send ``rec`` on ``stream``: joint_command, control_status, force_feedback or
        teleop_status (teleop.bus.graph)."""
        ...

    def resend(self, stream: str, rec: np.ndarray) -> None:
        """Send ``rec`` on ``stream`` again, unchanged, for a plant that re-sent its state:
        to the loop's receivers only (the observers' copy has it already, and a recording
        would hold it twice)."""
        ...


class ControllerCore:
    """What both tasks share: which states start a cycle, the command, the counters."""

    def __init__(
        self, config: Config, arm: ArmModel, outputs: ControllerOutputs, clock: Clock
    ) -> None:
        self.config = config
        self.arm = arm
        self.outputs = outputs
        self.clock = clock
        self.timestep_s = config.tick_s
        self.status = status_schedule(config)
        self._command = JOINT_COMMAND.new()
        self._lock = threading.Lock()  # the state gate: callbacks of several Zenoh threads
        # Held while a record of a cycle is filled, sent and kept, and while a kept one
        # is sent again (:meth:`_resend_answer`, from another callback).
        self._out_lock = threading.Lock()
        self._last_seq = -1
        self._realtime = config.run.mode == "realtime"
        self._state_seq = SeqCheck()  # realtime: which states are taken (see on_state)
        self.states_refused = 0  # realtime: states out of order (stale, forged, a restart's first)
        # Lockstep: per stream, copies of the records that answered the newest states (by
        # state seq), each to be sent again, byte for byte, when the plant sends its
        # state again: every state in flight may be the one whose answer was lost, and
        # the feedback of the state before the oldest goes out with it.
        kept = config.plant.lockstep_states_in_flight + 1
        self._answers: dict[str, TickedInputs[np.ndarray]] = {
            stream: TickedInputs(kept) for stream in ("force_feedback", "joint_command")
        }
        # t_source_ns of this run's state 0: a state 0 with the same stamp is the plant
        # re-sending it (byte for byte), not a new run.
        self._run_start_ns = -1
        self.cycles = 0
        self.skipped_states = 0
        self.commands_resent = 0  # answers sent again for a re-sent state (lockstep)
        self.runs = 0
        self.compute_ns_total = 0
        self._event = RUN_EVENT.new()
        self.events_sent: list[dict[str, Any]] = []

    # -- inputs ----------------------------------------------------------------------------
    def on_state(self, rec: np.ndarray, rx_ns: int) -> None:
        """A PLANT_STATE of this arm arrived at ``rx_ns``: a new run starts over, a state
        already answered (a re-send) is ignored, the others go to the task.

        A re-send of a state means the plant (lockstep) has waited a second for an
        answer: this controller's answer to it goes out again, byte for byte, in case it
        was lost on the way (:meth:`_resend_answer`; a receiver that has it drops the
        copy)."""
        with self._lock:
            seq = int(rec["seq"])
            started_over = False
            if self._realtime:
                # The plant never re-sends, and the state stream may be taken newest-only
                # (teleop.bus.graph), which may skip a new run's state 0. A seq going back
                # is the plant starting over once SeqCheck's rule says so (a run of states
                # in order), never on one state: a single stale or forged one would
                # otherwise make the controller forget its task.
                restarts = self._state_seq.restarts
                if not self._state_seq.accept(seq):
                    self.states_refused += 1
                    return
                # Re-anchored on a run that went back (not one that jumped ahead).
                restarted = self._state_seq.restarts != restarts
                started_over = restarted and 0 <= seq <= self._last_seq
            if (seq == 0 and int(rec["t_source_ns"]) != self._run_start_ns) or started_over:
                self._run_start_ns = int(rec["t_source_ns"])  # a new run (or plant restart):
                self.reset()  # forget the task state
                with self._out_lock:
                    for answers in self._answers.values():
                        answers.clear()
                self.runs += 1
            elif seq <= self._last_seq:
                if self._resend_answer(seq):
                    self.commands_resent += 1
                return  # a re-sent state this controller has already received
            elif self._last_seq >= 0 and seq > self._last_seq + 1:
                self.skipped_states += seq - self._last_seq - 1
            self._last_seq = seq
        self.handle_state(rec, rx_ns)

    def handle_state(self, state: np.ndarray, rx_ns: int) -> None:
        raise NotImplementedError

    def _resend_answer(self, state_seq: int) -> bool:
        """Lockstep: what answered ``state_seq`` sent again, unchanged, as far as it is
        kept: the FORCE_FEEDBACK of the state before (the haptic device steps a tick on
        the feedback of the tick before: one lost on the way, e.g. with a link that
        dropped when a process stalled past the Zenoh lease, holds back the handle
        sample the cycle of ``state_seq`` waits for), then this state's own feedback and
        JOINT_COMMAND; whether anything was sent."""
        feedback, commands = self._answers["force_feedback"], self._answers["joint_command"]
        with self._out_lock:
            records = [
                (stream, rec)
                for stream, rec in (
                    ("force_feedback", feedback.at(state_seq - 1)),
                    ("force_feedback", feedback.at(state_seq)),
                    ("joint_command", commands.at(state_seq)),
                )
                if rec is not None
            ]
            for stream, rec in records:
                self.outputs.resend(stream, rec)
            return bool(records)

    def _keep_answer(self, state_seq: int, stream: str, rec: np.ndarray) -> None:
        """Lockstep: keep a copy of ``rec``, sent on ``stream`` in answer to state
        ``state_seq``, to send again (caller holds ``_out_lock``)."""
        if not self._realtime:
            self._answers[stream].put(state_seq, rec.copy())

    def reset(self) -> None:
        """A new run: the task forgets its state."""
        raise NotImplementedError

    # -- outputs ---------------------------------------------------------------------------
    def send_command(
        self,
        state: np.ndarray,
        qd_ref_rad_s: np.ndarray,
        gripper_cmd: float,
        trace: np.ndarray,
        device_deadline_ns: int = 0,
    ) -> None:
        """Send the joint velocity references that answer ``state`` (and, in realtime
        teleoperation, the handle sample of the device period ``device_deadline_ns``)."""
        n = self.arm.n_joints
        with self._out_lock:
            self.cycles += 1
            cmd = self._command
            cmd["seq"] = self.cycles
            cmd["state_seq"] = state["seq"]
            cmd["device_deadline_ns"] = device_deadline_ns
            cmd["n_joints"] = n
            cmd["qd_ref_rad_s"][:n] = qd_ref_rad_s
            cmd["gripper_cmd"] = gripper_cmd
            cmd["trace_ns"][:] = trace
            now_ns = self.clock.now_ns()
            cmd["trace_ns"][Stage.CONTROLLER_TX] = now_ns
            cmd["t_source_ns"] = now_ns
            self.outputs.put("joint_command", cmd)
            self._keep_answer(int(state["seq"]), "joint_command", cmd)

    def send_events(self, events: list[MotionEvent], step: int) -> None:
        """Publish the run events the metrics saw (``controller_events``) and keep them
        for the summary."""
        for event in events:
            sim_time_ns = round(event.sim_time_s * 1e9)
            rec = next_run_event(self._event, event.event, self.clock.now_ns(), sim_time_ns,
                                 step, event.value)  # fmt: skip
            self.outputs.put("controller_events", rec)
            self.events_sent.append(
                {"event": event.event.name, "sim_time_s": event.sim_time_s, "value": event.value}
            )

    def summary(self) -> dict[str, Any]:
        mean_compute_us = self.compute_ns_total / self.cycles / 1e3 if self.cycles else None
        return {
            "cycles": self.cycles,
            "skipped_states": self.skipped_states,
            "states_refused": self.states_refused,
            "commands_resent": self.commands_resent,
            "runs": self.runs,
            "compute_mean_us": mean_compute_us,
            "events": self.events_sent,
        }


class PathCycle(ControllerCore):
    """Paper experiment 1: autonomous path following, one command per state."""

    def __init__(
        self, config: Config, arm: ArmModel, outputs: ControllerOutputs, clock: Clock
    ) -> None:
        super().__init__(config, arm, outputs, clock)
        self.controller = PathFollowingController(
            arm,
            config.control,
            config.path,
            period_s=self.timestep_s,
            clearance=ClearanceModel(config, arm),
        )
        self.metrics = PathMetrics.for_config(config)
        self._status = CONTROL_STATUS.new()

    def reset(self) -> None:
        self.controller.reset()
        self.metrics = PathMetrics.for_config(self.config)
        self.events_sent = []

    def handle_state(self, state: np.ndarray, rx_ns: int) -> None:
        n = self.arm.n_joints
        t0 = self.clock.now_ns()
        output = self.controller.update(
            state["q_rad"][:n], state["qd_rad_s"][:n], float(state["gripper_opening_m"])
        )
        self.compute_ns_total += self.clock.now_ns() - t0
        trace = state["trace_ns"].copy()
        trace[Stage.CONTROLLER_RX] = rx_ns  # path following: the state is the input
        self.send_command(state, output.qd_ref_rad_s, GRIPPER_OPEN, trace)
        sim_time_ns = int(state["sim_time_ns"])
        braked = bool(int(state["flags"]) & _BRAKING)
        self.metrics.add(sim_time_ns * 1e-9, output, commanded=not braked)
        if self.metrics.events:
            self.send_events(self.metrics.take_events(), int(state["step"]))
        if self.status.is_sample(int(state["step"])):
            self._send_status(output, sim_time_ns)

    def _send_status(self, output: ControlOutput, sim_time_ns: int) -> None:
        n = self.arm.n_joints
        rec = self._status
        rec["seq"] = self.cycles
        rec["t_source_ns"] = self.clock.now_ns()
        rec["sim_time_ns"] = sim_time_ns
        rec["desired_p_m"] = output.desired_p_m
        rec["tool_p_m"] = output.tool_p_m
        rec["path_error_m"] = output.path_error_m
        rec["manipulability"] = output.manipulability
        rec["path_s"] = output.path_s
        rec["n_joints"] = n
        rec["qd_cmd_rad_s"][:n] = output.qd_c_rad_s
        self.outputs.put("control_status", rec)

    def summary(self) -> dict[str, Any]:
        return {
            **self.metrics.summary(),
            "clearance_queries": self.controller.clearance.queries
            if self.controller.clearance is not None
            else None,
            "settle_s": self.metrics.settle_s,
            "compensation": self.config.control.compensation,
            **super().summary(),
        }


class BilateralCycle(ControllerCore):
    """Paper experiment 2: bilateral teleoperation through the haptic device.

    Thread safety: in lockstep the tick barrier runs each cycle in the callback that
    completes it. In realtime both half-cycles run in the bus callbacks (the haptic and
    plant links are served by different threads), one at a time: an input that arrives
    while one runs waits as pending, newest of its kind wins (:meth:`_dispatch`).
    """

    INPUTS = ("state", "haptic")  # joined per tick in lockstep; the state has contact too

    def __init__(
        self, config: Config, arm: ArmModel, outputs: ControllerOutputs, clock: Clock
    ) -> None:
        super().__init__(config, arm, outputs, clock)
        self.lockstep = config.run.mode == "lockstep"
        # The device renders the springs from the local model every servo period.
        self.stability = check_stability(
            config.teleop, config.haptic, config.haptic.render_period_s
        )
        mj_model = mujoco.MjModel.from_xml_path(str(config.robot.scene_path))
        self.controller = TeleopController(
            arm,
            config.teleop,
            config.control,
            period_s=self.timestep_s,
            mj_body_names=body_names(mj_model),
            clearance=ClearanceModel(config, arm),
        )
        self.head_schedule = head_schedule(config)
        # Lockstep: a handle sample more than this many ticks behind the state is silent.
        self.stale_ticks = round(config.haptic.stale_feedback_s / self.timestep_s)
        # Realtime: the handle is silent when its newest sample arrived longer ago than
        # this on the controller's clock. Not by ticks: a sample's tick is the newest
        # state the device had seen, a whole round trip behind across a slow link.
        self.handle_silent_ns = round(config.haptic.stale_feedback_s * 1e9)
        # Realtime: a newest plant state older than this on the clock means the plant went
        # silent; a command answering it would only be braked on (plant.watchdog_s).
        self.state_silent_ns = round(config.plant.watchdog_s * 1e9)
        self._feedback = FORCE_FEEDBACK.new()
        self.feedback_count = 0  # FORCE_FEEDBACK records sent (their seq)
        self._status = TELEOP_STATUS.new()
        self.head_poses = TickedInputs()
        self.haptic = Latest()
        self.barrier = TickBarrier(self.INPUTS, self._on_tick)
        self.states = Latest()  # realtime: the newest state
        self._rt_lock = threading.Lock()  # guards the fields below, held briefly
        self._rt_busy = False
        self._pending: dict[str, Any] = {}
        self._last_output: TeleopOutput | None = None
        # teleop.stabiliser "wave": the robot's end of the wave channel (else None).
        self.wave = (
            RobotWavePort(
                config.teleop.wave_impedance_n_s_m, config.tick_s, config.plant.watchdog_s
            )
            if config.teleop.stabiliser == "wave"
            else None
        )
        # When a handle's wave is taken (s): the state's simulated time in lockstep (each
        # state one bus period on), the controller's own clock in realtime.
        self._wave_time_s: Callable[[np.ndarray], float] = (
            (lambda state: int(state["sim_time_ns"]) / NS_PER_S)
            if self.lockstep
            else (lambda _state: self.clock.now_ns() / NS_PER_S)
        )
        # Realtime: (state seq, its joint-state terms of the control law, its closest
        # obstacle), prepared after that state's feedback went out, so a handle sample
        # answered on that state runs only the handle-dependent rest of the law
        # (TeleopController.prepare).
        self._prepared: tuple[int, JointStateTerms | None, ProximitySample | None]
        self._prepared = (-1, None, None)
        # Realtime: the handle samples' order and age, the states' age, and one log of
        # the loops left unanswered here (too old, or superseded while busy).
        self.shed_log = StampLog(1)
        self.haptic_in = Inbound(Stage.HAPTIC_SAMPLE, shed_log=self.shed_log, name="haptic_state")
        self.state_in = Inbound(Stage.PLANT_STATE_TX, shed_log=self.shed_log, name="plant_state")
        self.haptic_before_state = 0  # samples that arrived before any plant state
        self._reset_metrics()

    def _reset_metrics(self) -> None:
        self.tracking_sq_sum = 0.0
        self.tracking_count = 0
        self.max_obstacle_force_n = 0.0
        self.max_device_force_n = 0.0
        self.held_weight_sum_n = 0.0
        self.held_count = 0
        self.no_input_cycles = 0
        self.missing_head_poses = 0
        self.max_scene_force_n = 0.0
        self.max_limits_force_n = 0.0
        self.clearance_held_cycles = 0
        self.safety = MotionSafety(self.config.control.singularity_event_manipulability)
        self.plant_silent_samples = 0

    def reset(self) -> None:
        self.controller.reset()
        self.barrier.reset()
        if self.wave is not None:
            self.wave.reset()
        self._prepared = (-1, None, None)
        self._reset_metrics()
        self.events_sent = []

    # -- inputs ----------------------------------------------------------------------------
    def on_haptic(self, rec: np.ndarray, rx_ns: int) -> None:
        """A HAPTIC_STATE sample arrived at ``rx_ns``."""
        if self.lockstep:
            self.barrier.put("haptic", int(rec["tick"]), rec)
        else:
            self.haptic(rec, rx_ns)
            self._dispatch("haptic", (rec, rx_ns))

    def on_head_pose(self, rec: np.ndarray, rx_ns: int) -> None:
        """A HEAD_POSE arrived: it applies from its ``valid_from_tick``."""
        self.head_poses.put(int(rec["valid_from_tick"]), rec)

    def handle_state(self, state: np.ndarray, rx_ns: int) -> None:
        if self.lockstep:
            state["trace_ns"][Stage.CONTROLLER_RX] = rx_ns
            self.barrier.put("state", int(state["seq"]), state)
        else:
            state["trace_ns"][Stage.CONTROLLER_STATE_RX] = rx_ns
            with self._rt_lock:
                if not self.state_in.arrived(state, rx_ns):
                    return
            self.states(state, rx_ns)
            self._dispatch("state", state)

    # -- realtime half-cycles --------------------------------------------------------------
    def _dispatch(self, kind: str, item: Any) -> None:
        """Run a half-cycle now if the controller is free, else leave it pending.

        The callback that finds the controller free runs its own input, then the inputs
        that arrived meanwhile (newest of each kind; older ones are superseded: shed and
        logged). A busy controller thus never makes a Zenoh thread wait, no backlog
        builds up behind a slow cycle, and with a free controller an input costs no
        hand-off. One pass only: what arrives during it waits for the next callback
        (each stream comes once per bus period), so no thread loops forever under overload.
        """
        with self._rt_lock:
            if kind == "haptic" and not self.haptic_in.accept(*item, shed=False):
                return
            older = self._pending.pop(kind, None)
            if older is not None:
                self._drop(kind, older)
            if self._rt_busy:
                self._pending[kind] = item
                return
            self._rt_busy = True
        try:
            self._half_cycle(kind, item)
            with self._rt_lock:
                pending, self._pending = self._pending, {}
            for name in ("haptic", "state"):
                if name in pending:
                    self._half_cycle(name, pending[name])
        finally:
            with self._rt_lock:
                self._rt_busy = False

    def _half_cycle(self, kind: str, item: Any) -> None:
        if kind == "haptic":
            self.command_half_cycle(*item)
        else:
            self.feedback_half_cycle(item)

    def _drop(self, kind: str, item: Any) -> None:
        """An input left unanswered (the caller holds ``_rt_lock``)."""
        if kind == "haptic":
            self.haptic_in.drop(item[0])
        else:
            self.state_in.drop(item)

    def command_half_cycle(self, haptic: np.ndarray, rx_ns: int) -> None:
        """One HAPTIC_STATE sample -> one JOINT_COMMAND, on the newest plant state."""
        if self.haptic_in.too_old(haptic, self.clock.now_ns()):
            with self._rt_lock:
                self._drop("haptic", (haptic, rx_ns))
            return
        latest_state = self.states.get()
        if latest_state is None:
            self.haptic_before_state += 1
            return
        state = latest_state[0]
        tick = int(state["seq"])
        t0 = self.clock.now_ns()
        if self.state_in.age_ns(state, t0) > self.state_silent_ns:
            self.plant_silent_samples += 1  # the plant went silent: command no motion
            with self._rt_lock:  # the sample goes unanswered: shed, not vanished
                self._drop("haptic", (haptic, rx_ns))
            return
        prepared_seq, terms, obstacle = self._prepared
        if prepared_seq != tick:  # not prepared for this state: all of it here
            terms, obstacle = None, ProximitySample.from_state(state)
        yaw_rad = self._head_yaw_rad(tick)
        output, gripper_cmd, _ = self._control(state, haptic, obstacle, yaw_rad, terms)
        self.compute_ns_total += self.clock.now_ns() - t0
        trace = np.zeros(N_STAGES, dtype=np.int64)  # np.zeros_like is slower on a record field
        trace[Stage.HAPTIC_SAMPLE] = haptic["trace_ns"][Stage.HAPTIC_SAMPLE]
        trace[Stage.CONTROLLER_RX] = rx_ns
        deadline_ns = int(haptic["device_deadline_ns"])
        self.send_command(state, output.qd_ref_rad_s, gripper_cmd, trace, deadline_ns)
        self._last_output = output
        if self.status.is_sample(tick):
            self._send_status(tick, state, output, float(state["held_mass_kg"]) > 0)

    def feedback_half_cycle(self, state: np.ndarray) -> None:
        """One PLANT_STATE -> one FORCE_FEEDBACK (its trace continues the command's)."""
        if self.state_in.too_old(state, self.clock.now_ns()):
            with self._rt_lock:
                self._drop("state", state)
            return
        tick = int(state["seq"])
        latest = self.haptic.get()
        t0 = self.clock.now_ns()
        haptic = None
        if latest is not None and t0 - latest[1] <= self.handle_silent_ns:
            haptic = latest[0]
        if haptic is None:
            self.no_input_cycles += 1
        handle_d_m = np.array(haptic["device_p_m"]) if haptic is not None else np.zeros(3)
        yaw_rad = self._head_yaw_rad(tick)
        obstacle = ProximitySample.from_state(state)
        # The scene's and the limits' push-back of the newest state prepared (the previous
        # one): measuring this state's clearance first would delay the feedback by it.
        _, previous_terms, _ = self._prepared
        components, device_f_n, held_mass = self._feedback_force(
            state, obstacle, handle_d_m, yaw_rad, previous_terms, live=haptic is not None
        )
        self.compute_ns_total += self.clock.now_ns() - t0
        self._send_feedback(
            tick, state, components, device_f_n, state["trace_ns"], handle_d_m, haptic is not None
        )
        if self._last_output is not None:
            self._measure(self._last_output, components, device_f_n, held_mass)
        # Off the loop's critical path: the next handle sample will be answered on this
        # state; its joint-state half of the control law can run now.
        t0 = self.clock.now_ns()
        terms = self._prepare(state)
        self._prepared = (tick, terms, obstacle)
        self.compute_ns_total += self.clock.now_ns() - t0
        self._watch(state, terms)

    # -- the control law and the feedback --------------------------------------------------
    def _control(
        self,
        state: np.ndarray,
        haptic: np.ndarray | None,
        obstacle: ProximitySample | None,
        yaw_rad: float,
        terms: JointStateTerms | None = None,
    ) -> tuple[TeleopOutput, float, np.ndarray]:
        """One control law cycle from the handle (None: no input, the tool holds still);
        ``terms``: the joint-state half of the law, prepared from ``state`` (None:
        computed here).

        ``yaw_rad``: the HMD's view yaw that applies at the state's tick.

        Returns the output, the gripper command and the handle offset (m, device frame).
        """
        if haptic is None:
            handle_d_m, buttons = np.zeros(3), 0
        else:  # the record is this service's own and never written: a view will do
            handle_d_m, buttons = haptic["device_p_m"], int(haptic["buttons"])
        # Plain int bit tests: an enum.Flag operation costs microseconds per call.
        clutch = bool(buttons & _CLUTCH)
        gripper_cmd = GRIPPER_CLOSED if buttons & _GRIPPER_CLOSE else GRIPPER_OPEN
        if self.wave is not None and haptic is not None:
            # The handle's rate from its wave, against the robot's newest resistance.
            rate = self.wave.rate(haptic["wave_u"], self._wave_time_s(state)).tolist()
            v_ref = np.zeros(3) if clutch else rate_to_world(*rate, yaw_rad, self.config.teleop)
        else:
            v_ref = teleop_reference(handle_d_m, yaw_rad, clutch, self.config.teleop)
        n = self.arm.n_joints
        output = self.controller.update(
            state["q_rad"][:n],
            state["qd_rad_s"][:n],
            v_ref,
            obstacle,
            gripper_cmd,
            clutch,
            terms=terms,
            gripper_opening_m=float(state["gripper_opening_m"]),
        )
        return output, gripper_cmd, handle_d_m

    def _prepare(self, state: np.ndarray) -> JointStateTerms:
        """The joint-state half of the control law (clearance included) at ``state``."""
        n = self.arm.n_joints
        return self.controller.prepare(
            state["q_rad"][:n], state["qd_rad_s"][:n], float(state["gripper_opening_m"])
        )

    def _watch(self, state: np.ndarray, terms: JointStateTerms) -> None:
        """The state's clearance and manipulability into the run's safety figures, and
        the events they begin (CONTACT, SINGULARITY) out on ``controller_events``."""
        self.safety.add(int(state["sim_time_ns"]) * 1e-9, terms.clearance, terms.manipulability)
        if self.safety.events:
            self.send_events(self.safety.take_events(), int(state["step"]))

    def _feedback_force(
        self,
        state: np.ndarray,
        obstacle: ProximitySample | None,
        handle_d_m: np.ndarray,
        yaw_rad: float,
        terms: JointStateTerms | None,
        live: bool = True,
    ) -> tuple[FeedbackComponents, np.ndarray, float]:
        """Force feedback components, the device force (N, device frame) and the held mass,
        from the contact in ``state`` (PLANT_STATE) and the push-back of the scene and the
        arm's limits in ``terms`` (None: none). Not ``live`` (the handle went silent, or
        none yet): the components are still reported, the device force is zero (a handle
        that comes back must not be pushed by forces it did not feel build up)."""
        config = self.config
        world_f_gripper_n = np.array(state["world_f_contact_n"])
        held_mass_kg = float(state["held_mass_kg"])
        components = feedback_components(
            world_f_gripper_n,
            held_mass_kg,
            obstacle,
            handle_d_m,
            config.teleop,
            terms.world_f_scene_n if terms is not None else None,
            terms.world_f_limits_n if terms is not None else None,
        )
        if self.wave is not None:  # the robot's resistance: all but the handle's own spring
            robot_only = dataclasses.replace(components, device_workspace_f_n=np.zeros(3))
            self.wave.resist(-device_force(robot_only, yaw_rad, config.teleop, config.haptic))
        if not live:
            return components, np.zeros(3), held_mass_kg
        device_f_n = device_force(components, yaw_rad, config.teleop, config.haptic)
        return components, device_f_n, held_mass_kg

    def _head_yaw_rad(self, tick: int) -> float:
        """The HMD's predicted view yaw that applies at ``tick`` (config yaw before any)."""
        hmd = self.config.hmd
        if tick < self.head_schedule.lead_ticks:  # before the first HMD record can apply
            return hmd.head_yaw_rad
        if self.lockstep:
            valid_from = self.head_schedule.valid_from_for(tick)
            assert valid_from is not None
            rec = self.head_poses.wait_for(valid_from, HEAD_POSE_WAIT_S)
        else:  # the newest record: no need to know which one the schedule expects
            rec = self.head_poses.latest_at(tick)
        if rec is None:
            self.missing_head_poses += 1
            return hmd.head_yaw_rad
        return float(rec["predicted_yaw_rad"])

    # -- the lockstep cycle ----------------------------------------------------------------
    def _on_tick(self, tick: int, records: dict[str, np.ndarray]) -> None:
        state = records["state"]
        haptic = records.get("haptic")
        if haptic is not None and tick - int(haptic["tick"]) > self.stale_ticks:
            haptic = None  # the handle went silent: no reference, the tool holds still
        # Before the compute's clock starts: in lockstep this may wait for the HMD's record.
        yaw_rad = self._head_yaw_rad(tick)
        t0 = self.clock.now_ns()
        if haptic is None:
            self.no_input_cycles += 1
        obstacle = ProximitySample.from_state(state)
        terms = self._prepare(state)
        # The feedback first: with wave variables the control decodes the handle's rate
        # against the resistance of this state.
        handle_d_m = haptic["device_p_m"] if haptic is not None else np.zeros(3)
        components, device_f_n, held_mass = self._feedback_force(
            state, obstacle, handle_d_m, yaw_rad, terms, live=haptic is not None
        )
        output, gripper_cmd, _ = self._control(state, haptic, obstacle, yaw_rad, terms)
        self.compute_ns_total += self.clock.now_ns() - t0

        trace = state["trace_ns"].copy()
        if haptic is not None:
            trace[Stage.HAPTIC_SAMPLE] = haptic["trace_ns"][Stage.HAPTIC_SAMPLE]
        self._send_feedback(
            tick, state, components, device_f_n, trace, handle_d_m, haptic is not None
        )
        self.send_command(state, output.qd_ref_rad_s, gripper_cmd, trace)
        self._measure(output, components, device_f_n, held_mass)
        self._watch(state, terms)
        if self.status.is_sample(tick):
            self._send_status(tick, state, output, held_mass > 0)

    # -- outputs ---------------------------------------------------------------------------
    def _send_feedback(
        self,
        tick: int,
        state: np.ndarray,
        components: FeedbackComponents,
        device_f_n: np.ndarray,
        trace: np.ndarray,
        handle_d_m: np.ndarray,
        live: bool,
    ) -> None:
        """The FORCE_FEEDBACK of ``tick``: the device force at the handle position it was
        computed at (``handle_d_m``) and, as its local contact model, how the force
        changes about it (the workspace spring's stiffness; none with wave variables,
        whose handle renders its own spring, nor for a handle that is not ``live``)."""
        rec = self._feedback
        with self._out_lock:
            self.feedback_count += 1  # a Python int: += on a record field is far slower
            rec["seq"] = self.feedback_count
            rec["tick"] = tick
            rec["sim_time_ns"] = state["sim_time_ns"]
            rec["device_f_n"] = device_f_n
            rec["world_f_contact_n"] = components.world_contact_f_n
            rec["world_f_weight_n"] = components.world_weight_f_n
            rec["world_f_obstacle_n"] = components.world_obstacle_f_n
            rec["device_f_workspace_n"] = components.device_workspace_f_n
            rec["world_f_scene_n"] = components.world_scene_f_n
            rec["world_f_limits_n"] = components.world_limits_f_n
            if self.wave is not None:
                rec["wave_v"] = self.wave.wave_back()
            rec["device_p_ref_m"] = handle_d_m
            if live and self.wave is None:
                stiffness = workspace_stiffness_n_per_m(handle_d_m, self.config.teleop)
                rec["device_k_n_per_m"] = stiffness.ravel()
            else:
                rec["device_k_n_per_m"] = 0.0
            rec["trace_ns"][:] = trace
            now_ns = self.clock.now_ns()
            rec["trace_ns"][Stage.FEEDBACK_TX] = now_ns
            rec["t_source_ns"] = now_ns
            self.outputs.put("force_feedback", rec)
            self._keep_answer(tick, "force_feedback", rec)

    def _measure(
        self,
        output: TeleopOutput,
        components: FeedbackComponents,
        device_f_n: np.ndarray,
        held_mass: float,
    ) -> None:
        # Runs after the feedback went out, before the next input: in floats (a numpy norm
        # of a 3-vector costs more than the arithmetic, and more still with cold caches).
        error = output.world_v_ref_m_s - output.world_v_tool_m_s
        self.tracking_sq_sum += float(error @ error)
        self.tracking_count += 1
        obstacle_n = math.hypot(*components.world_obstacle_f_n.tolist())
        self.max_obstacle_force_n = max(self.max_obstacle_force_n, obstacle_n)
        scene_n = math.hypot(*components.world_scene_f_n.tolist())
        self.max_scene_force_n = max(self.max_scene_force_n, scene_n)
        limits_n = math.hypot(*components.world_limits_f_n.tolist())
        self.max_limits_force_n = max(self.max_limits_force_n, limits_n)
        if output.held_pairs:
            self.clearance_held_cycles += 1
        self.max_device_force_n = max(self.max_device_force_n, math.hypot(*device_f_n.tolist()))
        if held_mass > 0:
            self.held_weight_sum_n += math.hypot(*components.world_weight_f_n.tolist())
            self.held_count += 1

    def _send_status(
        self, tick: int, state: np.ndarray, output: TeleopOutput, holding: bool
    ) -> None:
        rec = self._status
        rec["seq"] += 1
        rec["t_source_ns"] = self.clock.now_ns()
        rec["tick"] = tick
        rec["sim_time_ns"] = state["sim_time_ns"]
        rec["world_v_ref_m_s"] = output.world_v_ref_m_s
        rec["world_v_tool_m_s"] = output.world_v_tool_m_s
        rec["world_p_tool_m"] = output.world_p_tool_m
        rec["speed_scale"] = min(1.0, max(0.0, output.speed_scale))
        rec["gripper_cmd"] = output.gripper_cmd
        rec["holding"] = int(holding)
        self.outputs.put("teleop_status", rec)

    def save_shed_log(self, path: Path) -> None:
        """Write the HAPTIC_SAMPLE stamps of the loops left unanswered here."""
        with self._rt_lock:
            self.shed_log.save(path)

    def summary(self) -> dict[str, Any]:
        rms = (self.tracking_sq_sum / self.tracking_count) ** 0.5 if self.tracking_count else None
        held = self.held_weight_sum_n / self.held_count if self.held_count else None
        return {
            "velocity_tracking_rms_m_s": rms,
            "max_obstacle_force_n": self.max_obstacle_force_n,
            "max_scene_force_n": self.max_scene_force_n,
            "max_limits_force_n": self.max_limits_force_n,
            "clearance_held_cycles": self.clearance_held_cycles,
            **self.safety.summary(),
            "motion_problems": self.safety.problems(),
            "clearance_queries": self.controller.clearance.queries
            if self.controller.clearance is not None
            else None,
            "max_device_force_command_n": self.max_device_force_n,
            "held_weight_n": held,
            "held_cycles": self.held_count,
            "no_input_cycles": self.no_input_cycles,
            "plant_silent_samples": self.plant_silent_samples,
            "missing_head_poses": self.missing_head_poses,
            # Obstacle samples on an arm body the model has no frame for: ignored, counted.
            "unmapped_obstacle_samples": self.controller.unmapped_obstacle_samples,
            "barrier_dropped": self.barrier.dropped,
            "haptic_lost": self.haptic_in.seq.lost,
            "haptic_reordered": self.haptic_in.seq.reordered,
            "haptic_before_state": self.haptic_before_state,
            "haptic_shed": self.haptic_in.shed,
            "states_shed": self.state_in.shed,
            "haptic_stream": self.haptic_in.counts(),  # lost, reordered, jumps, restarts...
            "state_stream": self.state_in.counts(),
            # wave variables: the energy the handle's waves brought, what the robot's end
            # held back of waves passed on beyond it (a varying delay), what the robot's
            # surroundings absorbed and the series damper dissipated (teleop.control.wave)
            "wave_bank": self.wave.summary() if self.wave is not None else None,
            "stability": {
                "k_max_n_per_m": self.stability.k_max_n_per_m,
                "k_workspace_n_per_m": self.stability.k_workspace_n_per_m,
                "k_obstacle_handle_n_per_m": self.stability.k_obstacle_handle_n_per_m,
            },
            **super().summary(),
        }
