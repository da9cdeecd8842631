"""The teleop stack under supervisord: which programs, and a scenario run on them.

``teleop run SCENARIO`` (not ``--inprocess``) calls :func:`run_on_services`:

1. the runner opens its own Zenoh session as the run's listener on a free loopback
   port, subscribes to the run's events and announces itself;
2. supervisord starts plant, controller and recorder, all connecting to that port;
   the plant waits for every peer's liveliness token (runner included) before its
   first step, so nothing is published before everybody listens;
3. the runner waits for the plant's FINISHED event (printing progress), stops the
   stack (each service writes ``<run_dir>/<service>.summary.json`` on close, the
   recorder completes its .rrd) and merges the summaries.

``teleop up`` starts the same programs detached with the plant as listener and no
end (``--continuous``); ``teleop down`` stops them. Both lay the stack out with one
recipe, :func:`plan_stack` (endpoint, overrides, credentials, mesh, programs, the outside
services' configs), the difference chosen once as a :class:`Launch`.

``--without SERVICE`` leaves services out of either: they keep their place in the peer
mesh, the user runs them (teleop.run.outside), and the launcher waits for their ready
tokens before the run goes on.

The launcher's rooms: this module plans and starts (:func:`plan_stack`,
:func:`run_on_services`, :func:`start_detached`); :mod:`teleop.run.run_watch` hears the
run (its events, progress and end); :mod:`teleop.run.fault_run` injects the faults asked
for and says what followed; :mod:`teleop.run.assemble` builds the summary from the files
the services wrote. Only the first touches processes; the last reads files only.
"""

from __future__ import annotations

import contextlib
import enum
import json
import os
import signal
import socket
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import zenoh

from teleop.bus import graph
from teleop.bus.access import (
    LAUNCHER,
    OBSERVER,
    site_observer,
    write_run_credentials,
)
from teleop.bus.graph import EYEVIEW, PLANT
from teleop.bus.session import (
    ServicesMissing,
    close_session,
    open_session,
    wait_alive,
)
from teleop.bus.topics import Topics
from teleop.core.config import (
    INPUT_DEVICE_OPERATORS,
    SCRIPTED,
    TERMINAL_OPERATORS,
    VIEWING_OPERATORS,
    BusConfig,
    Config,
    ConfigError,
    load_config,
)
from teleop.core.net import LOOPBACK, LoopbackPorts, endpoint_address
from teleop.core.rundir import (
    AUTH_DIR,
    RECORDING_FILE,
    SUPERVISOR_LOG_FILE,
    clear_run_results,
    idle_poll_status_path,
    summary_path,
)
from teleop.core.service_summaries import PlantSummary
from teleop.run import assemble, restart_priority
from teleop.run.failure import ProgramWatch, RunError, ServiceFailed, program_log_text
from teleop.run.fault_run import FaultRun
from teleop.run.faults import (
    parse_faults,
)
from teleop.run.foreground import Foreground, ForegroundExited
from teleop.run.outside import (
    DEFAULT_WITHOUT_TIMEOUT_S,
    OutsideMissing,
    check_without,
    join_instructions,
    wait_for_outside,
    write_outside_config,
)
from teleop.run.run_watch import RunWatch
from teleop.run.sites import (
    SiteError,
    check_site,
    site_links,
    site_participants,
    write_site_bundles,
)
from teleop.run.supervise import Program, Stack, StackError
from teleop.run.web_operator import WebAccess, prepare_web_operator, web_overrides

# The operator's eye view (graph.EYEVIEW) renders in a process of its own (see
# services/eyeview.py for why not a thread in the plant); it joins the stack of any
# scenario when eyeview.enabled.
# Keeps the idle CPUs polling in realtime runs (teleop/run/idle_poll.py): not a bus service.
IDLE_POLL = "idle_poll"
# Start order (supervisord priority: lower first) of the bus services, from the graph;
# they still wait on liveliness.
PRIORITY = {spec.name: spec.start_priority for spec in graph.SERVICES} | {
    router: graph.ROUTER_START_PRIORITY for router in graph.ROUTERS
}
# Before every service, and stopped after them, like the recorder (the producers are told
# to stop at once: teleop.run.supervise.STOP_AT_ONCE_MIN_PRIORITY).
IDLE_POLL_PRIORITY = 1
# Environment of every service: no telemetry, headless rendering, unbuffered logs.
SERVICE_ENVIRONMENT = {
    # This environment's executables first (the `rerun` viewer that recorder.spawn
    # starts), also when the launcher runs from .venv/bin without an activated venv.
    "PATH": os.pathsep.join((str(Path(sys.executable).parent), os.environ.get("PATH", os.defpath))),
    "RERUN_ANALYTICS": "0",
    "MUJOCO_GL": "egl",
    "PYTHONUNBUFFERED": "1",
    # Small matrices only: BLAS worker threads would just compete for the 2 cores.
    "OPENBLAS_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
}
# Waiting for all services to announce themselves (imports, model build, session) (s).
ALIVE_TIMEOUT_S = 60.0
# How often the wait for liveliness looks at the programs' states (s).
ALIVE_POLL_S = 0.5
# A run that does not finish within this many times its duration (plus slack) failed.
LOCKSTEP_TIMEOUT_FACTOR = 20.0
REALTIME_TIMEOUT_FACTOR = 2.0
RUN_TIMEOUT_SLACK_S = 30.0
# The launcher reads the run's sim time for its progress lines (every ALIVE_POLL_S) from
# the tool pose: this many a second are plenty, and its session drops the rest
# (Zenoh's ingress downsampling) before they cost it a Python callback each.
PROGRESS_TOOL_POSE_HZ = 10.0


