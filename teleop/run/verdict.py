"""What a services run says about the machine it ran on and about its own real time.

Pure functions of the services' summaries (their typed records,
teleop.core.service_summaries), so a unit test checks them without a stack:

- :func:`machine_section`: which realtime privileges the run asked for and which the
  kernel granted (SCHED_FIFO, CPU pinning, the idle CPU cgroup of the pollers, shared
  memory within the locked-memory limit): a run as an ordinary user degrades, and the
  summary says where.
- :func:`realtime_health`: whether a realtime run kept real time (loop overruns,
  watchdog brakes, realtime factor), judged against fixed bounds, so a run on a starved
  machine is flagged instead of reported as a clean success; and whether any of its
  data is missing (bad records dropped, services that never linked).
"""

from __future__ import annotations

import getpass
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from teleop.bus import graph
from teleop.bus.messages import PROTOCOL_VERSION, Reason
from teleop.core.service_summaries import Drops, EyeViewSummary, ServiceSummary
from teleop.run.idle_poll import IdlePoll

# Service.privileges outcomes start with one of these (teleop.bus.service).
GRANTED = "granted"
NOT_REQUESTED = "not requested"

# A run's verdict (realtime_health): "clean" when it kept real time and lost no data,
# "degraded" when it lost some real time but stayed within the bounds below, or some of
# its data is missing (a warning, exit code 0), "lost" when its loop went past one of
# the bounds (exit code teleop.cli.EXIT_REALTIME_LOST).
CLEAN, DEGRADED, LOST = "clean", "degraded", "lost"
# Fraction of the plant's deadlines (one per bus period) missed (ticks skipped after a
# stall): degraded above the first, lost above the second.
OVERRUN_DEGRADED = 0.001
OVERRUN_LOST = 0.02
# Simulated time per wall-clock second: degraded below the first, lost below the second.
REALTIME_FACTOR_DEGRADED = 0.99
REALTIME_FACTOR_LOST = 0.95
# Fraction of the plant's steps braked by the watchdog (a command that answered a state
# older than plant.watchdog_s: the loop lost its peer): degraded above 0, lost above this.
BRAKED_STEPS_LOST = 0.02


@dataclass(frozen=True)
class Privilege:
    """One privilege over the services that asked for it: the outcome of each service it
    was ``granted`` to, and why for each it was ``refused`` to."""

    granted: Mapping[str, str]
    refused: Mapping[str, str]

    @classmethod
    def of(cls, records: Mapping[str, ServiceSummary], key: str) -> Privilege:
        """Privilege ``key`` (a Service.privileges key) over the services' ``records``."""
        granted: dict[str, str] = {}
        refused: dict[str, str] = {}
        for name, record in records.items():
            outcome = (record.privileges or {}).get(key, NOT_REQUESTED)
            if outcome == NOT_REQUESTED:
                continue
            if outcome.startswith(GRANTED):
                granted[name] = outcome
            else:
                refused[name] = outcome
        return cls(granted, refused)

    def to_json(self) -> dict[str, dict[str, str]]:
        return {"granted": dict(self.granted), "refused": dict(self.refused)}


@dataclass(frozen=True)
class Machine:
    """The summary's ``machine`` section: who ran, and each privilege granted or refused
    (the idle CPU cgroup's by CPU, the eye view's shared memory pool as it reported it)."""

    user: str
    uid: int
    cpus: int
    sched_fifo: Privilege
    cpu_pinning: Privilege
    idle_requested_cpus: tuple[int, ...]
    idle_granted_cpus: tuple[int, ...]
    idle_refused: Mapping[str, str]  # CPU (as a JSON key) -> why it was not polled
    shm: Mapping[str, object] | None

    def to_json(self) -> dict[str, object]:
        return {
            "user": self.user,
            "uid": self.uid,
            "cpus": self.cpus,
            "sched_fifo": self.sched_fifo.to_json(),
            "cpu_pinning": self.cpu_pinning.to_json(),
            "idle_cgroup": {
                "requested_cpus": list(self.idle_requested_cpus),
                "granted": list(self.idle_granted_cpus),
                "refused": dict(self.idle_refused),
            },
            "shm": self.shm,
        }


def machine_section(
    records: Mapping[str, ServiceSummary], polled_cpus: Sequence[int], idle_poll: IdlePoll
) -> Machine:
    """The summary's ``machine`` section.

    ``records``: the services' summaries by name (their ``privileges`` and the eye view's
    ``shm_pool``); ``polled_cpus``: the CPUs the run asked to keep polling;
    ``idle_poll``: :func:`teleop.run.assemble.idle_poll_report` of them.
    """
    eyeview = records.get("eyeview")
    return Machine(
        user=getpass.getuser(),
        uid=os.getuid(),
        cpus=len(os.sched_getaffinity(0)),
        sched_fifo=Privilege.of(records, "sched_fifo"),
        cpu_pinning=Privilege.of(records, "cpu_pinning"),
        idle_requested_cpus=tuple(polled_cpus),
        idle_granted_cpus=idle_poll.cpus,
        idle_refused={str(cpu): why for cpu, why in idle_poll.failed.items()},
        shm=eyeview.shm_pool if isinstance(eyeview, EyeViewSummary) else None,
    )


