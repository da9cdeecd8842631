"""One robot's end of an operator, scripted (services/operator.py) or a person's
(:mod:`teleop.devices.person.service`): its hand stream and its task events, published on
that robot's keys."""

from __future__ import annotations

import time

import numpy as np

from teleop.bus.messages import (
    HAND_INPUT,
    RUN_EVENT,
    Button,
    Event,
    next_hand_input,
    next_run_event,
)
from teleop.bus.service import Service
from teleop.bus.topics import Topics
from teleop.devices.scripted.operator import HandCommand


class RobotOutputs:
    """One robot's end of an operator, scripted or a person's: its hand stream and its
    task events, on that robot's keys (ScriptedOutputs, and PersonOutputs of
    teleop.devices.person.loop)."""

    def __init__(self, service: Service, topics: Topics, timestep_ns: int) -> None:
        assert service.session is not None
        self.timestep_ns = timestep_ns
        self.hand_pub = service.publish_stream("hand_input", topics)
        self.events_pub = service.publish_stream("operator_events", topics)
        self._hand = HAND_INPUT.new()  # each stream's seq counts its own records
        self._event = RUN_EVENT.new()

    def hand(self, valid_from_tick: int, command: HandCommand) -> None:
        self.put_hand(valid_from_tick, command.target_p_m, command.buttons)

    def put_hand(self, valid_from_tick: int, target_p_m: np.ndarray, buttons: Button) -> None:
        rec = next_hand_input(self._hand, time.monotonic_ns(), valid_from_tick, target_p_m, buttons)
        self.hand_pub.put(rec)

    def event(self, event: Event, tick: int, step: int, value: float) -> None:
        now_ns = time.monotonic_ns()
        rec = next_run_event(self._event, event, now_ns, tick * self.timestep_ns, step, value)
        self.events_pub.put(rec)
