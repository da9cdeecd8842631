"""The operator service: the scripted operator (:mod:`teleop.devices.operator`) on the bus.

Inputs: TOOL_POSE and OBJECT_POSES (plant, every ``1 / scene_rate_hz``, stamped with
``sim_time_ns``; tick = sim_time_ns / timestep), HEAD_POSE (hmd, keyed by the tick its
predicted yaw applies from) and RUN_EVENT STARTED. Outputs: HAND_INPUT (to the haptic
device) and RUN_EVENT PHASE / TASK_DONE.

Decisions run on sim time, never on the wall clock. A TOOL_POSE arriving at tick ``m``
triggers one decision for every sample tick ``s`` of the operator's clock
(:func:`teleop.core.ticks.is_sample_tick` at ``decision_rate_hz``) in ``(previous arrival, m]``,
published with ``valid_from_tick = s + lead_ticks`` (``lead_ticks = 1 / (rate timestep)``):
exactly the records the haptic service waits for. At the default rates (scene and
decisions both 100 Hz) that is one decision per arrival with ``s = m``. A slower decision
rate decides on the arrivals that fall on or after each sample tick; a decision rate above
the scene rate would need a record before the TOOL_POSE that triggers it exists, which
deadlocks lockstep, so it is a config error.

Lockstep determinism: a decision uses only tick-stamped samples, the newest at or before
``s - reaction_delay`` (:class:`ObservationBuffer`). Before deciding, the service waits
(event driven) until that observation is complete: the OBJECT_POSES of the observed tool
tick, and, when an HMD is in the run (its liveliness token is up, or a HEAD_POSE arrived),
the HEAD_POSE whose ``valid_from_tick`` applies at the observed tick
(:func:`teleop.core.ticks.expected_valid_from` with the HMD's rate and lead). Without an HMD
the view yaw is ``hmd.head_yaw_rad``.

A new run (TOOL_POSE at tick 0, or the plant's STARTED event) resets the operator.
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

from teleop.bus.messages import HAND_INPUT, HEAD_POSE, OBJECT_POSES, RUN_EVENT, TOOL_POSE, Event
from teleop.bus.service import STOP_POLL_S, Service, service_main
from teleop.bus.session import Publisher, subscribe
from teleop.core.clock import NS_PER_S
from teleop.core.config import ConfigError
from teleop.core.ticks import expected_valid_from, is_sample_tick, last_sample_tick
from teleop.devices.operator import HandCommand, ObservationBuffer, Scenario, ScriptedOperator

logger = logging.getLogger(__name__)

# TASK_DONE names a tick this far ahead of the arrival that ends the task: the plant
# (in lockstep, waiting at that arrival's tick at most) finishes the run there exactly.
TASK_DONE_AHEAD_TICKS = 100
# Lockstep: longest wait for an observation's samples before deciding with what is there (s).
LOCKSTEP_INPUT_WAIT_S = 1.0
HMD_SERVICE = "hmd"  # liveliness name of the HMD service

_NEW_RUN = "new_run"  # queue item: the plant's STARTED event


class OperatorService(Service):
    name = "operator"

    def open(self) -> None:
        super().open()
        assert self.session is not None
        cfg = self.config
        self.timestep_s = cfg.plant.timestep_s
        self.timestep_ns = round(self.timestep_s * NS_PER_S)
        self.lockstep = cfg.run.mode == "lockstep"
        self.rate_hz = cfg.operator.decision_rate_hz
        if self.rate_hz > cfg.plant.scene_rate_hz:
            raise ConfigError(
                f"operator.decision_rate_hz ({self.rate_hz:g}) above plant.scene_rate_hz "
                f"({cfg.plant.scene_rate_hz:g}): decisions are driven by TOOL_POSE arrivals"
            )
        self.lead_ticks = round(1.0 / (self.rate_hz * self.timestep_s))
        self.delay_ticks = round(cfg.operator.reaction_delay_s / self.timestep_s)
        self.hmd_lead_ticks = round(cfg.hmd.prediction_s / self.timestep_s)
        self.scenario = Scenario.load(cfg.operator.scenario_path, cfg.robot.object_bodies)
        self.operator = ScriptedOperator(
            self.scenario, cfg.operator, cfg.teleop, cfg.haptic, self.timestep_s
        )
        self.buffer = ObservationBuffer(
            cfg.robot.object_bodies, self.delay_ticks, cfg.hmd.head_yaw_rad
        )
        self.hand_pub = self.keep(
            Publisher.declare(self.session, self.topics.hand_input, HAND_INPUT)
        )
        self.events_pub = self.keep(Publisher.declare(self.session, self.topics.events, RUN_EVENT))
        self._hand = HAND_INPUT.new()
        self._event = RUN_EVENT.new()
        # Tool-pose ticks and new-run markers, in arrival order, for the run thread.
        self._arrivals: queue.SimpleQueue[int | str] = queue.SimpleQueue()
        self._hmd_present = threading.Event()
        self._last_tick: int | None = None  # newest TOOL_POSE tick handled in this run
        self._phase_reported = -1
        self._done_reported = False
        self.runs = 0
        self.decisions = 0
        self.late_observations = 0  # lockstep waits that timed out
        self.duplicate_poses = 0  # TOOL_POSE re-sends (same tick) ignored
        self.phase_times: list[dict[str, Any]] = []
        topics, drops = self.topics, self.drops
        self.keep(subscribe(self.session, topics.tool_pose, TOOL_POSE, self._on_tool, drops))
        self.keep(subscribe(self.session, topics.objects, OBJECT_POSES, self._on_objects, drops))
        self.keep(subscribe(self.session, topics.head_pose, HEAD_POSE, self._on_head, drops))
        self.keep(subscribe(self.session, topics.events, RUN_EVENT, self._on_event, drops))
        self.keep(
            self.session.liveliness().declare_subscriber(
                topics.alive(HMD_SERVICE), self._on_hmd_token, history=True
            )
        )
        self.announce()

    # -- callbacks (Zenoh threads): store and hand over, nothing else ----------------------
    def _tick_of(self, rec: np.ndarray) -> int:
        return round(int(rec["sim_time_ns"]) / self.timestep_ns)

    def _on_tool(self, rec: np.ndarray, rx_ns: int) -> None:
        tick = self._tick_of(rec)
        self.buffer.add_tool(tick, rec["world_p_tool_m"])
        self._arrivals.put(tick)

    def _on_objects(self, rec: np.ndarray, rx_ns: int) -> None:
        self.buffer.add_objects(self._tick_of(rec), rec["world_p_m"][: int(rec["n_objects"])])

    def _on_head(self, rec: np.ndarray, rx_ns: int) -> None:
        self._hmd_present.set()
        self.buffer.add_head(int(rec["valid_from_tick"]), float(rec["predicted_yaw_rad"]))

    def _on_event(self, rec: np.ndarray, rx_ns: int) -> None:
        if int(rec["event"]) == Event.STARTED:
            self._arrivals.put(_NEW_RUN)

    def _on_hmd_token(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self._hmd_present.set()

    # -- the run thread --------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        """Handle arrivals in order until stopped (decisions follow sim time only)."""
        while not stop.is_set():
            try:
                item = self._arrivals.get(timeout=STOP_POLL_S)
            except queue.Empty:
                continue
            if item == _NEW_RUN:
                if self._last_tick not in (None, 0):  # 0: this run's first pose came first
                    self._new_run()
            else:
                assert isinstance(item, int)
                self._on_arrival(item)

    def _new_run(self) -> None:
        self.operator.reset()
        self._last_tick = None
        self._phase_reported = -1
        self._done_reported = False
        self.phase_times = []
        self.runs += 1
        logger.info("new run: operator reset")

    def _on_arrival(self, m: int) -> None:
        if m == 0 and self._last_tick != 0:
            self._new_run()
        elif self._last_tick is not None and m <= self._last_tick:
            self.duplicate_poses += 1  # a plant re-send of a state nobody answered yet
            return
        if self._last_tick is None:
            first = last_sample_tick(m, self.rate_hz, self.timestep_s)
        else:
            first = self._last_tick + 1
        self._last_tick = m
        for s in range(first, m + 1):
            if is_sample_tick(s, self.rate_hz, self.timestep_s):
                self._decide(s, m)

    def _decide(self, s: int, m: int) -> None:
        """One decision at sample tick ``s`` (triggered by the TOOL_POSE of tick ``m``)."""
        if self.lockstep:
            seen = s - self.delay_ticks
            head_from = None
            if self._hmd_present.is_set() and seen >= 0:
                head_from = expected_valid_from(
                    seen, self.config.hmd.rate_hz, self.timestep_s, self.hmd_lead_ticks
                )
            if not self.buffer.wait_ready(s, head_from, LOCKSTEP_INPUT_WAIT_S):
                self.late_observations += 1
        command = self.operator.decide(s, self.buffer.observe(s))
        self.decisions += 1
        self._publish_hand(s + self.lead_ticks, command)
        if command.phase != self._phase_reported and command.phase >= 0:
            self._phase_reported = command.phase
            self.phase_times.append(
                {
                    "phase": command.phase,
                    "name": self.scenario.phases[command.phase].name,
                    "sim_time_s": s * self.timestep_s,
                }
            )
            self._publish_event(Event.PHASE, s, s, float(command.phase))
        if command.done and not self._done_reported:
            self._done_reported = True
            finish_tick = m + TASK_DONE_AHEAD_TICKS
            self._publish_event(Event.TASK_DONE, s, finish_tick, float(command.success))
            logger.info(
                "task done at %.2f s: %s %s",
                s * self.timestep_s,
                "success" if command.success else "gave up",
                self.operator.failure,
            )

    def _publish_hand(self, valid_from_tick: int, command: HandCommand) -> None:
        rec = self._hand
        rec["seq"] += 1
        rec["t_source_ns"] = time.monotonic_ns()
        rec["valid_from_tick"] = valid_from_tick
        rec["target_p_m"] = command.target_p_m
        rec["buttons"] = int(command.buttons)
        self.hand_pub.put(rec)

    def _publish_event(self, event: Event, tick: int, step: int, value: float) -> None:
        """RUN_EVENT decided at ``tick``; ``step`` is the tick it names (see Event)."""
        rec = self._event
        rec["seq"] += 1
        rec["t_source_ns"] = time.monotonic_ns()
        rec["sim_time_ns"] = tick * self.timestep_ns
        rec["step"] = step
        rec["event"] = event
        rec["value"] = value
        self.events_pub.put(rec)

    def summary(self) -> dict[str, Any]:
        op = self.operator
        duration_s = None
        if op.task_start_tick is not None and op.done_tick is not None:
            duration_s = (op.done_tick - op.task_start_tick) * self.timestep_s
        return {
            **super().summary(),
            "scenario": self.scenario.source,
            "phases": self.phase_times,
            "task_done": op.done,
            "success": op.success if op.done else None,
            "failure": op.failure,
            "task_duration_s": duration_s,
            "gain_per_s": op.gain_per_s,
            "decisions": self.decisions,
            "late_observations": self.late_observations,
            "duplicate_poses": self.duplicate_poses,
            "runs": self.runs,
        }


def main() -> int:
    return service_main(OperatorService)


if __name__ == "__main__":
    sys.exit(main())
