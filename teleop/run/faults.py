"""Fault injection: ``teleop run SCENARIO --kill SERVICE@T --freeze SERVICE@T:SECONDS``.

A fault is injected into a service of the run when the plant's simulation time reaches
``T`` seconds (read from the plant's state stream): a kill is SIGKILL to the service's
process group (supervisord restarts it, the failure watch expects that one restart), a
freeze is SIGSTOP, then SIGCONT ``SECONDS`` of wall-clock time later. What followed is
measured from the plant's state stream, on the host's monotonic clock (every process of a
run stamps with it), from the instant of injection:

- ``brake_ms``: until the tool moves slower than :data:`BRAKE_SPEED_M_S` (the plant's
  watchdog holds the arm when commands stop); 0 when it was already still, None when it
  did not get that slow before the service was back, and for a service off the command
  path (the HMD, operator, recorder, eye view: the arm is not theirs to stop).
- ``restart_s``: a kill: until the new incarnation's ready token (it sees every peer);
  None for a freeze, or if it never came.
- ``resumed_s``: until the first state whose applied command was made after the service
  was back (ready again, or thawed), through it: for the haptic device a command made
  from one of its new samples, for the controller and the plant a command the
  controller sent after that instant; services off the command path (HMD, operator,
  recorder, eye view) resume when they are back.

This module holds the parsing (pure), the measurements (pure functions of recorded
arrays) and :class:`FaultInjector`, the thread that injects on time through injected
callables (the launcher passes the stack's signal and the bus's view).
"""

from __future__ import annotations

import difflib
import logging
import math
import os
import re
import signal
import threading
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from teleop.bus.messages import Flag, Stage
from teleop.core.config import ConfigError
from teleop.core.summary import FaultOutcome

logger = logging.getLogger(__name__)

KILL = "kill"
FREEZE = "freeze"
# The tool counts as braked (held still) below this speed (m/s): 1 mm/s.
BRAKE_SPEED_M_S = 1.0e-3
# The stage stamp of a plant state that shows a command made through the faulted
# service after it came back; services not listed are off the command path.
RESUME_STAGE = {
    "haptic": Stage.HAPTIC_SAMPLE,
    "controller": Stage.CONTROLLER_TX,
    "plant": Stage.CONTROLLER_TX,
}
# How close a misspelt service name must be to a real one to be suggested (difflib, 0-1).
SUGGESTION_CUTOFF = 0.5
# Longest freeze accepted (s): longer is a stopped service, not a freeze.
MAX_FREEZE_S = 3600.0
# How often the injector looks at the clock while a thaw is due (s; not a control loop).
THAW_POLL_S = 0.005
# How often the injector asks again for the pid of the next fault's service while that
# service is not running yet (s): it must know it before the fault is due, as a lockstep
# run races ahead while the supervisor answers.
PID_RETRY_S = 0.2
NS_PER_S = 1_000_000_000
NS_PER_MS = 1_000_000

_NUMBER = r"[0-9]+(?:\.[0-9]*)?|\.[0-9]+"
_KILL_RE = re.compile(rf"(?P<service>[^@\s]+)@(?P<at>{_NUMBER})")
_FREEZE_RE = re.compile(rf"(?P<service>[^@\s]+)@(?P<at>{_NUMBER}):(?P<seconds>{_NUMBER})")


class FaultSpecError(ConfigError):
    """A --kill or --freeze argument that cannot be used; the message says why."""


@dataclass(frozen=True)
class FaultSpec:
    """One fault to inject: ``kind`` (kill or freeze) into ``service`` once the plant's
    sim time reaches ``at_s``; a freeze lasts ``freeze_s`` seconds of wall-clock time."""

    service: str
    kind: str
    at_s: float
    freeze_s: float = 0.0

    def text(self) -> str:
        """The argument that asks for it, e.g. ``--freeze controller@5:1``."""
        tail = f":{self.freeze_s:g}" if self.kind == FREEZE else ""
        return f"--{self.kind} {self.service}@{self.at_s:g}{tail}"


