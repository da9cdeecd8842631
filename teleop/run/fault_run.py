"""The bus side of fault injection in a services run (:mod:`teleop.run.faults` decides
what to inject and when, and reports what followed): the plant's states recorded and fed
to the injector, ready tokens watched for restarts, the run failed when a killed plant
starts the world over, and the summary's ``faults``."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import zenoh

from teleop.bus.messages import PLANT_STATE, DropCounter
from teleop.bus.session import subscribe
from teleop.bus.topics import Topics
from teleop.control.kinematics import build_arm_model, tool_jacobian
from teleop.core.clock import NS_PER_S
from teleop.core.config import Config
from teleop.core.summary import FaultOutcome
from teleop.run.failure import ProgramWatch, RunError
from teleop.run.faults import (
    FaultInjector,
    FaultSpec,
    InjectorHooks,
    StateLog,
    fault_report,
    resumed_index,
    stage_stamps,
    world_reset,
)
from teleop.run.supervise import Stack


def _no_holds(at_s: float) -> None:
    """A realtime run's release: its plant keeps time and is never held."""


class FaultRun:
    """The bus side of fault injection in a run (teleop.run.faults): the plant's states
    recorded and fed to the injector, ready tokens watched for restarts, the run failed
    when a killed plant starts the world over, and the summary's ``faults``."""

    def __init__(self, config: Config, specs: Sequence[FaultSpec]) -> None:
        self.specs = specs
        self.realtime = config.run.mode == "realtime"
        self.arm = build_arm_model(config.robot)  # tool speed from joint state
        self.states = StateLog(self.arm.n_joints)
        self.injector: FaultInjector | None = None
        # What the bus told before start() made the injector, handed to it there: the
        # plant's STARTED stamp and its newest state (sim ns, step). A lockstep plant
        # may already hold at a fault's instant, sending no state until released.
        self._handover = threading.Lock()
        self._started_ns = 0
        self._newest: tuple[int, int] | None = None
        self._session: zenoh.Session | None = None  # the launcher's, for release tokens
        self._topics: Topics | None = None
        self._released: list[zenoh.LivelinessToken] = []

    @property
    def hold_at_s(self) -> tuple[float, ...]:
        """The sim instants at which a lockstep plant waits for this run's releases (the
        faults' instants); none in realtime, where sim time keeps wall-clock time."""
        return () if self.realtime else tuple(spec.at_s for spec in self.specs)

    def subscribe(self, session: zenoh.Session, topics: Topics, drops: DropCounter) -> list[Any]:
        """The plant's states (the observers' batched copy) and every ready token."""
        self._session, self._topics = session, topics

        def on_state(rec: np.ndarray, rx_ns: int) -> None:
            self.states.add(rec)
            with self._handover:
                self._newest = int(rec["sim_time_ns"]), int(rec["step"])
                if self.injector is not None:
                    self.injector.on_state(*self._newest)

        def on_token(sample: zenoh.Sample) -> None:
            if sample.kind != zenoh.SampleKind.PUT:
                return
            name, now_ns = topics.service_of(str(sample.key_expr)), time.monotonic_ns()
            if self.injector is not None:
                self.injector.on_ready(name, now_ns)

        states = subscribe(
            session, topics.plant_state_batch, PLANT_STATE, on_state, drops, batched=True
        )
        tokens = session.liveliness().declare_subscriber(topics.ready_all, on_token)
        return [states, tokens]

    def start(
        self, stack: Stack, watch: ProgramWatch, check: Callable[[], None]
    ) -> Callable[[], None]:
        """Start injecting into ``stack``; the run's check, extended by the plant's."""
        hooks = InjectorHooks(
            pid_of=stack.pid,
            signal_group=os.killpg,
            expect_restart=watch.expect_restart,
            now_ns=time.monotonic_ns,
            release=self._release if not self.realtime else _no_holds,
        )
        injector = FaultInjector(self.specs, hooks, realtime=self.realtime)
        with self._handover:
            if self._started_ns:
                injector.on_started(self._started_ns)
            if self._newest is not None:
                injector.on_state(*self._newest)
            self.injector = injector
        injector.start()

        def checked() -> None:
            check()
            self.check_world()

        return checked

    def check_world(self) -> None:
        """Raise RunError when a killed plant came back with the run started over."""
        assert self.injector is not None
        arrays = self.states.arrays()
        for record in self.injector.records:
            if record.inject_ns and world_reset(record, arrays):
                raise RunError(
                    f"the plant was killed at sim {record.t_s:.3f} s (step {record.step}) "
                    "and its new incarnation started the run over from step 0: the world "
                    "was reset, so the run cannot go on (the plant did not resume from a "
                    "checkpoint)"
                )

    def on_started(self, t_ns: int) -> None:
        """The plant's STARTED event (stamped ``t_ns``): realtime faults are due from it."""
        with self._handover:
            self._started_ns = self._started_ns or t_ns
            if self.injector is not None:
                self.injector.on_started(t_ns)

    def _release(self, at_s: float) -> None:
        """Declare the token that lets the lockstep plant held at sim ``at_s`` step on
        (graph.RELEASED_TOKEN); kept until the run ends, so a restarted plant finds it."""
        assert self._session is not None and self._topics is not None
        key = self._topics.released(round(at_s * NS_PER_S))
        self._released.append(self._session.liveliness().declare_token(key))

    def close(self) -> None:
        if self.injector is not None:
            self.injector.close()
        for token in self._released:
            token.undeclare()
        self._released.clear()

    def _speed_at(self, arrays: dict[str, np.ndarray]) -> Callable[[int], float]:
        def speed_at(i: int) -> float:
            jacobian = tool_jacobian(self.arm, arrays["q_rad"][i])
            return float(np.linalg.norm(jacobian[:3] @ arrays["qd_rad_s"][i]))

        return speed_at

    def report(self, success: bool | None) -> list[FaultOutcome]:
        """The summary's ``faults``: one record per fault (teleop.run.faults)."""
        if self.injector is None:
            return [FaultOutcome(s.service, s.kind, success=success, error="not injected")
                    for s in self.specs]  # fmt: skip
        arrays = self.states.arrays()
        speed_at = self._speed_at(arrays)
        return [fault_report(r, arrays, speed_at, success) for r in self.injector.records]

    def _windows(self) -> list[tuple[int, int]]:
        """Per injected fault, (injected, resumed or the record's end), host ns."""
        if self.injector is None:
            return []
        arrays = self.states.arrays()
        end_ns = int(arrays["t_ns"][-1]) if len(arrays["t_ns"]) else 0
        windows = []
        for record in self.injector.records:
            if not record.inject_ns:
                continue
            stamps = stage_stamps(arrays, record.spec.service)
            resumed = None
            if record.back_ns:
                resumed = resumed_index(arrays["t_ns"], stamps, arrays["braking"], record.back_ns)
            stop_ns = int(arrays["t_ns"][resumed]) if resumed is not None else end_ns
            windows.append((record.inject_ns, stop_ns))
        return windows

    def braked_states(self) -> int:
        """Plant states braked between an injection and the resumption it caused."""
        arrays = self.states.arrays()
        t_ns, braking = arrays["t_ns"], arrays["braking"]
        inside = np.zeros(len(t_ns), bool)
        for start_ns, stop_ns in self._windows():
            inside |= (t_ns >= start_ns) & (t_ns <= stop_ns)
        return int(np.count_nonzero(inside & braking))

    def brakes(self) -> int:
        """Brakes (runs of braked states) that began inside a fault's window."""
        arrays = self.states.arrays()
        t_ns, braking = arrays["t_ns"], arrays["braking"]
        onsets = np.flatnonzero(braking & ~np.concatenate(([False], braking[:-1])))
        return sum(1 for i in onsets if any(a <= t_ns[i] <= b for a, b in self._windows()))