def scenario_services(config: Config) -> tuple[str, ...]:
    """The processes of ``config.run.scenario``, plus the eye view when it is enabled
    (in realtime runs; in lockstep ones with ``eyeview.in_lockstep``, or when a person's
    device shows the view: their lockstep run goes at their own pace anyway)."""
    services = graph.scenario_services(config.run.scenario)
    eye = config.eyeview
    shown = config.run.operator in VIEWING_OPERATORS
    if eye.enabled and (config.run.mode == "realtime" or eye.in_lockstep or shown):
        return (*services, EYEVIEW)
    return services


def loopback_endpoint(ports: LoopbackPorts, tls: bool) -> str:
    """A free loopback endpoint for a process of a run, its port held by ``ports`` until
    the process listens there: ``tls/`` in a TLS run (``bus.tls``: its processes link
    only by mutual TLS), ``tcp/`` otherwise."""
    return f"{'tls' if tls else 'tcp'}/{LOOPBACK}:{ports.take()}"


def ensure_endpoint_free(endpoint: str) -> None:
    """Raise :class:`RunError` (one line, what to do) if ``endpoint``'s TCP port on this
    host is taken: by another stack, or any program. A stack never joins another's bus."""
    host, port = endpoint_address(endpoint)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host or "127.0.0.1", int(port)))
        except OSError as exc:
            raise RunError(
                f"bus endpoint {endpoint} is in use ({exc.strerror}): another stack or "
                "program listens there; stop it (teleop down --run-dir DIR) or drop "
                "--endpoint to take a free port"
            ) from None


def peer_mesh(
    names: Sequence[str], listener: str | None, ports: LoopbackPorts, *, tls: bool = False
) -> dict[str, list[str]]:
    """Each process's ``--set`` overrides for an explicit mesh, gossip off (why: see
    BusConfig.gossip). Every process but ``listener`` listens on a loopback port of its
    own (taken from ``ports``; ``tls``: a ``tls/`` endpoint) and connects to the run's listener
    (``bus.endpoint``) and to the processes before it in ``names``: each pair links
    once, by one connect, and no process needs gossip to find another. The launcher's
    own session, if it is the listener, is reached by everyone through ``bus.endpoint``.
    """
    listening: list[str] = []
    mesh: dict[str, list[str]] = {}
    for name in names:
        overrides = ["bus.gossip=false"]
        if name != listener:
            own = loopback_endpoint(ports, tls)
            overrides += [
                f'bus.peer_listen_endpoint="{own}"',
                f"bus.peer_connect_endpoints={json.dumps(listening, separators=(',', ':'))}",
            ]
            listening.append(own)
        mesh[name] = overrides
    return mesh


def service_command(
    name: str,
    run_dir: Path,
    config_file: Path | None,
    overrides: Sequence[str],
    module: Sequence[str] = (),
) -> list[str]:
    """``python -m services.<name>`` (or ``python -m <module...>``) with the run's
    directory, config file and ``--set`` overrides: how a launcher starts a process of
    the service lifecycle (teleop.bus.service.service_main)."""
    entry = list(module) or [f"services.{name}"]
    command = [sys.executable, "-m", *entry, "--run-dir", str(run_dir)]
    if config_file is not None:
        command += ["--config", str(Path(config_file).absolute())]
    for override in overrides:
        command += ["--set", override]
    return command


