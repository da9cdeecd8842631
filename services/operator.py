"""The operator service: :class:`teleop.devices.scripted.loop.ScriptedLoop` on the bus.

Inputs: TOOL_POSE and OBJECT_POSES (plant, every ``1 / scene_rate_hz``, stamped with
``sim_time_ns``; tick = sim_time_ns / timestep), HEAD_POSE (hmd, keyed by the tick its
predicted yaw applies from), RUN_EVENT STARTED and the liveliness tokens of the HMD and
the haptic device. Outputs: HAND_INPUT (to the haptic device) and RUN_EVENT PHASE /
TASK_DONE. In a run of several robots (``run.robots``) each of these comes from, and
goes to, every robot's keys: a loop per robot, the hand driving one at a time
(:class:`teleop.devices.scripted.loop.ScriptedStation`).

The Zenoh callbacks only store samples in the loop's observation buffer and queue the
tool-pose ticks; one run thread hands them to the station in arrival order, so decisions
follow sim time only (see ScriptedLoop for which decisions an arrival triggers).
"""

from __future__ import annotations

import logging
import queue
import sys
import threading
import time
from typing import Any

import numpy as np
import zenoh

from teleop.bus.messages import (
    Event,
    Flag,
)
from teleop.bus.service import STOP_POLL_S, Service, service_main
from teleop.bus.session import RecordCallback
from teleop.core.clock import NS_PER_S
from teleop.core.ring import Ring
from teleop.devices.robot_outputs import RobotOutputs
from teleop.devices.scripted.loop import (
    Arrival,
    PoseArrival,
    RunStarted,
    ScriptedLoop,
    ScriptedStation,
)
from teleop.devices.scripted.operator import ObservationBuffer
from teleop.devices.scripted.scenario import Scenario

logger = logging.getLogger(__name__)

HMD_SERVICE = "hmd"  # liveliness name of the HMD service
DEVICE_SERVICE = "haptic"  # liveliness name of the operator's device

# How many pose-to-decision delays the summary's percentiles take (the newest ones).
LATENESS_SAMPLES = 1 << 15


class ScriptedOperatorService(Service):
    """The scripted operator: an :class:`ScriptedLoop` per robot of the run (one, or one
    task per robot in turn: :class:`ScriptedStation`), each robot's streams into its
    loop, its decisions out on that robot's keys."""

    name = "operator"

    def open(self) -> None:
        super().open()
        assert self.session is not None
        cfg = self.config
        self.timestep_ns = round(cfg.tick_s * NS_PER_S)
        self.scenario = Scenario.load(cfg.operator.scenario_path, cfg.robot.object_bodies)
        lockstep = cfg.run.mode == "lockstep"
        self.station = ScriptedStation(
            [
                ScriptedLoop(
                    cfg,
                    self.scenario,
                    RobotOutputs(self, topics, self.timestep_ns),
                    lockstep=lockstep,
                )
                for topics in self.robot_topics
            ]
        )
        loops = self.station.loops
        # Tool poses and new runs, in arrival order, for the run thread.
        self._arrivals: queue.SimpleQueue[Arrival] = queue.SimpleQueue()
        # From a pose's sample on the plant to this operator's decisions on it (ns): how
        # late the hand is on top of its reaction delay (realtime; a starved operator).
        self._lateness_ns = Ring(LATENESS_SAMPLES)
        for robot, topics in enumerate(self.robot_topics):
            buffer = loops[robot].buffer
            self.subscribe_stream("tool_pose", self._on_tool(robot), topics)
            self.subscribe_stream("objects", self._on_objects(buffer), topics)
            self.subscribe_stream("head_pose", self._on_head(loops[robot]), topics)
            self.subscribe_events("plant_events", self._on_event(robot), topics)
        self.keep(
            self.session.liveliness().declare_subscriber(
                self.topics.alive(HMD_SERVICE), self._on_hmd_token, history=True
            )
        )
        self.keep(
            self.session.liveliness().declare_subscriber(
                self.topics.alive(DEVICE_SERVICE), self._on_device_token, history=True
            )
        )
        self.announce()

    # -- callbacks (Zenoh threads): store and hand over, nothing else ----------------------
    def _tick_of(self, rec: np.ndarray) -> int:
        return round(int(rec["sim_time_ns"]) / self.timestep_ns)

    def _on_tool(self, robot: int) -> RecordCallback:
        buffer = self.station.loops[robot].buffer

        def on_tool(rec: np.ndarray, rx_ns: int) -> None:
            tick = self._tick_of(rec)
            braked = bool(int(rec["flags"]) & Flag.BRAKING)
            buffer.add_tool(tick, rec["world_p_tool_m"], braked)
            self._arrivals.put(PoseArrival(robot, tick, int(rec["t_source_ns"])))

        return on_tool

    def _on_objects(self, buffer: ObservationBuffer) -> RecordCallback:
        def on_objects(rec: np.ndarray, rx_ns: int) -> None:
            n = int(rec["n_objects"])
            buffer.add_objects(self._tick_of(rec), rec["world_p_m"][:n])

        return on_objects

    def _on_head(self, loop: ScriptedLoop) -> RecordCallback:
        def on_head(rec: np.ndarray, rx_ns: int) -> None:
            loop.hmd_seen()
            loop.buffer.add_head(int(rec["valid_from_tick"]), float(rec["predicted_yaw_rad"]))

        return on_head

    def _on_event(self, robot: int) -> RecordCallback:
        def on_event(rec: np.ndarray, rx_ns: int) -> None:
            if int(rec["event"]) == Event.STARTED:
                self._arrivals.put(RunStarted(robot))

        return on_event

    def _on_hmd_token(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            for loop in self.station.loops:
                loop.hmd_seen()

    def _on_device_token(self, sample: zenoh.Sample) -> None:
        """The device's token: withdrawn while it is dead or restarting (the hand then
        moves nothing; ScriptedOperator.device_gone), back once it is up again."""
        gone = sample.kind == zenoh.SampleKind.DELETE
        if gone != self.station.loops[0].operator.device_gone:
            logger.warning("the haptic device %s", "is gone" if gone else "is back")
        for loop in self.station.loops:
            loop.operator.device_gone = gone

    # -- the run thread --------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        """Hand arrivals to the station in batches, in order, until stopped (what a batch
        decides: ScriptedStation.take)."""
        while not stop.is_set():
            try:
                items = [self._arrivals.get(timeout=STOP_POLL_S)]
            except queue.Empty:
                continue
            while True:
                try:
                    items.append(self._arrivals.get_nowait())
                except queue.Empty:
                    break
            self.station.take(items, self._decided)

    def _decided(self, sampled_ns: int) -> None:
        self._lateness_ns.append(time.monotonic_ns() - sampled_ns)

    def summary(self) -> dict[str, Any]:
        late: dict[str, Any] = {}
        if len(self._lateness_ns):
            p50, p99 = self._lateness_ns.percentiles([50, 99])
            late = {"p50": round(p50 / 1e6, 3), "p99": round(p99 / 1e6, 3),
                    "max": round(self._lateness_ns.max() / 1e6, 3)}  # fmt: skip
        tasks = self.station.summary([topics.robot_id for topics in self.robot_topics])
        return {**super().summary(), **tasks, "pose_to_decision_ms": late}


if __name__ == "__main__":
    sys.exit(service_main(ScriptedOperatorService))