def refused_privileges(machine: Machine) -> list[str]:
    """One line per privilege the run asked for and did not get (empty: all granted)."""
    lines = []
    for privilege, label in (
        (machine.sched_fifo, "SCHED_FIFO"),
        (machine.cpu_pinning, "CPU pinning"),
    ):
        if privilege.refused:
            why = next(iter(privilege.refused.values()))
            lines.append(f"{label} refused for {', '.join(privilege.refused)} ({why})")
    if machine.idle_refused:
        why = next(iter(machine.idle_refused.values()))
        cpus = ", ".join(machine.idle_refused)
        lines.append(f"idle CPU polling refused on CPU(s) {cpus} ({why})")
    if machine.shm and machine.shm.get("reason"):
        lines.append(f"shared memory: {machine.shm['reason']}")
    return lines


def senders_of(kind_name: str, receiver: str) -> tuple[str, ...]:
    """The services whose streams of record kind ``kind_name`` (a ``Kind`` name)
    ``receiver`` (a service, or ``launcher``) takes (teleop.bus.graph); empty if none."""
    role = graph.role_of(receiver)
    found: list[str] = []
    for stream in graph.STREAMS:
        if stream.schema.kind.name == kind_name and role in stream.consumers:
            found += [p for p in stream.producers if p not in found]
    return tuple(found)


def drop_lines(dropped: Mapping[str, Drops]) -> list[str]:
    """One line per receiver, record kind and reason of the bad records a run dropped,
    naming the sender and, for another protocol version, both versions. ``dropped``:
    receiver -> its drops (:meth:`DropCounter.by_key`: a service summary's
    ``dropped_by_reason`` and ``dropped_first``)."""
    lines = []
    for receiver, drops in dropped.items():
        first = drops.first
        for key, count in drops.counts.items():
            kind_name, _, reason = key.partition(":")
            senders = senders_of(kind_name, receiver)
            source = f" from {' or '.join(senders)}" if senders else ""
            detail = str(first.get(key) or "")
            if reason == Reason.VERSION:
                theirs = detail.split(",")[0] or "another"
                why = f"protocol version {theirs}, this stack speaks {PROTOCOL_VERSION}"
            else:
                why = reason + (f" ({detail})" if detail else "")
            lines.append(f"{receiver} dropped {count} {kind_name} record(s){source}: {why}")
    return lines


@dataclass(frozen=True)
class Health:
    """A run's real-time verdict (CLEAN, DEGRADED or LOST) and one line per bound missed."""

    verdict: str
    problems: tuple[str, ...]

    def to_json(self) -> dict[str, object]:
        """The summary's ``realtime_verdict`` and ``realtime_problems``."""
        return {"realtime_verdict": self.verdict, "realtime_problems": list(self.problems)}


def realtime_health(
    mode: str,
    *,
    overrun_fraction: float,
    realtime_factor: float,
    watchdog_brakes: int,
    braked_steps: int,
    steps: int,
    drops: Sequence[str],
    unlinked_peers: Mapping[str, Sequence[str]],
) -> Health:
    """Judge whether a run kept real time (the bounds above) and got all of its data.

    Bad records dropped (``drops``: a line each, :func:`drop_lines`) and services that
    never linked (``unlinked_peers``: service -> the peers it never saw; what they would
    have sent each other is missing) make a run DEGRADED, never LOST: the loop's timing
    is judged by the plant's own figures, which a missing peer (say the recorder) does
    not touch, and a peer the loop itself needs
    shows there (a plant without its controller brakes). A lockstep run has no real time
    to keep: only the missing data counts."""
    lost: list[str] = []
    degraded: list[str] = []
    if mode == "realtime":
        overruns = (
            f"the plant's loop overran {overrun_fraction:.2%} of its deadlines (one per bus period)"
        )
        if overrun_fraction > OVERRUN_LOST:
            lost.append(f"{overruns} (bound {OVERRUN_LOST:.0%})")
        elif overrun_fraction > OVERRUN_DEGRADED:
            degraded.append(overruns)
        pace = f"simulated time ran at {realtime_factor:.3f} x real time"
        if realtime_factor < REALTIME_FACTOR_LOST:
            lost.append(f"{pace} (bound {REALTIME_FACTOR_LOST:g})")
        elif realtime_factor < REALTIME_FACTOR_DEGRADED:
            degraded.append(pace)
        braked_fraction = braked_steps / steps if steps else 0.0
        brakes = (
            f"the watchdog braked {watchdog_brakes} time(s), {braked_steps} steps "
            f"({braked_fraction:.2%}): commands arrived too late"
        )
        if braked_fraction > BRAKED_STEPS_LOST:
            lost.append(f"{brakes} (bound {BRAKED_STEPS_LOST:.0%})")
        elif watchdog_brakes:
            degraded.append(brakes)
    degraded += drops
    if unlinked_peers:
        pairs = "; ".join(
            f"{name} never saw {', '.join(map(str, peers))}"
            for name, peers in unlinked_peers.items()
        )
        degraded.append(
            f"services never linked ({pairs}): what they would have sent each other is "
            "missing from the run"
        )
    verdict = LOST if lost else DEGRADED if degraded else CLEAN
    return Health(verdict=verdict, problems=tuple(lost + degraded))