def parse_fault(text: str, kind: str, services: Sequence[str]) -> FaultSpec:
    """One ``--kill SERVICE@T`` or ``--freeze SERVICE@T:SECONDS`` argument; ``services``:
    those the stack runs (a fault needs a process of the stack to go to)."""
    pattern, syntax = (
        (_KILL_RE, "SERVICE@T (T: sim seconds, e.g. controller@5)")
        if kind == KILL
        else (_FREEZE_RE, "SERVICE@T:SECONDS (e.g. controller@5:1)")
    )
    match = pattern.fullmatch(text.strip())
    if match is None:
        raise FaultSpecError(f"--{kind} {text!r}: expected {syntax}")
    service = match["service"]
    if service not in services:
        close = difflib.get_close_matches(service, services, n=1, cutoff=SUGGESTION_CUTOFF)
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise FaultSpecError(
            f"--{kind} {text!r}: no service {service!r} in this stack{hint}; "
            f"it runs {', '.join(services)}"
        )
    at_s = float(match["at"])
    freeze_s = float(match["seconds"]) if kind == FREEZE else 0.0
    if kind == FREEZE and not 0.0 < freeze_s <= MAX_FREEZE_S:
        raise FaultSpecError(
            f"--{kind} {text!r}: the freeze must last more than 0 and at most "
            f"{MAX_FREEZE_S:g} s, not {freeze_s:g}"
        )
    return FaultSpec(service, kind, at_s, freeze_s)


def parse_faults(
    kills: Iterable[str],
    freezes: Iterable[str],
    services: Sequence[str],
    duration_s: float,
) -> list[FaultSpec]:
    """Every --kill and --freeze of a run, in the order they are due; a fault due after
    the run's end (``duration_s`` of sim time) is refused."""
    faults = [parse_fault(text, KILL, services) for text in kills]
    faults += [parse_fault(text, FREEZE, services) for text in freezes]
    for fault in faults:
        if fault.at_s >= duration_s:
            raise FaultSpecError(
                f"{fault.text()}: due at {fault.at_s:g} s, but the run ends at "
                f"{duration_s:g} s of sim time (--duration)"
            )
    return sorted(faults, key=lambda f: f.at_s)


# -- what happened, measured from the state stream -----------------------------------------


@dataclass
class FaultRecord:
    """One fault as injected: when (host monotonic ns, and the plant's sim time), and when
    the service was back (``back_ns``: its new incarnation ready, or thawed; 0: not yet)."""

    spec: FaultSpec
    t_s: float = math.nan  # sim time of the newest plant state at the injection
    step: int = -1  # its plant step
    pid: int = 0  # the process (group) signalled
    inject_ns: int = 0
    ready_ns: int = 0  # kill: the new incarnation's ready token
    thaw_ns: int = 0  # freeze: SIGCONT
    error: str = ""  # the injection failed (e.g. the service was not running)

    @property
    def back_ns(self) -> int:
        return self.ready_ns if self.spec.kind == KILL else self.thaw_ns


class StateLog:
    """The plant states of a run, the fields the fault measurements need, in arrays that
    grow by doubling. ``add`` is called from the bus callback, the reads after the run
    (or under the caller's lock)."""

    def __init__(self, n_joints: int, capacity: int = 4096) -> None:
        self.n_joints = n_joints
        self.size = 0
        self._lock = threading.Lock()
        self._arrays = self._allocate(capacity)

    def _allocate(self, capacity: int) -> dict[str, np.ndarray]:
        n = self.n_joints
        return {
            "t_ns": np.zeros(capacity, np.int64),  # the state's t_source_ns
            "sim_time_ns": np.zeros(capacity, np.int64),
            "step": np.zeros(capacity, np.int64),
            "braking": np.zeros(capacity, bool),
            "controller_tx_ns": np.zeros(capacity, np.int64),
            "haptic_sample_ns": np.zeros(capacity, np.int64),
            "q_rad": np.zeros((capacity, n)),
            "qd_rad_s": np.zeros((capacity, n)),
        }

    def add(self, rec: np.ndarray) -> None:
        """Append one PLANT_STATE record."""
        with self._lock:
            if self.size == len(self._arrays["t_ns"]):
                grown = self._allocate(2 * self.size)
                for name, array in self._arrays.items():
                    grown[name][: self.size] = array
                self._arrays = grown
            i, n, a = self.size, self.n_joints, self._arrays
            a["t_ns"][i] = rec["t_source_ns"]
            a["sim_time_ns"][i] = rec["sim_time_ns"]
            a["step"][i] = rec["step"]
            a["braking"][i] = bool(int(rec["flags"]) & Flag.BRAKING)
            trace = rec["trace_ns"]
            a["controller_tx_ns"][i] = trace[Stage.CONTROLLER_TX]
            a["haptic_sample_ns"][i] = trace[Stage.HAPTIC_SAMPLE]
            a["q_rad"][i] = rec["q_rad"][:n]
            a["qd_rad_s"][i] = rec["qd_rad_s"][:n]
            self.size += 1

    def arrays(self) -> dict[str, np.ndarray]:
        """Views of the recorded states, in arrival order."""
        with self._lock:
            return {name: array[: self.size] for name, array in self._arrays.items()}