def service_programs(
    services: Sequence[str],
    config_file: Path | None,
    overrides: Sequence[str],
    run_dir: Path,
    *,
    listener: str | None,
    await_services: dict[str, Sequence[str]],
    continuous: bool,
    mesh: dict[str, list[str]],
    credentials: Mapping[str, Path] | None = None,
    restarts: Mapping[str, dict[str, int]] | None = None,
    modules: Mapping[str, str] | None = None,
    hold_at_s: Sequence[float] = (),
) -> list[Program]:
    """The supervisord programs of ``services``, each given the same config and
    overrides, then its place in the run's ``mesh`` (a :func:`peer_mesh` of the
    services, and of the outside ones too if any) and its ``credentials`` file, if any
    (:func:`run_credentials`); ``restarts``: how a service's restarts start
    (:func:`restart_priorities`); ``modules``: the program of a service that is not
    services/<name>.py (a person's operator); ``hold_at_s``: the sim instants at which
    a lockstep plant waits for the launcher's release (its faults' instants)."""
    programs = []
    for name in services:
        role, robot = graph.role_of(name), graph.robot_of(name)
        own = list(mesh[name])
        if robot is not None:  # one robot's instance of a per-robot service
            own.append(f"robot.robot_id={json.dumps(robot)}")
        if credentials is not None:
            own.append(f'bus.credentials_file="{credentials[name]}"')
        module = (f"services.{role}",)
        if graph.is_router(name):
            module = ("services.router",)
        if modules and name in modules:
            module = (modules[name],)
        command = service_command(name, run_dir, config_file, [*overrides, *own], module)
        if name == listener:
            command.append("--listen")
        if await_services.get(role):
            command += ["--await", ",".join(await_services[role])]
        # Tokens are per robot and by service: an instance's peers are the other services.
        peers = [other for other in graph.services_of(services) if other != role]
        if peers:
            command += ["--peers", ",".join(peers)]
        if continuous:
            command.append("--continuous")
        if role == PLANT and hold_at_s:
            command += ["--hold-at", ",".join(repr(float(t)) for t in hold_at_s)]
        if restarts and restarts.get(role):
            command = restart_priority.command(run_dir, name, command, **restarts[role])
        programs.append(
            Program(
                name=name,
                command=command,
                priority=PRIORITY[role],
                environment=dict(SERVICE_ENVIRONMENT),
            )
        )
    return programs


def restart_priorities(config: Config) -> dict[str, dict[str, int]]:
    """How each service's restarts start (teleop.run.restart_priority): the recorder and
    the eye view at their ``nice``, below the control path; the control path's services
    (``cpu.fifo_services``) under SCHED_FIFO ``cpu.restart_fifo_priority``, below the
    loops. Seconds of imports and loading, beside a loop that runs on, before their own
    code chooses. First starts are left alone."""
    restarts = {"recorder": {"nice": config.recorder.nice}, EYEVIEW: {"nice": config.eyeview.nice}}
    if config.cpu.restart_fifo_priority:
        for name in config.cpu.fifo_services:
            restarts[name] = {"fifo": config.cpu.restart_fifo_priority}
    return restarts


def run_credentials(
    config: Config, run_dir: Path, participants: Sequence[str]
) -> dict[str, Path] | None:
    """With ``bus.secure``: fresh credentials for ``participants`` and a read-only
    :data:`OBSERVER` in ``<run_dir>/auth`` (teleop.bus.access; with ``bus.tls`` their
    certificates too), their files by name; else None (an open bus). A run across hosts
    (``site.name``) adds every site's router and observer: the first robot's site makes
    every identity once (teleop.run.sites hands the other sites theirs), its router's
    certificate valid at ``site.listen``'s address too."""
    if not config.bus.secure:
        return None
    participants = [*participants, OBSERVER]
    addresses: dict[str, list[str]] = {}
    if config.site.name:
        participants += [n for n in site_links(config.robot_ids()) if n not in participants]
        if config.site.listen:
            host, _ = endpoint_address(config.site.listen)
            addresses[graph.router_name(config.site.name)] = [host]
    return write_run_credentials(
        run_dir / AUTH_DIR,
        participants,
        config.robot_ids(),
        tls=config.bus.mutual_tls,
        addresses=addresses,
    )


def idle_poll_cpus(config: Config) -> list[int]:
    """The CPUs a stack run with ``config`` keeps polling: in realtime runs with
    ``cpu.idle_poll``, those of ``cpu.idle_poll_cpus`` (all when empty) that this process
    may use; else none."""
    if not config.cpu.polls_idle(config.run.mode):
        return []
    available = os.sched_getaffinity(0)
    wanted = set(config.cpu.idle_poll_cpus) or available
    return sorted(wanted & available)


def idle_poll_programs(cpus: Sequence[int], run_dir: Path) -> list[Program]:
    """One idle poller (``services.idle_poll``) per CPU of ``cpus`` (:func:`idle_poll_cpus`).
    They start first and stop last (supervisord priority), so they span the whole run;
    each writes its status to :func:`idle_poll_status_path` (stale ones are removed)."""
    programs = []
    for cpu in cpus:
        status = idle_poll_status_path(run_dir, cpu)
        status.unlink(missing_ok=True)
        command = [sys.executable, "-m", f"services.{IDLE_POLL}", "--cpu", str(cpu)]
        programs.append(
            Program(
                name=f"{IDLE_POLL}_cpu{cpu}",
                command=[*command, "--status-file", str(status)],
                priority=IDLE_POLL_PRIORITY,
                environment=dict(SERVICE_ENVIRONMENT),
            )
        )
    return programs


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _plant_awaits(stack: Sequence[str], *extra: str) -> list[str]:
    """What the plant waits for (ready tokens, under its robot's keys) before its first
    step: every other service (an instance of ``stack`` by its service)."""
    return [name for name in graph.services_of(stack) if name != PLANT] + list(extra)


