"""The haptic service: :class:`teleop.devices.haptic.loop.HapticLoop` on the bus.

Inputs: FORCE_FEEDBACK (the force to render, from the controller), HAND_INPUT (where the
operator's hand pulls the handle, keyed by the plant tick it applies from) and, in
lockstep only, PLANT_STATE, used as the simulation clock (its ``seq`` is the plant tick).
In a run of several robots each comes from every robot's keys (the robot a hand input
came on is the one the hand means to drive), and each robot's plant's FINISHED takes it
off the clock.
Output: HAPTIC_STATE per device period, with the encoder position, the velocity estimate
and the force actually rendered, in the device frame, and the deadline of the device
period it was sampled in (the realtime plant steps on that clock); the recorder gets the
same records batched. The loop (both timing modes, the feedback hold and fade) is in
HapticLoop; the device is the emulator, driven through the HapticDevice interface only.
At exit the realtime latency stamps go to the run directory.
"""

from __future__ import annotations

import logging
import sys
import threading
from typing import Any

import numpy as np

from teleop.bus.messages import Event
from teleop.bus.service import Service, service_main
from teleop.bus.session import BatchPublisher, Publisher, RecordCallback
from teleop.core.clock import MonotonicClock
from teleop.core.rundir import HAPTIC_SAMPLES_FILE, HAPTIC_TRACE_FILE, shed_path
from teleop.devices.haptic.device import EmulatedDevice, max_stable_stiffness_n_per_m
from teleop.devices.haptic.loop import HapticLoop

logger = logging.getLogger(__name__)


class HapticService(Service):
    name = "haptic"

    def open(self) -> None:
        super().open()
        assert self.session is not None
        cfg = self.config
        self.lockstep = cfg.run.mode == "lockstep"
        self.device = EmulatedDevice(cfg.haptic, cfg.haptic.render_period_s)
        self.device.connect()
        self.loop = HapticLoop(cfg, self.device, self, MonotonicClock(), lockstep=self.lockstep)
        # Per robot (Config.robot_ids; one but in a run of several): its sample stream,
        # the recorder's batched copy, and what comes back from it.
        self.state_pubs: list[Publisher] = []
        self.state_batches: list[BatchPublisher] = []
        session = self.session
        for robot, topics in enumerate(self.robot_topics):
            self.state_pubs.append(self.publish_stream("haptic_state", topics))
            self.state_batches.append(
                self.keep(  # the recorder's copy, several samples per message
                    BatchPublisher.for_stream(
                        session, topics, "haptic_state_batch", cfg.bus.observer_batch_records
                    )
                )
            )
            self.subscribe_stream("force_feedback", self._on_feedback(robot), topics)
            self.subscribe_stream("hand_input", self._on_hand(robot), topics)
            if self.lockstep:  # realtime: the feedback's tick is the clock (see HapticLoop)
                self.subscribe_stream("plant_state", self._on_state(robot), topics)
            if len(self.robot_topics) > 1:  # a robot whose plant is done leaves the clock
                self.subscribe_events("plant_events", self._on_event(robot), topics)
        logger.info(
            "%s mode; stiffness a feedback law may render: K_max = 2 b / T = %.0f N/m",
            cfg.run.mode,
            max_stable_stiffness_n_per_m(cfg.haptic, cfg.haptic.render_period_s),
        )
        self.announce()

    # -- callbacks: straight into the loop, with the robot they came from ---------------
    def _on_state(self, robot: int) -> RecordCallback:
        def on_state(rec: np.ndarray, rx_ns: int) -> None:
            self.loop.on_state(rec, robot)

        return on_state

    def _on_feedback(self, robot: int) -> RecordCallback:
        def on_feedback(rec: np.ndarray, rx_ns: int) -> None:
            self.loop.on_feedback(rec, rx_ns, robot)

        return on_feedback

    def _on_hand(self, robot: int) -> RecordCallback:
        def on_hand(rec: np.ndarray, rx_ns: int) -> None:
            self.loop.on_hand(rec, robot)

        return on_hand

    def _on_event(self, robot: int) -> RecordCallback:
        def on_event(rec: np.ndarray, rx_ns: int) -> None:
            if int(rec["event"]) in (Event.FINISHED, Event.ABORTED):
                self.loop.on_finished(robot)

        return on_event

    # -- HapticOutputs -----------------------------------------------------------------
    def sample(self, rec: np.ndarray, robot: int) -> None:
        self.state_batches[robot].add(self.state_pubs[robot].put(rec))

    def resend(self, rec: np.ndarray, robot: int) -> None:
        self.state_pubs[robot].put(rec)

    # -- lifecycle ---------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        if self.lockstep:
            self.loop.run_lockstep(stop)
        else:
            self.loop.run_realtime(stop)
        logger.info("stopped: %s", self.summary())

    def close(self) -> None:
        device = getattr(self, "device", None)  # None if open() failed before building it
        if device is not None:
            device.disconnect()
        loop = getattr(self, "loop", None)
        run_dir = self.options.run_dir
        if run_dir is not None and loop is not None:
            with loop.cond:
                loop.trace_log.save(run_dir / HAPTIC_TRACE_FILE)
                loop.sample_log.save(run_dir / HAPTIC_SAMPLES_FILE)
                loop.feedback_in.save(shed_path(run_dir, self.name))
        super().close()

    def summary(self) -> dict[str, Any]:
        return {**super().summary(), "mode": self.config.run.mode, **self.loop.summary()}


if __name__ == "__main__":
    sys.exit(service_main(HapticService))