def stage_stamps(arrays: dict[str, np.ndarray], service: str) -> np.ndarray | None:
    """The stamp that shows, per state, when the applied command went through
    ``service`` (None: the service is off the command path)."""
    stage = RESUME_STAGE.get(service)
    if stage is None:
        return None
    return arrays["haptic_sample_ns" if stage == Stage.HAPTIC_SAMPLE else "controller_tx_ns"]


def brake_index(
    t_ns: np.ndarray, speed_at: Callable[[int], float], inject_ns: int, end_ns: int
) -> int | None:
    """Index of the first state stamped at or after ``inject_ns`` (and before
    ``end_ns``) whose tool speed ``speed_at(i)`` (m/s) is below :data:`BRAKE_SPEED_M_S`;
    None if none. ``t_ns`` in arrival order, which is stamp order for one incarnation."""
    start = int(np.searchsorted(t_ns, inject_ns, side="left"))
    for i in range(start, len(t_ns)):
        if t_ns[i] >= end_ns:
            return None
        if speed_at(i) < BRAKE_SPEED_M_S:
            return i
    return None


def resumed_index(
    t_ns: np.ndarray, stamps: np.ndarray | None, braking: np.ndarray, back_ns: int
) -> int | None:
    """Index of the first state from ``back_ns`` on that applies a command made after
    ``back_ns`` through the faulted service (``stamps``: :func:`stage_stamps`; None: any
    state from then on counts) and is not braking; None if none."""
    after = t_ns >= back_ns
    if stamps is not None:
        after &= stamps >= back_ns
    hits = np.flatnonzero(after & ~braking)
    return int(hits[0]) if len(hits) else None


def fault_report(
    record: FaultRecord,
    arrays: dict[str, np.ndarray],
    speed_at: Callable[[int], float],
    success: bool | None,
    end_ns: int | None = None,
) -> FaultOutcome:
    """The summary's record of one fault: what was injected, when, and what followed
    (see the module's docstring). ``speed_at(i)``: tool speed of state ``i`` (m/s);
    ``end_ns``: the brake is looked for before this instant (default: the service back,
    or the record's end)."""
    spec = record.spec
    outcome = FaultOutcome(
        service=spec.service,
        kind=spec.kind,
        t_s=None if math.isnan(record.t_s) else round(record.t_s, 4),
        freeze_s=spec.freeze_s if spec.kind == FREEZE else None,
        success=success,
    )
    if record.error:
        return replace(outcome, error=record.error)
    t_ns = arrays["t_ns"]
    before = int(np.searchsorted(t_ns, record.inject_ns, side="right")) - 1
    if before >= 0:  # the plant's sim time at the instant of injection
        outcome = replace(outcome, t_s=round(int(arrays["sim_time_ns"][before]) / NS_PER_S, 4))
    if spec.kind == FREEZE and record.thaw_ns:
        outcome = replace(outcome, frozen_s=_seconds(record.thaw_ns - record.inject_ns))
    back_ns = record.back_ns
    if end_ns is None:
        end_ns = back_ns if back_ns else np.iinfo(np.int64).max
    on_path = spec.service in RESUME_STAGE  # off it, the arm is not the fault's to stop
    brake = brake_index(t_ns, speed_at, record.inject_ns, end_ns) if on_path else None
    if brake is not None:
        brake_ns = max(0, int(t_ns[brake]) - record.inject_ns)
        outcome = replace(outcome, brake_ms=round(brake_ns / NS_PER_MS, 2))
    if spec.kind == KILL and record.ready_ns:
        outcome = replace(outcome, restart_s=_seconds(record.ready_ns - record.inject_ns))
    if back_ns:
        stamps = stage_stamps(arrays, spec.service)
        if stamps is None:
            outcome = replace(outcome, resumed_s=_seconds(back_ns - record.inject_ns))
        else:
            resumed = resumed_index(t_ns, stamps, arrays["braking"], back_ns)
            if resumed is not None:
                resumed_ns = int(t_ns[resumed]) - record.inject_ns
                outcome = replace(outcome, resumed_s=_seconds(resumed_ns))
    return outcome