def prepare_outside(
    config_file: Path | None,
    overrides: Sequence[str],
    run_dir: Path,
    stack: Sequence[str],
    outside: Sequence[str],
    mesh: dict[str, list[str]],
    plant_awaits: Sequence[str],
    timeout_s: float,
    credentials: Mapping[str, Path] | None = None,
) -> list[tuple[str, BusConfig]]:
    """Write each outside service's Zenoh config (its place in ``mesh`` and, on a secure
    bus, its ``credentials``); per service, the instructions that tell the user how to
    join, and its bus settings."""
    joins = []
    for name in outside:
        own_overrides = list(mesh[name])
        if credentials is not None:
            own_overrides.append(f'bus.credentials_file="{credentials[name]}"')
        own = load_config(config_file, [*overrides, *own_overrides])
        path = write_outside_config(run_dir, name, own)
        awaits = plant_awaits if name == "plant" else ()
        text = join_instructions(name, own, path, stack, awaits=awaits, timeout_s=timeout_s)
        joins.append((text, own.bus))
    return joins


class Launch(enum.Enum):
    """How a stack is launched: chosen once, by the command.

    - RUN (``teleop run``): this process holds the mesh's endpoint and takes part in the
      run (its own credentials; the plant waits for its ready token); the stack ends at
      the plant's FINISHED.
    - UP (``teleop up``): the plant holds the endpoint; the stack runs until stopped.
    """

    RUN = "run"
    UP = "up"

    @property
    def listener(self) -> str | None:
        """The service that holds the mesh's endpoint (None: the launcher itself)."""
        return None if self is Launch.RUN else "plant"

    @property
    def participants(self) -> tuple[str, ...]:
        """Processes of the run besides the services: the launcher, in a RUN."""
        return (LAUNCHER,) if self is Launch.RUN else ()


# The service a person's device stands in for (run.operator).
OPERATOR_SERVICE = "operator"


@dataclass(frozen=True)
class StackServices:
    """Which services a stack has: the scenario's, the ones left out (``--without``),
    those it starts and, in one site of a run across hosts (``site.name``), those the
    other site runs (``remote``) and this site's router (started first)."""

    scenario: tuple[str, ...]
    outside: tuple[str, ...]
    started: tuple[str, ...]
    remote: tuple[str, ...] = ()
    router: str = ""
    # Started by the launcher in the user's terminal, not by supervisord: a person's
    # operator (``run.operator``; teleop.run.foreground).
    foreground: tuple[str, ...] = ()
    # The program each service runs, where it is not services/<name>.py.
    modules: tuple[tuple[str, str], ...] = ()

    @classmethod
    def of(cls, config: Config, without: Sequence[str]) -> StackServices:
        """ConfigError names a service left out that the stack does not run."""
        scenario = graph.instances(scenario_services(config), config.robot_ids())
        if config.run.robots > 1 and without:
            raise ConfigError(
                f"--without: not in a run of several robots (run.robots={config.run.robots})"
            )
        outside = check_without(scenario, without)
        started = tuple(n for n in scenario if n not in outside)
        human = config.run.operator != SCRIPTED and OPERATOR_SERVICE in started
        terminal = human and config.run.operator in TERMINAL_OPERATORS
        foreground = (OPERATOR_SERVICE,) if terminal else ()
        input_device = config.run.operator in INPUT_DEVICE_OPERATORS
        program = "input_device" if input_device else config.run.operator
        modules = ((OPERATOR_SERVICE, f"services.{program}"),) if human else ()
        site = config.site.name
        if not site:
            return cls(scenario, outside, started, foreground=foreground, modules=modules)
        router = graph.router_instance(site, config.site.robot)
        mine = site_participants(site, config.site.robot, started, config.robot_ids())
        here = tuple(n for n in started if n in mine)
        remote = tuple(n for n in scenario if n not in here)
        return cls(scenario, outside, (router, *here), remote, router, foreground, modules)

    def listener(self, launch: Launch) -> str | None:
        """The process that holds the stack's endpoint: the launch's, or the site's
        router where the launch's listener runs on the other site."""
        if launch.listener is None or launch.listener in self.started:
            return launch.listener
        return self.router or None


@dataclass(frozen=True)
class StackPlan:
    """A stack laid out, nothing started yet: what each process is told (its overrides,
    its place in the mesh, its credentials), the supervisord programs, and the join
    instructions of the services left out."""

    services: StackServices
    endpoint: str
    run_overrides: list[str]
    credentials: dict[str, Path] | None
    mesh: dict[str, list[str]]
    programs: list[Program]
    joins: list[tuple[str, BusConfig]]  # per service left out: instructions, its bus
    polled_cpus: list[int]  # the CPUs kept polling (idle_poll_cpus), a poller each
    foreground: list[Program]  # run in the user's terminal (StackServices.foreground)
    web: WebAccess | None  # the web page's port and token (run.operator "web"), else None


