"""A service left out of the stack (``--without SERVICE``) and run from outside.

The launcher starts every other service, gives the outside one a place in the run's
peer mesh (its own loopback port to listen on, the ports of everyone else to connect
to: peers do not forward data for each other, so it needs a link to each), writes the
complete Zenoh config of that place to ``<run_dir>/outside/<service>.json5``
(:func:`write_outside_config`), tells the user what the service must do to join
(:func:`join_instructions`), and waits for its ready token (:func:`wait_for_outside`).
What a client must do is in docs/protocol.md, whose table of the tokens each service
waits for is generated here (:func:`join_tables`); examples/ has two such clients.

A by-hand observer of a running stack gets a Zenoh config the same way, from the run
directory alone (:func:`write_observer_config`, ``python -m teleop.run.outside observer
RUN_DIR``): a link to every process of the run, the read-only observer credentials.
"""

from __future__ import annotations

import argparse
import configparser
import json
import shlex
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import zenoh

from teleop.bus import graph
from teleop.bus.access import LAUNCHER, OBSERVER
from teleop.bus.messages import PROTOCOL_VERSION
from teleop.bus.session import ServicesMissing, session_config, wait_alive
from teleop.bus.topics import Topics
from teleop.core import markdown
from teleop.core.config import SCENARIOS, Config, ConfigError, load_config
from teleop.core.rundir import AUTH_DIR, FOREGROUND_DIR, SUPERVISOR_CONF_FILE

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


def outside_metadata(config: Config, service: str) -> dict[str, str | float]:
    """What the outside config file tells its program besides Zenoh's settings, under
    Zenoh's ``metadata`` (free-form JSON that Zenoh does not interpret: it only shows it
    in its admin space): the robot id of the run's keys, the service's name, the protocol
    version every record's header must carry, and the bus rate (``loop.rate_hz``: one
    record of each loop stream per period)."""
    return {
        "robot_id": config.robot.robot_id,
        "service": service,
        "protocol_version": PROTOCOL_VERSION,
        "loop_rate_hz": config.loop.rate_hz,
    }