def _seconds(duration_ns: int) -> float:
    return round(duration_ns / NS_PER_S, 4)


def world_reset(record: FaultRecord, arrays: dict[str, np.ndarray]) -> bool:
    """Whether the plant's first state after ``record`` (a plant kill) starts the run over
    from step 0 (the world reset) although the kill came later in the run."""
    if record.spec.service != "plant" or record.spec.kind != KILL or record.step <= 0:
        return False
    t_ns = arrays["t_ns"]
    first = int(np.searchsorted(t_ns, record.inject_ns, side="right"))
    return first < len(t_ns) and int(arrays["step"][first]) == 0


# -- the injector ------------------------------------------------------------------------


def _group_exists(pgid: int) -> bool:
    """Whether process group ``pgid`` still has a process (signal 0 probes, sends none)."""
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@dataclass
class InjectorHooks:
    """What the injector acts through: ``pid_of(name)`` the pid of a service's process,
    the leader of its process group (looked up before the fault's instant: asking the
    supervisor takes milliseconds); ``signal_group(pid, signum)`` signals that group;
    ``expect_restart(name)`` tells the failure watch a restart follows; ``now_ns()`` the
    host's monotonic clock; ``release(at_s)``, once the faults due at sim ``at_s`` are
    injected: lets a lockstep plant held there step on (a realtime run has no holds)."""

    pid_of: Callable[[str], int]
    signal_group: Callable[[int, int], None]
    expect_restart: Callable[[str], None]
    now_ns: Callable[[], int]
    release: Callable[[float], None]