def plan_stack(
    launch: Launch,
    config: Config,
    config_file: Path | None,
    overrides: Sequence[str],
    run_dir: Path,
    ports: LoopbackPorts,
    services: StackServices,
    *,
    endpoint: str | None = None,
    without_timeout_s: float = DEFAULT_WITHOUT_TIMEOUT_S,
    credentials: dict[str, Path] | None = None,
    hold_at_s: Sequence[float] = (),
) -> StackPlan:
    """The one launch recipe: the mesh's endpoint (``endpoint``, or a loopback port of
    ``ports``), the run's overrides, credentials for every participant (``credentials``:
    given, as a site's from the other site's launcher), an explicit mesh of the
    services (outside ones included), their programs (and the idle pollers'), and the
    outside services' Zenoh configs and join instructions, all written to ``run_dir``;
    ``hold_at_s``: a lockstep run's fault instants, where the plant waits for the
    launcher (:func:`service_programs`)."""
    tls = config.bus.mutual_tls
    endpoint = endpoint or loopback_endpoint(ports, tls)
    web = prepare_web_operator(config, run_dir, ports)  # --operator web: port, token
    run_overrides = [
        *overrides,
        *web_overrides(web),
        f'bus.endpoint="{endpoint}"',
        f'run.mode="{config.run.mode}"',
        f'run.scenario="{config.run.scenario}"',
    ]
    if not config.recorder.rrd_path:
        run_overrides.append(f'recorder.rrd_path="{run_dir / RECORDING_FILE}"')
    if credentials is None:
        credentials = run_credentials(config, run_dir, [*services.scenario, *launch.participants])
    listener = services.listener(launch)
    mesh = peer_mesh([*services.started, *services.outside], listener, ports, tls=tls)
    plant_awaits = _plant_awaits(services.scenario, *launch.participants)
    polled_cpus = idle_poll_cpus(config)
    restarts = {
        name: how for name, how in restart_priorities(config).items()
        if name not in services.foreground
    }  # fmt: skip
    every = service_programs(
        services.started,
        config_file,
        run_overrides,
        run_dir,
        listener=listener,
        await_services={"plant": plant_awaits},
        continuous=launch is Launch.UP,
        credentials=credentials,
        mesh=mesh,
        restarts=restarts,
        modules=dict(services.modules),
        hold_at_s=hold_at_s,
    )
    programs = [p for p in every if p.name not in services.foreground]
    programs += idle_poll_programs(polled_cpus, run_dir)
    foreground = [p for p in every if p.name in services.foreground]
    joins = prepare_outside(
        config_file, run_overrides, run_dir, services.scenario, services.outside, mesh,
        plant_awaits, without_timeout_s, credentials,
    )  # fmt: skip
    return StackPlan(
        services, endpoint, run_overrides, credentials, mesh, programs, joins, polled_cpus,
        foreground, web,
    )  # fmt: skip


def run_on_services(
    config: Config,
    config_file: Path | None,
    overrides: Sequence[str],
    run_dir: Path,
    progress: Callable[[str], None] | None = None,
    *,
    without: Sequence[str] = (),
    without_timeout_s: float = DEFAULT_WITHOUT_TIMEOUT_S,
    announce: Callable[[str], None] = _stderr,
    restarts_expected: Sequence[str] = (),
    kills: Sequence[str] = (),
    freezes: Sequence[str] = (),
) -> dict[str, Any]:
    """Run ``config.run.scenario`` on the supervised services; return the merged summary.

    ``restarts_expected``: services that will be killed on purpose (a test of their
    recovery): their restarts do not fail the run.

    ``without``: services left out; ``announce`` tells the user how to join each (its
    Zenoh config is in the run directory), then the run waits up to
    ``without_timeout_s`` for their ready tokens (RunError after that). Their summaries
    are missing: the run's summary takes what the stack measured and lists them under
    ``outside``.

    ``kills`` / ``freezes``: faults to inject, ``SERVICE@T`` / ``SERVICE@T:SECONDS``
    (teleop.run.faults; a bad one raises FaultSpecError before anything starts); the
    summary's ``faults`` says what followed each.

    A person's operator (``run.operator``) runs in this process's terminal, started once
    the stack is up and stopped when the run ends (teleop.run.foreground); the run fails
    if it ends first.

    Several robots (``run.robots``): a plant and a controller per robot
    (``<service>-<robot_id>``, graph.instances), the station's services once; the run
    ends when every plant has finished, and the summary has a section per robot
    (:func:`teleop.run.assemble.robot_section`) under ``robots``.
    """
    _refuse_run(config, kills, freezes)
    layout = StackServices.of(config, without)
    fault_specs = parse_faults(kills, freezes, layout.started, config.run.duration_s)
    run_dir = run_dir.absolute()
    run_dir.mkdir(parents=True, exist_ok=True)
    refuse_if_running(run_dir)
    clear_run_results(run_dir)
    faults = FaultRun(config, fault_specs) if fault_specs else None
    watch = RunWatch(config, faults.on_started if faults is not None else None)
    # The run's ports stay held here until it ends: a restarted service takes its own again.
    with LoopbackPorts() as ports:
        plan = plan_stack(
            Launch.RUN, config, config_file, overrides, run_dir, ports, layout,
            without_timeout_s=without_timeout_s,
            hold_at_s=faults.hold_at_s if faults is not None else (),
        )  # fmt: skip
        wall_start = time.perf_counter()
        _run_plan(
            plan, run_dir, config, watch, faults, progress,
            without_timeout_s=without_timeout_s, announce=announce,
            restarts_expected=restarts_expected,
        )  # fmt: skip
        wall_s = time.perf_counter() - wall_start
    return assemble.run_summary(
        config, run_dir, layout.started, layout.outside, watch, faults, plan.polled_cpus, wall_s
    )