def write_outside_config(run_dir: Path, service: str, config: Config) -> Path:
    """Write the Zenoh config an outside ``service`` opens its session with
    (``zenoh.Config.from_file(path)``); its path.

    ``config.bus`` is that service's bus settings in the run's mesh (endpoint, own listen
    port, the ports to connect to, gossip off, its credentials). The file holds
    everything in which the session the stack's own services open
    (teleop.bus.session.session_config) differs from Zenoh's defaults: mode peer,
    multicast off, gossip off, endpoints, and the same shared-memory and low-latency
    transport settings (a low-latency peer and a normal one do not link); and, under
    ``metadata``, the robot id (:func:`outside_metadata`). The file is private to the
    user (mode 0600).
    """
    conf = session_config(config.bus, listen=False)
    conf.insert_json5("metadata", json.dumps(outside_metadata(config, service)))
    wanted = _differences(json.loads(str(conf)), json.loads(str(zenoh.Config())))
    path = outside_config_path(run_dir, service)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = (
        f"// Zenoh config of the '{service}' service, run outside the stack (teleop run or\n"
        "// up --without): open the session with zenoh.Config.from_file(this file).\n"
        "// Written by the launcher for this run only: its ports change every run.\n"
        f"// Robot id: {config.robot.robot_id} (also metadata/robot_id below, which Zenoh\n"
        "// does not interpret): every key is teleop/<robot id>/...\n"
        f"// Protocol version: {PROTOCOL_VERSION} (metadata/protocol_version): every record's\n"
        "// header starts with it; the stack drops a record of any other version.\n"
        f"// Bus rate: {config.loop.rate_hz:g} Hz (metadata/loop_rate_hz): one HAPTIC_STATE,\n"
        "// JOINT_COMMAND, PLANT_STATE and FORCE_FEEDBACK per period.\n"
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


def tokens_to_await(
    service: str, stack: Sequence[str], *, launcher: bool
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Whose tokens ``service`` waits for in a stack of ``stack``'s services (outside
    ones included): the ``alive`` tokens before it declares its own ``ready`` (every
    other service: its links to each are up), and the ``ready`` tokens before its work
    (the plant only, before its first step: every other service, and the ``launcher``
    of ``teleop run`` when ``launcher``). The launcher starts its programs with the
    same lists (``--peers``, ``--await``; a test holds them together)."""
    alive = tuple(name for name in stack if name != service)
    if service != "plant":
        return alive, ()
    return alive, (*alive, *((LAUNCHER,) if launcher else ()))


def _names(names: Sequence[str]) -> str:
    return ", ".join(f"`{name}`" for name in names) or "-"


def join_tables() -> str:
    """The table of docs/protocol.md ("Bringing your own service"): per scenario and
    service, whose ``alive`` tokens it waits for before ``ready``, and whose ``ready``
    tokens before its work (Markdown; ``python -m teleop.run.outside``)."""
    rows = []
    optional = [spec for spec in graph.SERVICES if spec.optional]
    for scenario in SCENARIOS:
        stack = graph.scenario_services(scenario)
        extra = [spec.name for spec in optional if scenario in spec.scenarios]
        for service in stack:
            alive, ready = tokens_to_await(service, stack, launcher=False)
            with_launcher = tokens_to_await(service, stack, launcher=True)[1]
            ready_text = "-"
            if ready:
                ready_text = f"`teleop run`: {_names(with_launcher)}; `teleop up`: {_names(ready)}"
            rows.append((scenario, f"`{service}`", _names(alive), ready_text))
        if extra:
            rows.append((scenario, _names(extra), "as any other service", "-"))
    header = ("scenario", "service", "`alive` tokens to see before declaring `ready`",
              "`ready` tokens to see before its work")  # fmt: skip
    lines = markdown.table(header, rows)
    notes = [
        f"`{spec.name}` runs with `{spec.optional}`: every service then waits for its "
        "`alive` token too, and the plant for its `ready` token."
        for spec in optional
    ]
    return "\n".join([*lines, "", *notes])


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
    others, _ = tokens_to_await(service, stack, launcher=False)
    bus = config.bus
    lines = [
        f"{service} is left out: start your own (see docs/protocol.md; examples/).",
        f"  zenoh config:  {config_path}  (zenoh.Config.from_file)",
        f"  it listens on  {bus.peer_listen_endpoint}",
        f"  it connects to {', '.join([bus.endpoint, *bus.peer_connect_endpoints])}",
        f"  robot id:      {config.robot.robot_id}   mode: {config.run.mode}   "
        f"scenario: {config.run.scenario}",
        f"  protocol:      version {PROTOCOL_VERSION} in every record's header (also the "
        f"token {topics.protocol(PROTOCOL_VERSION)}); docs/protocol.md, Versioning",
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
    left: list[str] = []  # came alive, then went before it was ready

    def on_alive(sample: zenoh.Sample) -> None:
        name = topics.service_of(str(sample.key_expr))
        if sample.kind == zenoh.SampleKind.DELETE and name in services:
            left.append(name)

    watch = session.liveliness().declare_subscriber(topics.alive_all, on_alive)
    try:
        _wait_ready(session, topics, services, timeout_s, report, stop, still_running, left)
    finally:
        watch.undeclare()


def _wait_ready(
    session: zenoh.Session,
    topics: Topics,
    services: Sequence[str],
    timeout_s: float,
    report: Callable[[str], None],
    stop: threading.Event | None,
    still_running: Callable[[], None] | None,
    left: list[str],
) -> None:
    """:func:`wait_for_outside`'s loop; ``left``: services whose alive token went (each
    reported once, as it happens)."""
    start = time.monotonic()
    next_report = 0.0
    missing = tuple(services)
    told = 0
    while True:
        while told < len(left):
            report(
                f"{left[told]} came and left before it was ready: its own output says why "
                f"(a client of another protocol version leaves so; this stack speaks "
                f"version {PROTOCOL_VERSION}, token {topics.protocol(PROTOCOL_VERSION)})"
            )
            told += 1
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


# The run's settings on a supervised program's command line (teleop.run.stack.service_command).
_CONFIG_FLAG, _SET_FLAG = "--config", "--set"
# A program's own place in the run's mesh and its own credentials: not the observer's.
_OWN_SETTINGS = (
    "bus.peer_listen_endpoint=",
    "bus.peer_connect_endpoints=",
    "bus.credentials_file=",
)
OBSERVER_CONFIG = OBSERVER  # <run_dir>/outside/observer.json5


def _program_commands(run_dir: Path) -> list[list[str]]:
    """The argv of every program in ``<run_dir>/supervisord.conf`` (as supervisord reads
    it: '%' doubled in the file, the command split by POSIX shlex), and of the programs
    the launcher runs in its terminal (``<run_dir>/foreground/``)."""
    path = run_dir / SUPERVISOR_CONF_FILE
    if not path.exists():
        raise FileNotFoundError(f"{path}: no stack was started in {run_dir}")
    parser = configparser.RawConfigParser(strict=False)
    parser.read(path)
    supervised = [
        shlex.split(parser.get(section, "command").replace("%%", "%"))
        for section in parser.sections()
        if section.startswith("program:") and parser.has_option(section, "command")
    ]
    # The launcher's own terminal programs (teleop.run.foreground), as argv lists.
    commands = sorted((run_dir / FOREGROUND_DIR).glob("*.json"))
    foreground = [json.loads(command.read_text()) for command in commands]
    return supervised + foreground


def _settings(argv: Sequence[str]) -> tuple[Path | None, list[str]]:
    """A service command's config file and its ``--set`` overrides, in order."""
    config_file, overrides = None, []
    for flag, value in zip(argv, argv[1:], strict=False):
        if flag == _CONFIG_FLAG:
            config_file = Path(value)
        elif flag == _SET_FLAG:
            overrides.append(value)
    return config_file, overrides


