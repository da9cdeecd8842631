"""The plant service: :class:`teleop.sim.plant_loop.PlantLoop` on the bus.

Input: JOINT_COMMAND (from the controller, or any client that speaks docs/protocol.md),
and the operator's RUN_EVENTs (its TASK_DONE names the tick at which the run ends). Outputs:
PLANT_STATE every step (and its batched copy for observers), TOOL_POSE and OBJECT_POSES
at the scene rate, RUN_EVENT on start, finish, grasp, release and watchdog changes. The
stepping and watchdog (teleop.sim.stepping) and the pacing (teleop.sim.pacing) are in
PlantLoop; this module wires them to Zenoh.
"""

from __future__ import annotations

import logging
import sys
import threading
from typing import Any

import numpy as np
import zenoh

from teleop.bus.messages import (
    JOINT_COMMAND,
    DecodeError,
    Event,
    Kind,
    Reason,
)
from teleop.bus.service import Service, service_main
from teleop.bus.session import BatchPublisher, subscribe
from teleop.core.clock import MonotonicClock
from teleop.core.rundir import checkpoint_path, shed_path
from teleop.sim.checkpoint import CheckpointStore
from teleop.sim.plant_loop import PlantLoop

logger = logging.getLogger(__name__)


class PlantService(Service):
    name = "plant"
    _bad_release_logged = False

    def open(self) -> None:
        super().open()
        assert self.session is not None
        session, topics = self.session, self.topics
        self.publishers = {
            name: self.publish_stream(name)
            for name in ("plant_state", "tool_pose", "objects", "plant_events")
        }
        self.state_batch = self.keep(  # the observers' copy, several states per message
            BatchPublisher.for_stream(
                session, topics, "plant_state_batch", self.config.bus.observer_batch_records
            )
        )
        store = None
        if self.options.run_dir is not None:  # checkpoints, and a restart resumes from them
            store = CheckpointStore(checkpoint_path(self.options.run_dir, self.instance))
        holds_ns = self.options.hold_at_ns
        self.loop = PlantLoop(self.config, self, MonotonicClock(), store, holds_ns)
        if holds_ns:  # the launcher's releases, those declared before this start included
            self.keep(
                session.liveliness().declare_subscriber(
                    topics.released_all, self._on_released, history=True
                )
            )
        self.subscribe_events("operator_events", self._on_event)
        self.keep(
            subscribe(session, topics.joint_command, JOINT_COMMAND, self._on_command, self.drops)
        )
        self.announce()

    # -- callbacks -----------------------------------------------------------------------
    def _on_event(self, rec: np.ndarray, rx_ns: int) -> None:
        if int(rec["event"]) == Event.TASK_DONE:
            self.loop.on_task_done(int(rec["step"]))

    def _on_released(self, sample: zenoh.Sample) -> None:
        """A release token (graph.RELEASED_TOKEN) appeared: the holds up to its instant
        are released. Its withdrawal (the launcher's end) releases nothing."""
        if sample.kind != zenoh.SampleKind.PUT:
            return
        at_ns = self.topics.released_ns_of(str(sample.key_expr))
        if at_ns is None:
            if not self._bad_release_logged:  # logged once: a peer may declare many
                logger.warning("ignored a release token with no sim instant: %s", sample.key_expr)
                self._bad_release_logged = True
            return
        self.loop.release(at_ns)

    def _on_command(self, rec: np.ndarray, rx_ns: int) -> None:
        """Accept commands for exactly this arm; anything else is counted and dropped."""
        n_joints = self.loop.core.plant.n_joints
        if int(rec["n_joints"]) != n_joints:
            detail = f"n_joints={int(rec['n_joints'])}, arm has {n_joints}"
            self.drops.record(DecodeError(Kind.JOINT_COMMAND, Reason.COUNT, detail))
            return
        self.loop.on_command(rec, rx_ns)

    # -- PlantOutputs --------------------------------------------------------------------
    def put(self, stream: str, rec: np.ndarray) -> bytes:
        data = self.publishers[stream].put(rec)
        if stream == "plant_state":
            self.state_batch.add(data)
        return data

    def put_bytes(self, stream: str, data: bytes) -> None:
        self.publishers[stream].put_bytes(data)

    def flush(self) -> None:
        self.state_batch.flush()

    # -- lifecycle -----------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        if not self.wait_for_peers(stop):
            return
        steps = None
        if not self.options.continuous:
            steps = round(self.config.run.duration_s / self.config.tick_s)
        self.loop.run(stop, steps)
        core = self.loop.core
        if core.finished or core.aborted:
            ended = "finished" if core.finished else "aborted"
            logger.info("run %s: %s", ended, self.summary())
            # The run's end on file as well as on the bus: the runner ends the run on
            # either, so a FINISHED event lost on a starved machine cannot hang it.
            self.write_summary()
            stop.wait()  # hold (no stepping) until stopped: supervisord must not restart us

    def on_strangers(self, zids: list[str]) -> None:
        self.loop.core.publish_event(Event.UNKNOWN_PEER, float(len(self.unknown_peers)))

    def close(self) -> None:
        loop = getattr(self, "loop", None)  # None if open() failed before building it
        if self.options.run_dir is not None and loop is not None:
            loop.save_shed_log(shed_path(self.options.run_dir, self.instance))
        super().close()

    def summary(self) -> dict[str, Any]:
        return {**super().summary(), **self.loop.summary()}


if __name__ == "__main__":
    sys.exit(service_main(PlantService))
