"""What a services run says about the machine it ran on and about its own real time.

Pure functions of the services' summaries (the dicts they write at close), so a unit
test checks them without a stack:

- :func:`machine_section`: which realtime privileges the run asked for and which the
  kernel granted (SCHED_FIFO, CPU pinning, the idle CPU cgroup of the pollers, shared
  memory within the locked-memory limit): a run as an ordinary user degrades, and the
  summary says where.
- :func:`realtime_health`: whether a realtime run kept real time (loop overruns,
  watchdog brakes, lost messages, realtime factor), judged against fixed bounds, so a
  run on a starved machine is flagged instead of reported as a clean success.
"""

from __future__ import annotations

import getpass
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

# Service.privileges outcomes start with one of these (teleop.bus.service).
GRANTED = "granted"
NOT_REQUESTED = "not requested"

# A realtime run kept real time when all of these hold (see realtime_health):
# - the plant's loop missed at most this fraction of its 1 ms deadlines (skipped
#   ticks after a stall); the 2-core target sees about 0.02 % on a quiet machine;
MAX_OVERRUN_FRACTION = 0.01
# - simulated time kept up with the wall clock within this fraction;
MIN_REALTIME_FACTOR = 0.98
# - the plant braked on a stale command at most this many times (each brake is a
#   command that answered a state older than plant.watchdog_s: the loop lost its peer);
MAX_WATCHDOG_BRAKES = 0
# - no record was dropped as bad, and no pair of services failed to link.
MAX_DROPPED_MESSAGES = 0


def _privilege(summaries: Mapping[str, Mapping[str, Any]], key: str) -> dict[str, Any]:
    """``{"granted": {service: outcome}, "refused": {service: why}}`` of one privilege,
    over the services that asked for it."""
    granted: dict[str, str] = {}
    refused: dict[str, str] = {}
    for name, summary in summaries.items():
        outcome = summary.get("privileges", {}).get(key, NOT_REQUESTED)
        if outcome == NOT_REQUESTED:
            continue
        if outcome.startswith(GRANTED):
            granted[name] = outcome
        else:
            refused[name] = outcome
    return {"granted": granted, "refused": refused}


def machine_section(
    summaries: Mapping[str, Mapping[str, Any]],
    polled_cpus: Sequence[int],
    idle_poll: Mapping[str, Any],
) -> dict[str, Any]:
    """The summary's ``machine`` section: who ran, and each privilege granted or refused.

    ``summaries``: the services' own summaries (their ``privileges`` and the eye view's
    ``shm_pool``); ``polled_cpus``: the CPUs the run asked to keep polling;
    ``idle_poll``: :func:`teleop.run.stack.idle_poll_report` of them.
    """
    eye_pool = summaries.get("eyeview", {}).get("shm_pool")
    idle_refused = {str(cpu): why for cpu, why in idle_poll.get("idle_poll_failed", {}).items()}
    return {
        "user": getpass.getuser(),
        "uid": os.getuid(),
        "cpus": len(os.sched_getaffinity(0)),
        "sched_fifo": _privilege(summaries, "sched_fifo"),
        "cpu_pinning": _privilege(summaries, "cpu_pinning"),
        "idle_cgroup": {
            "requested_cpus": list(polled_cpus),
            "granted": list(idle_poll.get("idle_poll_cpus", [])),
            "refused": idle_refused,
        },
        "shm": eye_pool,
    }


def refused_privileges(machine: Mapping[str, Any]) -> list[str]:
    """One line per privilege the run asked for and did not get (empty: all granted)."""
    lines = []
    for key, label in (("sched_fifo", "SCHED_FIFO"), ("cpu_pinning", "CPU pinning")):
        refused = machine.get(key, {}).get("refused", {})
        if refused:
            why = next(iter(refused.values()))
            lines.append(f"{label} refused for {', '.join(refused)} ({why})")
    idle = machine.get("idle_cgroup", {})
    if idle.get("refused"):
        why = next(iter(idle["refused"].values()))
        lines.append(f"idle CPU polling refused on CPU(s) {', '.join(idle['refused'])} ({why})")
    pool = machine.get("shm")
    if pool and pool.get("reason"):
        lines.append(f"shared memory: {pool['reason']}")
    return lines


@dataclass(frozen=True)
class Health:
    """A run's real-time verdict: ``ok`` and, when not, one reason per bound missed."""

    ok: bool
    problems: tuple[str, ...]

    def as_dict(self) -> dict[str, Any]:
        return {"realtime_ok": self.ok, "realtime_problems": list(self.problems)}


def realtime_health(
    mode: str,
    *,
    overrun_fraction: float,
    realtime_factor: float,
    watchdog_brakes: int,
    dropped_messages: int,
    unlinked_peers: Mapping[str, Any],
) -> Health:
    """Judge whether a run kept real time (see the bounds above). A lockstep run has no
    real time to keep: only lost messages and unlinked peers count there."""
    problems = []
    if mode == "realtime":
        if overrun_fraction > MAX_OVERRUN_FRACTION:
            problems.append(
                f"the plant's loop overran {overrun_fraction:.1%} of its deadlines "
                f"(bound {MAX_OVERRUN_FRACTION:.0%})"
            )
        if realtime_factor < MIN_REALTIME_FACTOR:
            problems.append(
                f"simulated time ran at {realtime_factor:.2f} x real time "
                f"(bound {MIN_REALTIME_FACTOR:g})"
            )
        if watchdog_brakes > MAX_WATCHDOG_BRAKES:
            problems.append(
                f"the plant braked {watchdog_brakes} time(s) on stale commands (watchdog)"
            )
    if dropped_messages > MAX_DROPPED_MESSAGES:
        problems.append(f"{dropped_messages} message(s) dropped as bad records")
    if unlinked_peers:
        problems.append(f"services never linked: {dict(unlinked_peers)}")
    return Health(ok=not problems, problems=tuple(problems))