def stack_endpoints(run_dir: Path) -> tuple[str, tuple[str, ...]]:
    """Where the processes of the stack started in ``run_dir`` (``teleop run`` or ``teleop
    up``) listen: the run's listener (``bus.endpoint``: the launcher of ``teleop run``, the
    plant of ``teleop up``) and every other process's own endpoint, its outside services'
    included (from their config files). Peers do not forward data for each other: a
    session that must hear every stream needs a link to each of these."""
    listener, own = "", []
    for argv in _program_commands(run_dir):
        for override in _settings(argv)[1]:
            name, _, value = override.partition("=")
            if name == "bus.endpoint":
                listener = json.loads(value)
            elif name == "bus.peer_listen_endpoint":
                own.append(json.loads(value))
    for path in sorted((run_dir / OUTSIDE_DIR).glob("*.json5")):
        if path.stem != OBSERVER_CONFIG:
            own += json.loads(str(zenoh.Config.from_file(str(path))))["listen"]["endpoints"]
    if not listener:
        raise ValueError(f"{run_dir / SUPERVISOR_CONF_FILE}: no service names bus.endpoint")
    return listener, tuple(dict.fromkeys(own))


def observer_config(run_dir: Path) -> Config:
    """The run's config as its services load it, with the bus of a read-only observer:
    connected to the listener and to every other process (:func:`stack_endpoints`),
    listening on a port of its own choice, with ``<run_dir>/auth/observer.json`` as its
    credentials when the run's bus is secure."""
    run_dir = Path(run_dir).absolute()
    services = [argv for argv in _program_commands(run_dir) if _SET_FLAG in argv]
    if not services:
        raise ValueError(f"{run_dir / SUPERVISOR_CONF_FILE}: no bus service in it")
    config_file, overrides = _settings(services[0])
    run_settings = [o for o in overrides if not o.startswith(_OWN_SETTINGS)]
    config = load_config(config_file, run_settings)
    listener, own = stack_endpoints(run_dir)
    credentials = run_dir / AUTH_DIR / f"{OBSERVER}.json"
    bus = replace(
        config.bus,
        endpoint=listener,
        gossip=False,
        peer_listen_endpoint="",
        peer_connect_endpoints=own,
        credentials_file=str(credentials) if config.bus.secure else "",
    )
    return replace(config, bus=bus)


def write_observer_config(run_dir: Path) -> Path:
    """Write ``<run_dir>/outside/observer.json5``, the Zenoh config of a by-hand observer
    of the stack running in ``run_dir`` (:func:`observer_config`); its path."""
    return write_outside_config(Path(run_dir), OBSERVER_CONFIG, observer_config(run_dir))


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m teleop.run.outside``: the join table of docs/protocol.md;
    ``python -m teleop.run.outside observer RUN_DIR``: write the observer's config."""
    parser = argparse.ArgumentParser(prog="python -m teleop.run.outside", description=main.__doc__)
    sub = parser.add_subparsers(dest="command")
    observer = sub.add_parser("observer", help="write RUN_DIR/outside/observer.json5")
    observer.add_argument("run_dir", type=Path, help="the --run-dir of a running stack")
    args = parser.parse_args(argv)
    if args.command == "observer":
        print(write_observer_config(args.run_dir))
    else:
        print(join_tables())
    return 0


if __name__ == "__main__":
    sys.exit(main())
