"""The bus adapter of a person's operator: :class:`teleop.devices.person.loop.PersonLoop`
on the bus, the device left to a subclass (the services of services/keyboard.py,
services/input_device.py and services/web.py).

It takes the operator's place in the stack (participant ``operator``: its credentials,
tokens and rights), so the haptic device, controller and plant run as with the scripted
operator. Inputs: RUN_EVENT from the plant (STARTED, GRASP, RELEASE, FINISHED, ABORTED),
TOOL_POSE and OBJECT_POSES (the world the person sees), the controller's batched
FORCE_FEEDBACK (the force felt, for a device that cannot render it). Outputs: HAND_INPUT
and RUN_EVENT PHASE / TASK_DONE.

Threads: Zenoh's callbacks hand records to the loop under one lock; a pacer thread sends
the hand inputs when the loop says they are due (event driven: it sleeps until then); the
device's own loop (:meth:`PersonOperatorService.interact`) runs in the main thread and
reads the person's input through :meth:`intent`.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import numpy as np

from teleop.bus.messages import (
    FORCE_FEEDBACK,
    Button,
    Event,
)
from teleop.bus.service import Service
from teleop.bus.session import RecordCallback, subscribe
from teleop.core.clock import NS_PER_S
from teleop.core.ring import Ring
from teleop.devices.person.intent import HandIntent
from teleop.devices.person.loop import PersonLoop, PersonStation
from teleop.devices.robot_outputs import RobotOutputs
from teleop.devices.scripted.routing import SceneKnowledge

logger = logging.getLogger(__name__)

# How many key-to-input delays the summary's percentiles take (the newest ones).
LATENCY_SAMPLES = 1 << 14


class PersonOperatorService(Service):
    """The operator's place in the stack, driven by a person's device."""

    name = "operator"
    device = "human"  # the device's name, for the summary and messages

    def open(self) -> None:
        super().open()
        assert self.session is not None
        cfg = self.config
        self.timestep_ns = round(cfg.tick_s * NS_PER_S)
        self._force_scale = cfg.teleop.force_scale
        self.lock = threading.Lock()
        scene = SceneKnowledge.from_config(cfg)
        lockstep = cfg.run.mode == "lockstep"
        # One task loop per robot, its outputs on that robot's keys; the station says
        # which robot the hand drives (teleop.devices.person.loop.PersonStation).
        loops = []
        for topics in self.robot_topics:
            outputs = RobotOutputs(self, topics, self.timestep_ns)
            loops.append(PersonLoop(cfg, outputs, scene, lockstep=lockstep))
        self.station = PersonStation(loops)
        self.run_over = threading.Event()  # every robot's plant finished or aborted its run
        self._finished: set[int] = set()
        self._wake = threading.Event()  # the pacer: a run started, or the input changed
        # From a device input (a key press) to the first hand input that carries it (ns).
        self._input_latency_ns = Ring(LATENCY_SAMPLES)
        self._pending_input_ns: int | None = None
        for robot, topics in enumerate(self.robot_topics):
            self.subscribe_stream("tool_pose", self._on_tool(robot), topics)
            self.subscribe_stream("objects", self._on_objects(robot), topics)
            self.subscribe_events("plant_events", self._on_event(robot), topics)
            self.keep(
                subscribe(self.session, topics.force_feedback_batch, FORCE_FEEDBACK,
                          self._on_feedback(robot), self.drops, batched=True)
            )  # fmt: skip
        self.announce()

    @property
    def loop(self) -> PersonLoop:
        """The driven robot's task loop (its view is what the device shows)."""
        return self.station.loop

    @property
    def robot_id(self) -> str:
        """The id of the robot the hand drives."""
        return self.robot_topics[self.station.active].robot_id

    # -- callbacks (Zenoh threads) -------------------------------------------------------
    def _tick_of(self, rec: np.ndarray) -> int:
        return round(int(rec["sim_time_ns"]) / self.timestep_ns)

    def _on_tool(self, robot: int) -> RecordCallback:
        loop = self.station.loops[robot]

        def on_tool(rec: np.ndarray, rx_ns: int) -> None:
            with self.lock:
                loop.on_tool(self._tick_of(rec), rec["world_p_tool_m"], rx_ns)
            self._wake.set()  # lockstep: the run moved on, inputs held back may go

        return on_tool

    def _on_objects(self, robot: int) -> RecordCallback:
        loop = self.station.loops[robot]

        def on_objects(rec: np.ndarray, rx_ns: int) -> None:
            n = int(rec["n_objects"])
            with self.lock:
                loop.on_objects(self._tick_of(rec), list(rec["world_p_m"][:n]))

        return on_objects

    def _on_feedback(self, robot: int) -> RecordCallback:
        loop = self.station.loops[robot]

        def on_feedback(rec: np.ndarray, rx_ns: int) -> None:
            weight_f_n = self._force_scale * rec["world_f_weight_n"]  # as the handle renders it
            with self.lock:
                loop.on_force(rec["device_f_n"], weight_f_n)

        return on_feedback

    def _on_event(self, robot: int) -> RecordCallback:
        loop = self.station.loops[robot]

        def on_event(rec: np.ndarray, rx_ns: int) -> None:
            event = int(rec["event"])
            with self.lock:
                if event == Event.STARTED:
                    self._finished.discard(robot)
                    self.run_over.clear()
                    loop.on_started(time.monotonic_ns())
                elif event in (Event.GRASP, Event.RELEASE):
                    loop.on_hold(event == Event.GRASP, self._tick_of(rec))
                elif event in (Event.FINISHED, Event.ABORTED):
                    self._finished.add(robot)
                    if len(self._finished) == len(self.station.loops):
                        self.run_over.set()
            self._wake.set()

        return on_event

    # -- the person's device -------------------------------------------------------------
    def intent(self, now_ns: int) -> HandIntent:
        """What the person asks of the hand now (the subclass reads its device)."""
        raise NotImplementedError

    def interact(self, stop: threading.Event) -> None:
        """The device's own loop, in the main thread, until ``stop``."""
        raise NotImplementedError

    def input_changed(self, at_ns: int) -> None:
        """The device read an input at ``at_ns`` (monotonic): the pacer sends it at the
        next input due, and times the wait."""
        if self._pending_input_ns is None:
            self._pending_input_ns = at_ns
        self._wake.set()

    def end_task(self) -> None:
        """The person ends the run: TASK_DONE of every robot's task, not a success."""
        with self.lock:
            self.station.end_task()

    def switch_robot(self) -> bool:
        """The device's robot switch: the hand drives the next robot whose task is not
        done, the device taking up its gripper (:meth:`take_robot`). False: no other
        robot to drive."""
        with self.lock:
            if not self.station.switch():
                return False
            self.take_robot(self.station.loop.last_buttons)
        self._wake.set()
        return True

    def take_robot(self, buttons: Button) -> None:
        """The hand came to another robot (the switch, or the move-on after a task): the
        device stops its motion and takes up ``buttons``, the gripper and clutch as the
        hand last left that robot. Called with :attr:`lock` held; the device's subclass
        says how."""

    # -- threads -------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        pacer = threading.Thread(target=self._pace, args=(stop,), name="hand-pacer", daemon=True)
        pacer.start()
        try:
            self.interact(stop)
        finally:
            stop.set()
            self._wake.set()
            pacer.join(timeout=2.0)

    def _pace(self, stop: threading.Event) -> None:
        """Send each hand input when the loop says it is due; sleep until the next."""
        while not stop.is_set():
            # Cleared before the loop looks, so a wake-up set while it works is kept.
            self._wake.clear()
            now_ns = time.monotonic_ns()
            with self.lock:
                if self.station.move_on():  # the driven robot's task is done
                    self.take_robot(self.station.loop.last_buttons)
                sent_before = self.station.inputs_sent
                next_ns = self.station.due(now_ns, self.intent(now_ns))
                sent = self.station.inputs_sent > sent_before
            if sent and self._pending_input_ns is not None:
                self._time_input(now_ns - self._pending_input_ns)
                self._pending_input_ns = None
            self._wake.wait(max(0.0, (next_ns - time.monotonic_ns()) / NS_PER_S))

    def _time_input(self, latency_ns: int) -> None:
        self._input_latency_ns.append(latency_ns)

    def summary(self) -> dict[str, Any]:
        with self.lock:
            task = self.station.summary([t.robot_id for t in self.robot_topics])
        timed = self._input_latency_ns
        latency: dict[str, Any] = {"inputs": timed.count}
        if len(timed):
            p50, p99 = timed.percentiles([50, 99])
            latency.update(p50=round(p50 / 1e6, 3), p99=round(p99 / 1e6, 3),
                           max=round(timed.max() / 1e6, 3))  # fmt: skip
        return {
            **super().summary(),
            **task,
            "device": self.device,
            "input_to_hand_ms": latency,
        }