@dataclass
class FaultInjector:
    """Injects ``faults`` (sorted by ``at_s``) on time, in a thread of its own.

    The bus adapter feeds it: :meth:`on_state` with every plant state's sim time and step,
    :meth:`on_started` with the plant's STARTED stamp, :meth:`on_ready` with every ready
    token that appears. :meth:`close` thaws any service still frozen (a run that ends
    first must not leave one stopped) and ends the thread.

    ``realtime``: sim time keeps wall-clock time, so a fault is due ``at_s`` after the
    plant's start on the host's clock: on time even when this process, a normally
    scheduled one beside realtime services, gets the state stream late. Lockstep: due on
    the first state at or past ``at_s``, where the plant waits (it is told the instants,
    teleop.sim.pacing.LockstepHolds) until the injector, having injected, releases it.
    """

    faults: Sequence[FaultSpec]
    hooks: InjectorHooks
    realtime: bool = False
    records: list[FaultRecord] = field(init=False)
    _cond: threading.Condition = field(init=False, default_factory=threading.Condition)
    _sim_s: float = field(init=False, default=-math.inf)
    _step: int = field(init=False, default=-1)
    _next_due_s: float = field(init=False, default=math.inf)  # sim time of the next fault
    _started_ns: int = field(init=False, default=0)  # the plant's STARTED (realtime)
    _closed: bool = field(init=False, default=False)
    _thread: threading.Thread | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        self.records = [FaultRecord(spec) for spec in self.faults]

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="fault-injector", daemon=True)
        self._thread.start()

    def on_state(self, sim_time_ns: int, step: int) -> None:
        """A plant state was published (sim time, step): faults due now are injected."""
        with self._cond:
            self._sim_s = sim_time_ns / NS_PER_S
            self._step = step
            if not self.realtime and self._sim_s >= self._next_due_s:  # else nothing to do
                self._cond.notify_all()

    def on_started(self, t_ns: int) -> None:
        """The plant began the run at ``t_ns`` (its STARTED event's stamp; the first only:
        a restarted plant's does not move the faults)."""
        with self._cond:
            if not self._started_ns:
                self._started_ns = t_ns
                self._cond.notify_all()

    def _due(self, spec: FaultSpec) -> bool:
        if not self.realtime:
            return self._sim_s >= spec.at_s
        return bool(self._started_ns) and self.hooks.now_ns() >= self._due_ns(spec)

    def _due_ns(self, spec: FaultSpec) -> int:
        return self._started_ns + round(spec.at_s * NS_PER_S)

    def on_ready(self, service: str, t_ns: int) -> None:
        """``service``'s ready token appeared at ``t_ns``: a killed one is back, and the
        faults still to come on it take the pid of the process now running (looked up
        ahead of their instant)."""
        with self._cond:
            for record in self.records:
                if record.spec.service == service and not record.inject_ns:
                    record.pid = 0
                    self._cond.notify_all()
            for record in self.records:
                if (
                    record.spec.service == service
                    and record.spec.kind == KILL
                    and record.inject_ns
                    and not record.ready_ns
                    and t_ns > record.inject_ns
                ):
                    record.ready_ns = t_ns

    def _run(self) -> None:
        pending = list(self.records)
        thaws: list[FaultRecord] = []
        with self._cond:
            while not self._closed and (pending or thaws):
                now_ns = self.hooks.now_ns()
                for record in [r for r in thaws if self._thaw_due_ns(r) <= now_ns]:
                    thaws.remove(record)
                    self._signal(record, signal.SIGCONT)
                    record.thaw_ns = self.hooks.now_ns()
                if pending and not pending[0].pid:
                    self._prefetch_pid(pending[0])
                while pending and self._due(pending[0].spec):
                    record = pending.pop(0)
                    self._inject(record)
                    if record.spec.kind == FREEZE and record.inject_ns:
                        thaws.append(record)
                    self._unlocked(self.hooks.release, record.spec.at_s)
                self._next_due_s = pending[0].spec.at_s if pending else math.inf
                due = [self._thaw_due_ns(r) for r in thaws]
                if self.realtime and pending and self._started_ns:
                    due.append(self._due_ns(pending[0].spec))
                if pending and not pending[0].pid:  # not running yet: ask again soon
                    due.append(self.hooks.now_ns() + round(PID_RETRY_S * NS_PER_S))
                timeout_s = None
                if due:
                    timeout_s = max(0, min(due) - self.hooks.now_ns()) / NS_PER_S
                    if thaws or self.realtime:
                        timeout_s = min(THAW_POLL_S, timeout_s)
                if not self._closed:  # close() may have come while a hook ran unlocked
                    self._cond.wait(timeout_s)
            for record in thaws:  # closed while frozen
                self._signal(record, signal.SIGCONT)
                record.thaw_ns = self.hooks.now_ns()

    def _thaw_due_ns(self, record: FaultRecord) -> int:
        return record.inject_ns + round(record.spec.freeze_s * NS_PER_S)

    def _prefetch_pid(self, record: FaultRecord) -> None:
        """Look the next fault's pid up ahead of its instant, the lock released meanwhile
        (asking a supervisor that shares a starved machine can take a good part of a
        second, and the bus callbacks must not wait on it)."""
        try:
            pid = self._unlocked(self.hooks.pid_of, record.spec.service)
        except Exception:  # the stack's errors: looked up again at the instant
            pid = 0
        record.pid = pid

    def _unlocked(self, hook: Callable[[Any], Any], arg: Any) -> Any:
        """``hook(arg)`` with the lock released: the bus callbacks never wait on a call
        to the supervisor or to Zenoh (which may wait on them)."""
        self._cond.release()
        try:
            return hook(arg)
        finally:
            self._cond.acquire()

    def _inject(self, record: FaultRecord) -> None:
        spec = record.spec
        signum = signal.SIGKILL if spec.kind == KILL else signal.SIGSTOP
        record.t_s, record.step = self._sim_s, self._step
        if record.pid and not _group_exists(record.pid):
            record.pid = 0  # looked up before a restart: that process is gone
        if not record.pid:
            try:
                record.pid = self.hooks.pid_of(spec.service)
            except Exception as exc:  # the stack's errors: the service may be gone
                record.error = f"no process to signal: {exc}"
        if not record.pid and not record.error:
            record.error = "no process to signal: the service is not running"
        if record.error:
            logger.error("%s: %s", spec.text(), record.error)
            return
        if spec.kind == KILL:
            self.hooks.expect_restart(spec.service)
        record.inject_ns = self.hooks.now_ns()
        self._signal(record, signum)
        logger.warning("injected %s at sim %.3f s", spec.text(), record.t_s)

    def _signal(self, record: FaultRecord, signum: int) -> None:
        try:
            self.hooks.signal_group(record.pid, signum)
        except OSError as exc:
            record.error = record.error or f"{signal.Signals(signum).name} failed: {exc}"
            logger.error("%s: %s", record.spec.text(), record.error)

    def close(self) -> None:
        """Thaw what is frozen and end the thread; safe to call twice."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