def _refuse_run(config: Config, kills: Sequence[str], freezes: Sequence[str]) -> None:
    """RunError or ConfigError for a run ``teleop run`` does not make."""
    if config.site.name:
        raise RunError(
            "site.name: a run across hosts starts one site per host with teleop up --site "
            "(docs/sites.md); teleop run keeps the whole stack on this host"
        )
    robots = len(config.robot_ids())
    if robots > 1 and (kills or freezes):
        raise ConfigError(
            f"--kill and --freeze: not in a run of several robots (run.robots={robots})"
        )


def _launcher_session(
    plan: StackPlan, config: Config, watch: RunWatch, faults: FaultRun | None
) -> tuple[zenoh.Session, list[Any]]:
    """The launcher's session, the mesh's listener, hearing the run (``watch``, and the
    faults' plant states and tokens); the session and what to undeclare."""
    credentials = plan.credentials
    bus = replace(
        config.bus,
        endpoint=plan.endpoint,
        gossip=False,
        credentials_file=str(credentials[LAUNCHER]) if credentials else "",
    )
    progress_rate = {robot.tool_pose: PROGRESS_TOOL_POSE_HZ for robot in watch.robots}
    session = open_session(bus, listen=True, ingress_rate_hz=progress_rate)
    entities: list[Any] = []
    try:
        if faults is not None:
            entities += faults.subscribe(session, watch.robots[0], watch.drops)
        entities += watch.listen(session)
    except BaseException:
        close_session(session, *reversed(entities))
        raise
    return session, entities


def _run_plan(
    plan: StackPlan,
    run_dir: Path,
    config: Config,
    watch: RunWatch,
    faults: FaultRun | None,
    progress: Callable[[str], None] | None,
    *,
    without_timeout_s: float,
    announce: Callable[[str], None],
    restarts_expected: Sequence[str],
) -> None:
    """Start ``plan``'s programs and wait for the run's end; the stack stopped after it
    (each service writes its summary on close), the launcher's session closed."""
    session, entities = _launcher_session(plan, config, watch, faults)
    try:
        for text, _ in plan.joins:
            announce(text)
        with contextlib.ExitStack() as running:
            stack = running.enter_context(Stack(run_dir, plan.programs))
            watch_programs = ProgramWatch(stack.log_path, _read_log, frozenset(restarts_expected))
            check = _failure_check(stack, watch_programs)
            if faults is not None:
                check = faults.start(stack, watch_programs, check)
            # Entered last: stopped first, while the stack still runs (its summary then
            # has the run's end).
            for program in plan.foreground:
                foreground = running.enter_context(Foreground(program, run_dir))
                check = _foreground_check(foreground, check)
            try:
                _wait_run(session, plan, run_dir, config, watch, stack, check, progress,
                          without_timeout_s=without_timeout_s, announce=announce)  # fmt: skip
            except ServiceFailed as exc:
                # Said now, not after the stop (which can take seconds more).
                announce(f"teleop: the run failed:\n{exc.block()}\nstopping the services...")
                exc.reported = True
                raise
            finally:
                if faults is not None:
                    faults.close()  # nothing left frozen when the stack stops
    finally:
        close_session(session, *reversed(entities))


def _wait_run(
    session: zenoh.Session,
    plan: StackPlan,
    run_dir: Path,
    config: Config,
    watch: RunWatch,
    stack: Stack,
    check: Callable[[], None],
    progress: Callable[[str], None] | None,
    *,
    without_timeout_s: float,
    announce: Callable[[str], None],
) -> None:
    """Every service alive, the outside ones ready, then the run to its end."""
    layout = plan.services
    _wait_alive(session, watch.robots, layout.started, stack, check)
    try:
        wait_for_outside(
            session, watch.robots[0], layout.outside, without_timeout_s, announce,
            still_running=check,
        )  # fmt: skip
    except OutsideMissing as exc:
        raise RunError(str(exc)) from None
    if plan.web is not None:  # the page is up: its URL and token, to the person
        announce(plan.web.announcement())
    lockstep = config.run.mode == "lockstep"
    factor = LOCKSTEP_TIMEOUT_FACTOR if lockstep else REALTIME_TIMEOUT_FACTOR
    deadline_s = config.run.duration_s * factor + RUN_TIMEOUT_SLACK_S
    plants = graph.instances([PLANT], watch.robot_ids)
    _wait_finished(watch, deadline_s, stack, progress, run_dir, plants, check)


