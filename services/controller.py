"""The controller service: :mod:`teleop.control.cycle` on the bus.

Inputs: PLANT_STATE (every task) and, in teleoperation, HAPTIC_STATE and HEAD_POSE.
Outputs: JOINT_COMMAND, and CONTROL_STATUS (path following) or FORCE_FEEDBACK (with
its batched copy for the recorder) and TELEOP_STATUS (teleoperation). Each input is
handled on the thread that takes it off the bus (Zenoh's callback thread, or for a
stream taken newest-only in realtime its NewestSubscriber's: the path-following states,
the head poses), with no further hand-off; the cycles themselves are the cores'.
"""

from __future__ import annotations

import logging
import sys
import threading
from typing import Any

import numpy as np

from teleop.bus.messages import DecodeError, Kind, Reason
from teleop.bus.service import Service, service_main
from teleop.bus.session import BatchPublisher
from teleop.control.cycle import BilateralCycle, ControllerCore, PathCycle
from teleop.control.kinematics import build_arm_model
from teleop.core.clock import MonotonicClock
from teleop.core.rundir import shed_path

logger = logging.getLogger(__name__)


class ControllerService(Service):
    name = "controller"

    def open(self) -> None:
        super().open()
        assert self.session is not None
        session, topics = self.session, self.topics
        self.arm = build_arm_model(self.config.robot)
        teleoperated = self.config.run.teleoperated
        outputs = ["joint_command", "controller_events"]
        outputs += ["force_feedback", "teleop_status"] if teleoperated else ["control_status"]
        self.publishers = {name: self.publish_stream(name) for name in outputs}
        self.feedback_batch: BatchPublisher | None = None
        core_class = BilateralCycle if teleoperated else PathCycle
        self.core: ControllerCore = core_class(self.config, self.arm, self, MonotonicClock())
        if isinstance(self.core, BilateralCycle):
            self.feedback_batch = self.keep(  # the recorder's copy, several per message
                BatchPublisher.for_stream(
                    session, topics, "force_feedback_batch", self.config.bus.observer_batch_records
                )
            )
            core = self.core
            self.subscribe_stream("haptic_state", core.on_haptic)
            self.subscribe_stream("head_pose", core.on_head_pose)
        self.subscribe_stream("plant_state", self._on_state)
        self.announce()

    def _on_state(self, rec: np.ndarray, rx_ns: int) -> None:
        """Accept states of exactly this arm; anything else is counted and dropped."""
        if int(rec["n_joints"]) != self.arm.n_joints:
            detail = f"n_joints={int(rec['n_joints'])}, arm has {self.arm.n_joints}"
            self.drops.record(DecodeError(Kind.PLANT_STATE, Reason.COUNT, detail))
            return
        self.core.on_state(rec, rx_ns)

    # -- ControllerOutputs ---------------------------------------------------------------
    def put(self, stream: str, rec: np.ndarray) -> None:
        data = self.publishers[stream].put(rec)
        if stream == "force_feedback" and self.feedback_batch is not None:
            self.feedback_batch.add(data)

    def resend(self, stream: str, rec: np.ndarray) -> None:
        self.publishers[stream].put(rec)

    # -- lifecycle -----------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        stop.wait()  # every cycle runs in the bus callbacks

    def close(self) -> None:
        core = getattr(self, "core", None)  # None if open() failed before building it
        if self.options.run_dir is not None and isinstance(core, BilateralCycle):
            core.save_shed_log(shed_path(self.options.run_dir, self.instance))
        super().close()

    def summary(self) -> dict[str, Any]:
        return {**super().summary(), **self.core.summary()}


if __name__ == "__main__":
    sys.exit(service_main(ControllerService))
