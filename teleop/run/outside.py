"""A service left out of the stack (``--without SERVICE``) and run from outside.

The launcher starts every other service, gives the outside one a place in the run's
peer mesh (its own loopback port to listen on, the ports of everyone else to connect
to: peers do not forward data for each other, so it needs a link to each), writes the
complete Zenoh config of that place to ``<run_dir>/outside/<service>.json5``
(:func:`write_outside_config`), tells the user what the service must do to join
(:func:`join_instructions`), and waits for its ready token (:func:`wait_for_outside`).
What a client must do is in docs/protocol.md; examples/ has two such clients.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import zenoh

from teleop.bus import graph
from teleop.bus.session import ServicesMissing, session_config, wait_alive
from teleop.bus.topics import Topics
from teleop.core.config import BusConfig, Config, ConfigError

OUTSIDE_DIR = "outside"  # under the run directory: one Zenoh config per outside service
# Waiting for an outside service: a line of countdown this often (s), and the wait
# between checks of a stop request (s).
COUNTDOWN_STEP_S = 10.0
POLL_S = 0.5
DEFAULT_WITHOUT_TIMEOUT_S = 120.0


class OutsideMissing(RuntimeError):
    """An outside service did not join within its time."""


def check_without(services: Sequence[str], without: Sequence[str]) -> tuple[str, ...]:
    """The services to leave out, in stack order; ConfigError names any that this stack
    does not run (a typo, or a service of another scenario)."""
    unknown = sorted(set(without) - set(services))
    if unknown:
        raise ConfigError(
            f"--without {', '.join(unknown)}: not a service of this stack ({', '.join(services)})"
        )
    return tuple(name for name in services if name in without)


def outside_config_path(run_dir: Path, service: str) -> Path:
    return run_dir / OUTSIDE_DIR / f"{service}.json5"


def _differences(value: Any, default: Any) -> Any:
    """The parts of a JSON config ``value`` that differ from ``default`` (None: none)."""
    if isinstance(value, dict) and isinstance(default, dict):
        out = {}
        for key, item in value.items():
            diff = _differences(item, default.get(key)) if key in default else item
            if diff is not None:
                out[key] = diff
        return out or None
    return None if value == default else value


def write_outside_config(run_dir: Path, service: str, bus: BusConfig) -> Path:
    """Write the Zenoh config an outside ``service`` opens its session with
    (``zenoh.Config.from_file(path)``); its path.

    ``bus`` is that service's bus settings in the run's mesh (endpoint, own listen port,
    the ports to connect to, gossip off). The file holds everything in which the
    session the stack's own services open (teleop.bus.session.session_config) differs
    from Zenoh's defaults: mode peer, multicast off, gossip off, endpoints, and the
    same shared-memory and low-latency transport settings (a low-latency peer and a
    normal one do not link). The file is private to the user (mode 0600).
    """
    conf = session_config(bus, listen=False)
    wanted = _differences(json.loads(str(conf)), json.loads(str(zenoh.Config())))
    path = outside_config_path(run_dir, service)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = (
        f"// Zenoh config of the '{service}' service, run outside the stack (teleop run or\n"
        "// up --without): open the session with zenoh.Config.from_file(this file).\n"
        "// Written by the launcher for this run only: its ports change every run.\n"
    )
    path.touch(mode=0o600)
    path.write_text(header + json.dumps(wanted, indent=2) + "\n")
    return path


def _stream_lines(service: str, topics: Topics, scenario: str) -> list[str]:
    lines = []
    for stream in graph.scenario_streams(scenario):
        role = []
        if service in stream.producers:
            role.append("publish" + (" (observers' batched copy)" if stream.batch_of else ""))
        if service in stream.consumers:
            role.append("subscribe")
        if role:
            lines.append(
                f"    {' and '.join(role):9s} {getattr(topics, stream.name)}  "
                f"{stream.schema.kind.name}, {stream.rate}"
            )
    return lines


def join_instructions(
    service: str,
    config: Config,
    config_path: Path,
    stack: Sequence[str],
    *,
    awaits: Sequence[str] = (),
    timeout_s: float,
) -> str:
    """What the user's own ``service`` must do to join this stack (printed by the CLI)."""
    topics = Topics(config.robot.robot_id)
    others = [name for name in stack if name != service]
    bus = config.bus
    lines = [
        f"{service} is left out: start your own (see docs/protocol.md; examples/).",
        f"  zenoh config:  {config_path}  (zenoh.Config.from_file)",
        f"  it listens on  {bus.peer_listen_endpoint}",
        f"  it connects to {', '.join([bus.endpoint, *bus.peer_connect_endpoints])}",
        f"  robot id:      {config.robot.robot_id}   mode: {config.run.mode}   "
        f"scenario: {config.run.scenario}",
        f"  declare        {topics.alive(service)}  (once its publishers and subscribers exist)",
        f"  then           {topics.alive(service, ready=True)}  (once it sees the alive "
        f"tokens of: {', '.join(others)})",
    ]
    if awaits:
        lines.append(
            f"  then wait for  {topics.ready_all}  of: {', '.join(awaits)}  (before its work)"
        )
    lines += ["  streams:", *_stream_lines(service, topics, config.run.scenario)]
    cpu = config.cpu
    if config.run.mode == "realtime" and cpu.fifo_priority > 0 and service in cpu.fifo_services:
        # The stack's loops hold both cores of a small machine under SCHED_FIFO: a loop
        # scheduled normally runs only in what they leave, and its periods slip.
        lines.append(
            f"  realtime:      the stack's loops run SCHED_FIFO {cpu.fifo_priority}: run yours "
            f"at it too (chrt -f {cpu.fifo_priority} python ...; needs CAP_SYS_NICE)"
        )
    lines.append(f"  waiting up to {timeout_s:g} s for it (--without-timeout)")
    return "\n".join(lines)


def wait_for_outside(
    session: zenoh.Session,
    topics: Topics,
    services: Sequence[str],
    timeout_s: float,
    report: Callable[[str], None],
    *,
    stop: threading.Event | None = None,
    still_running: Callable[[], None] | None = None,
) -> None:
    """Wait until every outside service's ready token is present, reporting the time
    left every :data:`COUNTDOWN_STEP_S`; OutsideMissing after ``timeout_s``.

    ``still_running`` is called between checks and may raise (a stack service that
    died meanwhile); ``stop`` ends the wait early with OutsideMissing as well.
    """
    if not services:
        return
    start = time.monotonic()
    next_report = 0.0
    missing = tuple(services)
    while True:
        waited_s = time.monotonic() - start
        left_s = timeout_s - waited_s
        if left_s <= 0 or (stop is not None and stop.is_set()):
            raise OutsideMissing(
                f"outside service(s) not ready after {timeout_s:g} s: {', '.join(missing)} "
                f"(no {topics.ready_all.removesuffix('*')}<service> token; is it running, "
                "with the config file printed above?)"
            )
        if waited_s >= next_report:
            report(f"waiting for {', '.join(missing)} (outside the stack): {left_s:.0f} s left")
            next_report += COUNTDOWN_STEP_S
        try:
            wait_alive(session, topics, missing, min(POLL_S, left_s), ready=True)
            report(f"{', '.join(services)} joined after {time.monotonic() - start:.1f} s")
            return
        except ServicesMissing as exc:
            missing = exc.missing
        if still_running is not None:
            still_running()
