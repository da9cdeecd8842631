"""What the launcher hears of a services run (``teleop run``): each robot's plant
finishing, the task's phases (the progress lines), the operator's TASK_DONE per robot and
the newest tool pose (the run's sim time). Its own subscriptions and tokens on the
launcher's session; the summary's assembly reads what it heard
(:mod:`teleop.run.assemble`)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh

from teleop.bus.access import LAUNCHER
from teleop.bus.messages import DropCounter, Event
from teleop.bus.session import (
    Latest,
    declare_alive,
    declare_protocol,
    subscribe_events,
    subscribe_stream,
)
from teleop.bus.topics import Topics
from teleop.core.config import SCRIPTED, Config
from teleop.devices.person.loop import PHASES as PERSON_PHASES
from teleop.devices.scripted.scenario import Scenario
from teleop.run.progress import RunProgress


def task_phases(config: Config) -> tuple[str, ...]:
    """The phases the progress lines name: a person's task's (read from the world), the
    scripted operator's scenario's, or none (an autonomous run)."""
    if not config.run.teleoperated:
        return ()
    if config.run.operator != SCRIPTED:
        return PERSON_PHASES  # teleop.devices.person.loop
    scenario = Scenario.load(config.operator.scenario_path, config.robot.object_bodies)
    return tuple(phase.name for phase in scenario.phases)


class RunWatch:
    """The run's events as they come (Zenoh's threads): :attr:`finished` once every
    robot's plant finished or aborted, :attr:`task_done` the operator's TASK_DONE values
    per robot (1: success), :attr:`tool` the newest tool pose of any robot, :attr:`tracker`
    the progress; records the launcher drops counted in :attr:`drops`. ``on_started``:
    called with the plant's STARTED stamp (the fault injector's clock)."""

    def __init__(self, config: Config, on_started: Callable[[int], None] | None = None) -> None:
        self.config = config
        self.robot_ids = config.robot_ids()
        self.robots = [Topics(rid) for rid in self.robot_ids]
        self.drops = DropCounter()
        self.finished = threading.Event()
        self.task_done: dict[str, list[float]] = {rid: [] for rid in self.robot_ids}
        self.tool = Latest()
        self.tracker = RunProgress(config.run.duration_s, task_phases(config))
        self._on_started = on_started
        self._finished_robots: set[str] = set()

    def _events_of(self, robot_id: str) -> Callable[[np.ndarray, int], None]:
        def on_event(rec: np.ndarray, rx_ns: int) -> None:
            event = int(rec["event"])
            if event == Event.STARTED and self._on_started is not None:
                self._on_started(int(rec["t_source_ns"]))
            if event in (Event.FINISHED, Event.ABORTED):
                self._finished_robots.add(robot_id)
                if len(self._finished_robots) == len(self.robot_ids):
                    self.finished.set()
            elif event == Event.PHASE:
                self.tracker.on_phase(int(rec["value"]), int(rec["sim_time_ns"]) * 1e-9)
            elif event == Event.TASK_DONE:
                self.task_done[robot_id].append(float(rec["value"]))

        return on_event

    def listen(self, session: zenoh.Session) -> list[Any]:
        """Subscribe to every robot's events and tool pose, and declare the launcher's
        protocol, alive and ready tokens under each robot's keys; what to undeclare."""
        run = self.config.run
        entities: list[Any] = []
        for robot in self.robots:
            on_event = self._events_of(robot.robot_id)
            entities.append(subscribe_events(session, robot, "plant_events", on_event, self.drops))
            if run.teleoperated:  # the operator's TASK_DONE (success or not)
                entities.append(
                    subscribe_events(session, robot, "operator_events", on_event, self.drops)
                )
            entities.append(
                subscribe_stream(session, robot, "tool_pose", self.tool, self.drops,
                                 consumer=LAUNCHER, mode=run.mode, scenario=run.scenario)
            )  # fmt: skip
            entities.append(declare_protocol(session, robot))
            entities.append(declare_alive(session, robot, LAUNCHER))
            entities.append(declare_alive(session, robot, LAUNCHER, ready=True))
        return entities

    def sim_s(self) -> float | None:
        """The run's sim time by the newest tool pose (None before the first)."""
        latest = self.tool.get()
        return None if latest is None else int(latest[0]["sim_time_ns"]) * 1e-9
