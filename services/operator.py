"""The operator service: :class:`teleop.devices.operator.OperatorLoop` on the bus.

Inputs: TOOL_POSE and OBJECT_POSES (plant, every ``1 / scene_rate_hz``, stamped with
``sim_time_ns``; tick = sim_time_ns / timestep), HEAD_POSE (hmd, keyed by the tick its
predicted yaw applies from), RUN_EVENT STARTED and the liveliness tokens of the HMD and
the haptic device. Outputs: HAND_INPUT (to the haptic device) and RUN_EVENT PHASE /
TASK_DONE.

The Zenoh callbacks only store samples in the loop's observation buffer and queue the
tool-pose ticks; one run thread hands them to the loop in arrival order, so decisions
follow sim time only (see OperatorLoop for which decisions an arrival triggers).
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
    HAND_INPUT,
    RUN_EVENT,
    Event,
    Flag,
    next_hand_input,
    next_run_event,
)
from teleop.bus.service import STOP_POLL_S, Service, service_main
from teleop.bus.session import Publisher, subscribe_events
from teleop.core.clock import NS_PER_S
from teleop.devices.operator import HandCommand, OperatorLoop, Scenario

logger = logging.getLogger(__name__)

HMD_SERVICE = "hmd"  # liveliness name of the HMD service
DEVICE_SERVICE = "haptic"  # liveliness name of the operator's device

_NEW_RUN = "new_run"  # queue item: the plant's STARTED event
# How many pose-to-decision delays the summary's percentiles take (the newest ones).
LATENESS_SAMPLES = 1 << 15


class OperatorService(Service):
    name = "operator"

    def open(self) -> None:
        super().open()
        assert self.session is not None
        cfg = self.config
        self.timestep_ns = round(cfg.plant.timestep_s * NS_PER_S)
        self.scenario = Scenario.load(cfg.operator.scenario_path, cfg.robot.object_bodies)
        self.loop = OperatorLoop(cfg, self.scenario, self, lockstep=cfg.run.mode == "lockstep")
        self.hand_pub = self.keep(Publisher.for_stream(self.session, self.topics, "hand_input"))
        self.events_pub = self.keep(
            Publisher.for_stream(self.session, self.topics, "operator_events")
        )
        self._hand = HAND_INPUT.new()
        self._event = RUN_EVENT.new()
        # Tool poses (tick, the plant's sample stamp) and new-run markers, in arrival
        # order, for the run thread.
        self._arrivals: queue.SimpleQueue[tuple[int, int] | str] = queue.SimpleQueue()
        # From a pose's sample on the plant to this operator's decisions on it (ns): how
        # late the hand is on top of its reaction delay (realtime; a starved operator).
        self._lateness_ns = np.zeros(LATENESS_SAMPLES, dtype=np.int64)
        self._poses_decided = 0
        topics, drops = self.topics, self.drops
        self.subscribe_stream("tool_pose", self._on_tool)
        self.subscribe_stream("objects", self._on_objects)
        self.subscribe_stream("head_pose", self._on_head)
        self.keep(subscribe_events(self.session, topics, "plant_events", self._on_event, drops))
        self.keep(
            self.session.liveliness().declare_subscriber(
                topics.alive(HMD_SERVICE), self._on_hmd_token, history=True
            )
        )
        self.keep(
            self.session.liveliness().declare_subscriber(
                topics.alive(DEVICE_SERVICE), self._on_device_token, history=True
            )
        )
        self.announce()

    # -- callbacks (Zenoh threads): store and hand over, nothing else ----------------------
    def _tick_of(self, rec: np.ndarray) -> int:
        return round(int(rec["sim_time_ns"]) / self.timestep_ns)

    def _on_tool(self, rec: np.ndarray, rx_ns: int) -> None:
        tick = self._tick_of(rec)
        braked = bool(int(rec["flags"]) & Flag.BRAKING)
        self.loop.buffer.add_tool(tick, rec["world_p_tool_m"], braked)
        self._arrivals.put((tick, int(rec["t_source_ns"])))

    def _on_objects(self, rec: np.ndarray, rx_ns: int) -> None:
        n = int(rec["n_objects"])
        self.loop.buffer.add_objects(self._tick_of(rec), rec["world_p_m"][:n])

    def _on_head(self, rec: np.ndarray, rx_ns: int) -> None:
        self.loop.hmd_seen()
        self.loop.buffer.add_head(int(rec["valid_from_tick"]), float(rec["predicted_yaw_rad"]))

    def _on_event(self, rec: np.ndarray, rx_ns: int) -> None:
        if int(rec["event"]) == Event.STARTED:
            self._arrivals.put(_NEW_RUN)

    def _on_hmd_token(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self.loop.hmd_seen()

    def _on_device_token(self, sample: zenoh.Sample) -> None:
        """The device's token: withdrawn while it is dead or restarting (the hand then
        moves nothing; ScriptedOperator.device_gone), back once it is up again."""
        gone = sample.kind == zenoh.SampleKind.DELETE
        if gone != self.loop.operator.device_gone:
            logger.warning("the haptic device %s", "is gone" if gone else "is back")
        self.loop.operator.device_gone = gone

    # -- the run thread --------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        """Hand arrivals to the loop in order until stopped. A late operator (realtime:
        poses queued behind a newer one; lockstep: a run that went on without it,
        OperatorLoop.left_behind) decides on the newest pose only and skips the rest: it
        catches up by skipping, never by a burst of late hand inputs. Lockstep otherwise
        decides every one (the haptic device waits for each)."""
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
            poses = [item for item in items if isinstance(item, tuple)]
            newest_tick = poses[-1][0] if poses else -1
            behind = bool(poses) and self.loop.left_behind(newest_tick)
            catch_up = behind and (len(poses) > 1 or self.loop.lockstep)
            for i, item in enumerate(items):
                if item == _NEW_RUN:
                    self.loop.on_started()
                    continue
                assert isinstance(item, tuple)
                if behind and any(isinstance(later, tuple) for later in items[i + 1 :]):
                    continue  # a newer pose is queued behind it
                tick, sampled_ns = item
                self._lateness_ns[self._poses_decided % LATENESS_SAMPLES] = (
                    time.monotonic_ns() - sampled_ns
                )
                self._poses_decided += 1
                self.loop.on_arrival(tick, catch_up=catch_up)

    # -- OperatorOutputs: the loop's decisions onto the bus --------------------------------
    def hand(self, valid_from_tick: int, command: HandCommand) -> None:
        rec = next_hand_input(self._hand, time.monotonic_ns(), valid_from_tick,
                              command.target_p_m, command.buttons)  # fmt: skip
        self.hand_pub.put(rec)

    def event(self, event: Event, tick: int, step: int, value: float) -> None:
        now_ns = time.monotonic_ns()
        rec = next_run_event(self._event, event, now_ns, tick * self.timestep_ns, step, value)
        self.events_pub.put(rec)

    def summary(self) -> dict[str, Any]:
        lateness_ms = self._lateness_ns[: min(self._poses_decided, LATENESS_SAMPLES)] / 1e6
        late: dict[str, Any] = {}
        if len(lateness_ms):
            p50, p99 = np.percentile(lateness_ms, [50, 99])
            late = {"p50": round(p50, 3), "p99": round(p99, 3), "max": round(lateness_ms.max(), 3)}
        return {**super().summary(), **self.loop.summary(), "pose_to_decision_ms": late}


if __name__ == "__main__":
    sys.exit(service_main(OperatorService))
