"""The bus adapter of a person's operator: :class:`teleop.devices.human_loop.HumanOperatorLoop`
on the bus, the device left to a subclass (services/keyboard.py).

It takes the operator's place in the stack (participant ``operator``: its credentials,
tokens and rights), so the haptic device, controller and plant run as with the scripted
operator. Inputs: RUN_EVENT from the plant (STARTED, GRASP, RELEASE, FINISHED, ABORTED),
TOOL_POSE and OBJECT_POSES (the world the person sees), the controller's batched
FORCE_FEEDBACK (the force felt, for a device that cannot render it). Outputs: HAND_INPUT
and RUN_EVENT PHASE / TASK_DONE.

Threads: Zenoh's callbacks hand records to the loop under one lock; a pacer thread sends
the hand inputs when the loop says they are due (event driven: it sleeps until then); the
device's own loop (:meth:`HumanOperatorService.interact`) runs in the main thread and
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
    HAND_INPUT,
    RUN_EVENT,
    Button,
    Event,
    next_hand_input,
    next_run_event,
)
from teleop.bus.service import Service
from teleop.bus.session import Publisher, subscribe, subscribe_events
from teleop.core.clock import NS_PER_S
from teleop.devices.human import HandIntent
from teleop.devices.human_loop import HumanOperatorLoop
from teleop.devices.routing import SceneKnowledge

logger = logging.getLogger(__name__)

# How many key-to-input delays the summary's percentiles take (the newest ones).
LATENCY_SAMPLES = 1 << 14


class HumanOperatorService(Service):
    """The operator's place in the stack, driven by a person's device."""

    name = "operator"
    device = "human"  # the device's name, for the summary and messages

    def open(self) -> None:
        super().open()
        assert self.session is not None
        cfg = self.config
        self.timestep_ns = round(cfg.plant.timestep_s * NS_PER_S)
        self._force_scale = cfg.teleop.force_scale
        self.lock = threading.Lock()
        self.loop = HumanOperatorLoop(
            cfg, self, SceneKnowledge.from_config(cfg), lockstep=cfg.run.mode == "lockstep"
        )
        self.hand_pub = self.keep(Publisher.for_stream(self.session, self.topics, "hand_input"))
        self.events_pub = self.keep(
            Publisher.for_stream(self.session, self.topics, "operator_events")
        )
        self._hand = HAND_INPUT.new()
        self._event = RUN_EVENT.new()
        self.run_over = threading.Event()  # the plant finished or aborted the run
        self._wake = threading.Event()  # the pacer: a run started, or the input changed
        # From a device input (a key press) to the first hand input that carries it (ns).
        self._input_latency_ns = np.zeros(LATENCY_SAMPLES, dtype=np.int64)
        self._inputs_timed = 0
        self._pending_input_ns: int | None = None
        self.subscribe_stream("tool_pose", self._on_tool)
        self.subscribe_stream("objects", self._on_objects)
        self.keep(subscribe_events(self.session, self.topics, "plant_events", self._on_event,
                                   self.drops))  # fmt: skip
        self.keep(
            subscribe(self.session, self.topics.force_feedback_batch, FORCE_FEEDBACK,
                      self._on_feedback, self.drops, batched=True)
        )  # fmt: skip
        self.announce()

    # -- callbacks (Zenoh threads) -------------------------------------------------------
    def _tick_of(self, rec: np.ndarray) -> int:
        return round(int(rec["sim_time_ns"]) / self.timestep_ns)

    def _on_tool(self, rec: np.ndarray, rx_ns: int) -> None:
        with self.lock:
            self.loop.on_tool(self._tick_of(rec), rec["world_p_tool_m"], rx_ns)
        self._wake.set()  # lockstep: the run moved on, inputs held back may go

    def _on_objects(self, rec: np.ndarray, rx_ns: int) -> None:
        n = int(rec["n_objects"])
        with self.lock:
            self.loop.on_objects(self._tick_of(rec), list(rec["world_p_m"][:n]))

    def _on_feedback(self, rec: np.ndarray, rx_ns: int) -> None:
        weight_f_n = self._force_scale * rec["world_f_weight_n"]  # as the handle renders it
        with self.lock:
            self.loop.on_force(rec["device_f_n"], weight_f_n)

    def _on_event(self, rec: np.ndarray, rx_ns: int) -> None:
        event = int(rec["event"])
        with self.lock:
            if event == Event.STARTED:
                self.run_over.clear()
                self.loop.on_started(time.monotonic_ns())
            elif event in (Event.GRASP, Event.RELEASE):
                self.loop.on_hold(event == Event.GRASP, self._tick_of(rec))
            elif event in (Event.FINISHED, Event.ABORTED):
                self.run_over.set()
        self._wake.set()

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
        """The person ends the run: TASK_DONE, not a success."""
        with self.lock:
            self.loop.end_task()

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
                sent_before = self.loop.inputs_sent
                next_ns = self.loop.due(now_ns, self.intent(now_ns))
                sent = self.loop.inputs_sent > sent_before
            if sent and self._pending_input_ns is not None:
                self._time_input(now_ns - self._pending_input_ns)
                self._pending_input_ns = None
            self._wake.wait(max(0.0, (next_ns - time.monotonic_ns()) / NS_PER_S))

    def _time_input(self, latency_ns: int) -> None:
        self._input_latency_ns[self._inputs_timed % LATENCY_SAMPLES] = latency_ns
        self._inputs_timed += 1

    # -- HumanOutputs: the loop's decisions onto the bus -----------------------------------
    def hand(self, valid_from_tick: int, target_p_m: np.ndarray, buttons: Button) -> None:
        now_ns = time.monotonic_ns()
        self.hand_pub.put(next_hand_input(self._hand, now_ns, valid_from_tick, target_p_m, buttons))

    def event(self, event: Event, tick: int, step: int, value: float) -> None:
        now_ns = time.monotonic_ns()
        rec = next_run_event(self._event, event, now_ns, tick * self.timestep_ns, step, value)
        self.events_pub.put(rec)

    def summary(self) -> dict[str, Any]:
        with self.lock:
            task = self.loop.summary()
        timed = self._input_latency_ns[: min(self._inputs_timed, LATENCY_SAMPLES)] / 1e6
        latency: dict[str, Any] = {"inputs": int(self._inputs_timed)}
        if len(timed):
            p50, p99 = np.percentile(timed, [50, 99])
            latency.update(p50=round(p50, 3), p99=round(p99, 3), max=round(timed.max(), 3))
        return {
            **super().summary(),
            **task,
            "device": self.device,
            "input_to_hand_ms": latency,
        }
