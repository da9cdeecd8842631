"""The controller service: one control cycle per plant state, event driven.

Each JOINT_STATE is handled in the Zenoh callback that delivers it (measured: a
hand-off to a service thread cost about 60 us per cycle on this 2-core machine,
for a compute of about 100-150 us): the cycle computes the path-following command
with the same :class:`PathFollowingController` as the in-process run and publishes
a JOINT_COMMAND that names the state it answers (``state_seq``), then a
CONTROL_STATUS for the recorder. A controller too slow for the plant's rate makes
its commands stale, and the plant's watchdog brakes: the safe failure.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import numpy as np

from teleop.bus import Publisher, subscribe
from teleop.control import ControlOutput, PathFollowingController
from teleop.experiments import PathMetrics
from teleop.kinematics import build_arm_model
from teleop.messages import (
    CONTROL_STATUS,
    JOINT_COMMAND,
    JOINT_STATE,
    DecodeError,
    Kind,
    Reason,
    Stage,
)
from teleop.service import Service

logger = logging.getLogger(__name__)

# The path-following task keeps the gripper open (fraction of full opening).
GRIPPER_OPEN = 1.0


class ControllerService(Service):
    name = "controller"

    def open(self) -> None:
        super().open()
        assert self.session is not None
        self.arm = build_arm_model(self.config.robot)
        self.controller = PathFollowingController(
            self.arm, self.config.control, self.config.path, period_s=self.config.plant.timestep_s
        )
        self.metrics = PathMetrics(settle_s=self.config.run.settle_s)
        self.status_every_steps = max(
            1, round(1.0 / (self.config.control.status_rate_hz * self.config.plant.timestep_s))
        )
        self.command_pub = self.keep(
            Publisher.declare(self.session, self.topics.joint_command, JOINT_COMMAND)
        )
        self.status_pub = self.keep(
            Publisher.declare(self.session, self.topics.control_status, CONTROL_STATUS)
        )
        self._lock = threading.Lock()
        self._last_seq = -1
        self.keep(
            subscribe(
                self.session, self.topics.joint_state, JOINT_STATE, self._on_state, self.drops
            )
        )
        self._command = JOINT_COMMAND.new()
        self._status = CONTROL_STATUS.new()
        self.cycles = 0
        self.skipped_states = 0
        self.runs = 0
        self.compute_ns_total = 0
        self.announce()

    def _on_state(self, rec: np.ndarray, rx_ns: int) -> None:
        if int(rec["n_joints"]) != self.arm.n_joints:
            detail = f"n_joints={int(rec['n_joints'])}, arm has {self.arm.n_joints}"
            self.drops.record(DecodeError(Kind.JOINT_STATE, Reason.COUNT, detail))
            return
        with self._lock:
            seq = int(rec["seq"])
            if seq == 0:  # a new run began (or the plant restarted): forget the path state
                self.controller.reset()
                self.metrics = PathMetrics(settle_s=self.config.run.settle_s)
                self.runs += 1
            elif seq <= self._last_seq:
                return  # a re-sent state this controller has already answered
            elif self._last_seq >= 0 and seq > self._last_seq + 1:
                self.skipped_states += seq - self._last_seq - 1
            self._last_seq = seq
            self._cycle(rec, rx_ns)

    def run(self, stop: threading.Event) -> None:
        """The work happens in the state callback; this thread only waits to be stopped."""
        stop.wait()

    def _cycle(self, state: np.ndarray, rx_ns: int) -> None:
        n = self.arm.n_joints
        t0 = time.monotonic_ns()
        output = self.controller.update(state["q_rad"][:n], state["qd_rad_s"][:n])
        self.compute_ns_total += time.monotonic_ns() - t0
        sim_time_ns = int(state["sim_time_ns"])
        self.cycles += 1

        cmd = self._command
        cmd["seq"] = self.cycles
        cmd["state_seq"] = state["seq"]
        cmd["n_joints"] = n
        cmd["qd_ref_rad_s"][:n] = output.qd_ref_rad_s
        cmd["gripper_cmd"] = GRIPPER_OPEN
        cmd["trace_ns"][:] = state["trace_ns"]
        cmd["trace_ns"][Stage.CONTROLLER_RX] = rx_ns
        now_ns = time.monotonic_ns()
        cmd["trace_ns"][Stage.CONTROLLER_TX] = now_ns
        cmd["t_source_ns"] = now_ns
        self.command_pub.put(cmd)
        self.metrics.add(sim_time_ns * 1e-9, output)
        if int(state["step"]) % self.status_every_steps == 0:
            self._publish_status(output, sim_time_ns, now_ns)

    def _publish_status(self, output: ControlOutput, sim_time_ns: int, now_ns: int) -> None:
        n = self.arm.n_joints
        rec = self._status
        rec["seq"] = self.cycles
        rec["t_source_ns"] = now_ns
        rec["sim_time_ns"] = sim_time_ns
        rec["desired_p_m"] = output.desired_p_m
        rec["tool_p_m"] = output.tool_p_m
        rec["path_error_m"] = output.path_error_m
        rec["manipulability"] = output.manipulability
        rec["path_s"] = output.path_s
        rec["n_joints"] = n
        rec["qd_cmd_rad_s"][:n] = output.qd_c_rad_s
        self.status_pub.put(rec)

    def summary(self) -> dict[str, Any]:
        mean_compute_us = self.compute_ns_total / self.cycles / 1e3 if self.cycles else None
        return {
            **super().summary(),
            **self.metrics.summary(),
            "settle_s": self.metrics.settle_s,
            "compensation": self.config.control.compensation,
            "cycles": self.cycles,
            "skipped_states": self.skipped_states,
            "runs": self.runs,
            "compute_mean_us": mean_compute_us,
        }