def _wait_finished(
    watch: RunWatch,
    deadline_s: float,
    stack: Stack,
    progress: Callable[[str], None] | None,
    run_dir: Path,
    plants: Sequence[str],
    check: Callable[[], None],
) -> None:
    """Wait until every plant (``plants``: one per robot) has finished: its FINISHED
    event, or its summary on file saying so (written as it finishes: an event lost on a
    starved machine does not hang the run). Reports progress meanwhile: sim time from
    the tool pose stream, the task's phase from the operator's events."""
    start = time.monotonic()
    tracker = watch.tracker
    while not watch.finished.wait(timeout=0.5) and not all(
        ended_plant_summary(run_dir, p) is not None for p in plants
    ):
        if time.monotonic() - start > deadline_s:
            raise RunError(f"run did not finish within {deadline_s:g} s: {stack.status()}")
        check()
        sim_s = watch.sim_s()
        if progress is not None and sim_s is not None:
            line = tracker.due(sim_s)
            if line is not None:
                progress(line)
    sim_s = watch.sim_s()
    if progress is not None and sim_s is not None:
        progress(tracker.line(sim_s) + "   finished")


def ended_plant_summary(run_dir: Path, plant: str = PLANT) -> dict[str, Any] | None:
    """``plant``'s summary if it is on file and says the run finished (or ended on a
    failure: aborted); None otherwise."""
    path = summary_path(run_dir, plant)
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(summary, dict):
        return None
    plant_summary = PlantSummary.from_json(summary)
    return summary if plant_summary.finished or plant_summary.aborted else None


def refuse_if_running(run_dir: Path) -> None:
    """Raise RunError when a stack already runs in ``run_dir`` (a `teleop up`, or
    another run): two stacks cannot share a run directory."""
    try:
        Stack.attach(run_dir)
    except StackError:
        return
    raise RunError(
        f"a stack already runs in {run_dir}: stop it (teleop down --run-dir {run_dir}) "
        "or use another --run-dir"
    )


def _foreground_check(foreground: Foreground, check: Callable[[], None]) -> Callable[[], None]:
    """``check``, then whether ``foreground`` still runs (RunError if not)."""

    def both() -> None:
        check()
        try:
            foreground.check()
        except ForegroundExited as exc:
            raise RunError(str(exc)) from None

    return both


def _failure_check(stack: Stack, watch: ProgramWatch | None = None) -> Callable[[], None]:
    """A check that raises :class:`ServiceFailed` (the failure block) as soon as a
    program of ``stack`` has died, crash-looped or stopped (teleop.run.failure);
    ``watch``: the one to use (it may expect restarts: a test's or an injected kill's)."""
    if watch is None:
        watch = ProgramWatch(stack.log_path, _read_log)
    return lambda: watch.check(stack.process_infos())


def _read_log(path: Path) -> str:
    return program_log_text(path, path.parent.parent / SUPERVISOR_LOG_FILE)


def _wait_alive(
    session: zenoh.Session,
    robots: Sequence[Topics],
    services: Sequence[str],
    stack: Stack,
    check: Callable[[], None],
) -> None:
    """Wait up to ALIVE_TIMEOUT_S for every service's ready token (it has its session,
    its subscribers and its links to its peers: supervisord's RUNNING only says the
    process lived a second), checking the programs meanwhile (one that dies or
    crash-loops fails the run at once, not after the time-out). A service still not
    ready then has hung in its start-up: it is killed (it may not answer the stop
    signal) and :class:`ServiceFailed` names it with its log. Under several robots each
    robot's keys hold a ready token of each service (``services``' processes: a per-robot
    service's own, a station service's for every robot)."""
    deadline = time.monotonic() + ALIVE_TIMEOUT_S
    waiting = list(robots)
    roles = graph.services_of(services)
    while True:
        check()
        try:
            while waiting:
                wait_alive(session, waiting[0], roles, ALIVE_POLL_S, ready=True)
                waiting.pop(0)
            return
        except ServicesMissing as exc:
            if time.monotonic() < deadline:
                continue
            robot_id = waiting[0].robot_id
            name = next(
                (n for n in services
                 if graph.role_of(n) == exc.missing[0] and graph.robot_of(n) in (None, robot_id)),
                exc.missing[0],
            )  # fmt: skip
            with contextlib.suppress(StackError, OSError):
                stack.signal_program(name, signal.SIGKILL)
            path = stack.log_path(name)
            raise ServiceFailed(
                name,
                f"did not come alive within {ALIVE_TIMEOUT_S:g} s",
                path,
                _read_log(path),
                startup=True,
            ) from None


def _listen_endpoints(mesh: Mapping[str, Sequence[str]], names: Sequence[str]) -> list[str]:
    """The endpoints ``names`` listen on in a :func:`peer_mesh` (its overrides say)."""
    prefix = "bus.peer_listen_endpoint="
    return [
        json.loads(override.removeprefix(prefix))
        for name in names
        for override in mesh[name]
        if override.startswith(prefix)
    ]


def start_detached(
    config: Config,
    config_file: Path | None,
    overrides: Sequence[str],
    run_dir: Path,
    endpoint: str | None = None,
    *,
    without: Sequence[str] = (),
    without_timeout_s: float = DEFAULT_WITHOUT_TIMEOUT_S,
    announce: Callable[[str], None] = _stderr,
    credentials: dict[str, Path] | None = None,
) -> tuple[dict[str, str], str]:
    """``teleop up``: the stack with the plant as listener on ``endpoint`` (None: a free
    loopback port), running until stopped; the services' states and the endpoint.
    Raises :class:`RunError` if the endpoint is taken, or is not a ``tls/`` one in a
    TLS run (``bus.tls``).

    ``without``: services left out, as in :func:`run_on_services`: once the rest is
    started, wait for their ready tokens (a session of this process linked to each of
    them); if one does not come within ``without_timeout_s``, stop the stack and raise
    RunError.

    One site of a run across hosts (``site.name``, teleop.run.sites): the site's services
    and its router (the listener where the plant runs elsewhere); the robot site writes
    the operator site's bundle (announced), the operator site is given its
    ``credentials`` from it. The plant waits for the other site's services as for its own.
    """
    run_dir = run_dir.absolute()
    refuse_if_running(run_dir)
    layout = _refuse_up(config, endpoint, without)
    clear_run_results(run_dir)  # a previous stack's checkpoint must not be resumed
    # Held until every service listens: then each holds its own.
    with LoopbackPorts() as ports:
        plan = plan_stack(
            Launch.UP, config, config_file, overrides, run_dir, ports, layout,
            endpoint=endpoint, without_timeout_s=without_timeout_s, credentials=credentials,
        )  # fmt: skip
        credentials = plan.credentials
        if config.site.listen and credentials is not None:  # the first robot's site
            bundles = write_site_bundles(run_dir, config, overrides, credentials, layout.scenario)
            for site, bundle in bundles:
                announce(
                    f"{site} site: copy {bundle} to its host (it holds private keys: scp "
                    f"keeps it 0600), then there: teleop up --site {site} --join FILE (its "
                    f"router connects to {config.site.listen})"
                )
        stack = Stack(run_dir, plan.programs)
        stack.start(detach=True)
        for text, _ in plan.joins:
            announce(text)
        watcher = site_observer(config.site.name, config.site.robot)
        observer = credentials[watcher] if credentials is not None else None
        listener = layout.listener(Launch.UP)
        peers = _listen_endpoints(plan.mesh, [n for n in layout.started if n != listener])
        peers += [bus.peer_listen_endpoint for _, bus in plan.joins]
        _await_ready_detached(stack, config, plan.endpoint, peers, layout.started,
                              layout.outside, without_timeout_s, announce, observer)  # fmt: skip
        if plan.web is not None:  # the page is up: its URL and token, to the person
            announce(plan.web.announcement())
        return stack.status(), plan.endpoint


def _refuse_up(config: Config, endpoint: str | None, without: Sequence[str]) -> StackServices:
    """The stack ``teleop up`` starts; RunError or ConfigError for one it does not."""
    if config.run.robots > 1 and not config.site.name:
        raise ConfigError(
            f"run.robots={config.run.robots}: teleop up runs one robot on one host; several "
            "robots run with teleop run grasp --robots N, or a robot site each (--site)"
        )
    try:
        check_site(config)
    except SiteError as exc:
        raise RunError(str(exc)) from None
    if endpoint is not None:
        if config.bus.mutual_tls and not endpoint.startswith("tls/"):
            raise RunError(
                f"endpoint {endpoint}: this run links over mutual TLS (bus.tls), so its "
                "endpoint is tls/HOST:PORT (or --set bus.tls=false for a tcp/ one)"
            )
        ensure_endpoint_free(endpoint)
    layout = StackServices.of(config, without)
    if layout.foreground:
        raise RunError(
            f"run.operator={config.run.operator}: teleop up runs the stack detached, with no "
            f"terminal for it; drive it with teleop run grasp --operator {config.run.operator}"
        )
    return layout


def _await_ready_detached(
    stack: Stack,
    config: Config,
    endpoint: str,
    peers: Sequence[str],
    services: Sequence[str],
    outside: Sequence[str],
    timeout_s: float,
    announce: Callable[[str], None],
    observer: Path | None,
) -> None:
    """``teleop up``: wait for every service's ready token (the stack's, then the outside
    ones' for up to ``timeout_s``) over links of this process's own to each (``peers``:
    their endpoints besides the listener's ``endpoint``; peers do not forward tokens),
    with the run's ``observer`` credentials (None: an open bus), watching the programs
    meanwhile. On a failure (a service that dies, crash-loops, hangs in start-up or does
    not come) the stack is stopped and the error raised: ServiceFailed with the
    service's log, or RunError."""
    watcher = replace(
        config.bus,
        endpoint=endpoint,
        gossip=False,
        peer_listen_endpoint="",
        peer_connect_endpoints=tuple(peers),
        credentials_file=str(observer) if observer is not None else "",
    )
    robots = [Topics(robot_id) for robot_id in config.site_robot_ids()]
    topics = robots[0]
    session = None
    try:
        session = open_session(watcher, listen=False)
        check = _failure_check(stack)
        _wait_alive(session, robots, services, stack, check)
        wait_for_outside(session, topics, outside, timeout_s, announce, still_running=check)
    except (OutsideMissing, RunError) as exc:
        stack.stop()
        raise RunError(f"{exc}; stopped the stack") from None
    except BaseException:
        stack.stop()
        raise
    finally:
        close_session(session)
