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
"""

from __future__ import annotations

import contextlib
import enum
import json
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from teleop.bus import graph
from teleop.bus.access import (
    LAUNCHER,
    OBSERVER,
    OPERATOR_OBSERVER,
    site_observer,
    write_run_credentials,
)
from teleop.bus.messages import PLANT_STATE, DropCounter, Event
from teleop.bus.service import read_summary
from teleop.bus.session import (
    Latest,
    ServicesMissing,
    close_session,
    declare_alive,
    declare_protocol,
    open_session,
    subscribe,
    subscribe_events,
    subscribe_stream,
    wait_alive,
)
from teleop.bus.topics import Topics
from teleop.control.kinematics import build_arm_model, tool_jacobian
from teleop.core.config import (
    INPUT_DEVICE_OPERATORS,
    ROBOT_SITE,
    SCRIPTED,
    TERMINAL_OPERATORS,
    VIEWING_OPERATORS,
    BusConfig,
    Config,
    ConfigError,
    load_config,
)
from teleop.core.criteria import judge_task
from teleop.core.net import LOOPBACK, LoopbackPorts, endpoint_address
from teleop.core.rundir import (
    AUTH_DIR,
    LOG_DIR,
    RECORDING_FILE,
    SUPERVISOR_LOG_FILE,
    clear_run_results,
    idle_poll_status_path,
    summary_path,
)
from teleop.core.summary import CONTROLLER, GRASP, PATH, copied_fields
from teleop.devices.human_loop import PHASES as HUMAN_PHASES
from teleop.devices.operator import Scenario
from teleop.run import restart_priority
from teleop.run.failure import ProgramWatch, ServiceFailed, program_log_text
from teleop.run.faults import (
    FaultInjector,
    FaultSpec,
    InjectorHooks,
    StateLog,
    fault_report,
    parse_faults,
    resumed_index,
    stage_stamps,
    world_reset,
)
from teleop.run.foreground import Foreground, ForegroundExited
from teleop.run.idle_poll import POLLING, read_status
from teleop.run.outside import (
    DEFAULT_WITHOUT_TIMEOUT_S,
    OutsideMissing,
    check_without,
    join_instructions,
    wait_for_outside,
    write_outside_config,
)
from teleop.run.progress import RunProgress
from teleop.run.sites import SiteError, check_site, write_operator_bundle
from teleop.run.supervise import Program, Stack, StackError
from teleop.run.verdict import drop_lines, machine_section, realtime_health, refused_privileges
from teleop.run.web_operator import WebAccess, prepare_web_operator, web_overrides

# The operator's eye view renders in a process of its own (see services/eyeview.py for
# why not a thread in the plant); it joins the stack of any scenario when eyeview.enabled.
EYEVIEW = "eyeview"
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


class RunError(RuntimeError):
    """A services run did not complete; the message says which service and why."""


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
) -> list[Program]:
    """The supervisord programs of ``services``, each given the same config and
    overrides, then its place in the run's ``mesh`` (a :func:`peer_mesh` of the
    services, and of the outside ones too if any) and its ``credentials`` file, if any
    (:func:`run_credentials`); ``restarts``: how a service's restarts start
    (:func:`restart_priorities`); ``modules``: the program of a service that is not
    services/<name>.py (a person's operator)."""
    programs = []
    for name in services:
        role, robot = graph.role_of(name), graph.robot_of(name)
        own = list(mesh[name])
        if robot is not None:  # one robot's instance of a per-robot service
            own.append(f"robot.robot_id={json.dumps(robot)}")
        if credentials is not None:
            own.append(f'bus.credentials_file="{credentials[name]}"')
        module = (f"services.{role}",)
        if name in graph.ROUTERS:
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
    (``site.name``) adds both sites' routers and the operator site's observer: the
    robot site makes every identity once (teleop.run.sites hands the operator site's
    over), its router's certificate valid at ``site.listen``'s address too."""
    if not config.bus.secure:
        return None
    participants = [*participants, OBSERVER]
    addresses: dict[str, list[str]] = {}
    if config.site.name:
        participants += [*graph.ROUTERS, OPERATOR_OBSERVER]
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


def idle_poll_report(cpus: Sequence[int], run_dir: Path) -> dict[str, Any]:
    """After a run: the CPUs whose poller polled, and why the others did not."""
    statuses = {cpu: read_status(idle_poll_status_path(run_dir, cpu)) for cpu in cpus}
    return {
        "idle_poll_cpus": [cpu for cpu, status in statuses.items() if status == POLLING],
        "idle_poll_failed": {cpu: s for cpu, s in statuses.items() if s != POLLING},
    }


def _read_summary(run_dir: Path, service: str) -> dict[str, Any]:
    summary = read_summary(run_dir, service)
    if summary is None:
        path = summary_path(run_dir, service)
        raise RunError(f"{service} wrote no summary ({path}); see {run_dir / LOG_DIR}")
    return summary


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
PLANT = "plant"


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
        router = graph.router_name(site)
        here = graph.on_site(started, site)
        remote = tuple(n for n in scenario if graph.site_of(n) != site)
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
) -> StackPlan:
    """The one launch recipe: the mesh's endpoint (``endpoint``, or a loopback port of
    ``ports``), the run's overrides, credentials for every participant (``credentials``:
    given, as a site's from the other site's launcher), an explicit mesh of the
    services (outside ones included), their programs (and the idle pollers'), and the
    outside services' Zenoh configs and join instructions, all written to ``run_dir``."""
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
    (:func:`robot_view`, :func:`_robot_section`) under ``robots``.
    """
    if config.site.name:
        raise RunError(
            "site.name: a run across hosts starts one site per host with teleop up --site "
            "(docs/sites.md); teleop run keeps the whole stack on this host"
        )
    layout = StackServices.of(config, without)
    services, outside = layout.started, layout.outside
    robot_ids = config.robot_ids()
    if len(robot_ids) > 1 and (kills or freezes):
        raise ConfigError(
            f"--kill and --freeze: not in a run of several robots (run.robots={len(robot_ids)})"
        )
    fault_specs = parse_faults(kills, freezes, services, config.run.duration_s)
    run_dir = run_dir.absolute()
    run_dir.mkdir(parents=True, exist_ok=True)
    refuse_if_running(run_dir)
    clear_run_results(run_dir)
    robots = [Topics(rid) for rid in robot_ids]
    topics = robots[0]
    plants = graph.instances([PLANT], robot_ids)
    drops = DropCounter()
    finished = threading.Event()  # every robot's plant finished
    finished_robots: set[str] = set()
    # Per robot, the operator's TASK_DONE value (1: success), if any.
    task_done: dict[str, list[float]] = {rid: [] for rid in robot_ids}
    tool = Latest()  # the newest tool pose of any robot: the run's sim time

    phases: tuple[str, ...] = ()
    if config.run.teleoperated and config.run.operator != SCRIPTED:
        phases = HUMAN_PHASES  # read from the world (teleop.devices.human_loop)
    elif config.run.teleoperated:
        scenario = Scenario.load(config.operator.scenario_path, config.robot.object_bodies)
        phases = tuple(phase.name for phase in scenario.phases)
    tracker = RunProgress(config.run.duration_s, phases)

    def events_of(robot_id: str) -> Callable[[np.ndarray, int], None]:
        def on_event(rec: np.ndarray, rx_ns: int) -> None:
            if int(rec["event"]) == Event.STARTED and faults is not None:
                faults.on_started(int(rec["t_source_ns"]))
            if int(rec["event"]) in (Event.FINISHED, Event.ABORTED):
                finished_robots.add(robot_id)
                if len(finished_robots) == len(robot_ids):
                    finished.set()
            elif int(rec["event"]) == Event.PHASE:
                tracker.on_phase(int(rec["value"]), int(rec["sim_time_ns"]) * 1e-9)
            elif int(rec["event"]) == Event.TASK_DONE:
                task_done[robot_id].append(float(rec["value"]))

        return on_event

    faults = _FaultRun(config, fault_specs) if fault_specs else None
    # The run's ports stay held here until it ends: a restarted service takes its own again.
    ports = LoopbackPorts()
    session = None
    entities: list[Any] = []
    try:
        plan = plan_stack(
            Launch.RUN, config, config_file, overrides, run_dir, ports, layout,
            without_timeout_s=without_timeout_s,
        )  # fmt: skip
        credentials = plan.credentials
        bus = replace(  # the mesh's listener
            config.bus,
            endpoint=plan.endpoint,
            gossip=False,
            credentials_file=str(credentials[LAUNCHER]) if credentials else "",
        )
        session = open_session(bus, listen=True)
        if faults is not None:
            entities += faults.subscribe(session, topics, drops)
        for robot in robots:
            on_event = events_of(robot.robot_id)
            entities.append(subscribe_events(session, robot, "plant_events", on_event, drops))
            if config.run.teleoperated:  # the operator's TASK_DONE (success or not)
                entities.append(
                    subscribe_events(session, robot, "operator_events", on_event, drops)
                )
            entities.append(
                subscribe_stream(
                    session,
                    robot,
                    "tool_pose",
                    tool,
                    drops,
                    consumer=LAUNCHER,
                    mode=config.run.mode,
                    scenario=config.run.scenario,
                )
            )
            entities.append(declare_protocol(session, robot))
            entities.append(declare_alive(session, robot, LAUNCHER))
            entities.append(declare_alive(session, robot, LAUNCHER, ready=True))
        for text, _ in plan.joins:
            announce(text)
        factor = (
            LOCKSTEP_TIMEOUT_FACTOR if config.run.mode == "lockstep" else REALTIME_TIMEOUT_FACTOR
        )
        deadline_s = config.run.duration_s * factor + RUN_TIMEOUT_SLACK_S
        wall_start = time.perf_counter()
        with contextlib.ExitStack() as running:
            stack = running.enter_context(Stack(run_dir, plan.programs))
            watch = ProgramWatch(stack.log_path, _read_log, frozenset(restarts_expected))
            check = _failure_check(stack, watch)
            if faults is not None:
                check = faults.start(stack, watch, check)
            # Entered last: stopped first, while the stack still runs (its summary then
            # has the run's end).
            for program in plan.foreground:
                check = _foreground_check(running.enter_context(Foreground(program, run_dir)),
                                          check)  # fmt: skip
            try:
                _wait_alive(session, robots, services, stack, check)
                try:
                    wait_for_outside(
                        session, topics, outside, without_timeout_s, announce,
                        still_running=check,
                    )  # fmt: skip
                except OutsideMissing as exc:
                    raise RunError(str(exc)) from None
                if plan.web is not None:  # the page is up: its URL and token, to the person
                    announce(plan.web.announcement())
                _wait_finished(
                    finished, tool, tracker, deadline_s, stack, progress, run_dir, plants, check
                )
            except ServiceFailed as exc:
                # Said now, not after the stop (which can take seconds more).
                announce(f"teleop: the run failed:\n{exc.block()}\nstopping the services...")
                exc.reported = True
                raise
            finally:
                if faults is not None:
                    faults.close()  # nothing left frozen when the stack stops
        wall_s = time.perf_counter() - wall_start
    finally:
        close_session(session, *reversed(entities))
        ports.close()

    # A service killed on purpose whose new incarnation was stopped while still starting
    # has only its killed process's running summary, or none if that one was killed
    # before its first (teleop.bus.service): the run's figures then go without it.
    killed = {spec.service for spec in fault_specs if spec.kind == "kill"}
    read = {name: read_summary(run_dir, name) for name in services}
    summaries = {
        name: summary if summary is not None else _read_summary(run_dir, name)
        for name, summary in read.items()
        if summary is not None or name not in killed
    }
    # A pair of peers that never linked: what one sent the other is lost (Service.become_ready).
    unlinked = {n: s["unlinked_peers"] for n, s in summaries.items() if s.get("unlinked_peers")}
    # The bad records each receiver dropped (restarted services: their earlier
    # processes' too), by kind and reason, and their total.
    dropped_by: dict[str, dict[str, Any]] = {"launcher": drops.by_key()}
    for name, s in summaries.items():
        for incarnation in (*s.get("earlier_incarnations", []), s):
            mine = dropped_by.setdefault(name, {"counts": {}, "first": {}})
            for key, count in (incarnation.get("dropped_by_reason") or {}).items():
                mine["counts"][key] = mine["counts"].get(key, 0) + count
            for key, detail in (incarnation.get("dropped_first") or {}).items():
                mine["first"].setdefault(key, detail)
    dropped = sum(sum(d["counts"].values()) for d in dropped_by.values())
    restarted = {
        name: len(s["earlier_incarnations"])
        for name, s in summaries.items()
        if s.get("earlier_incarnations")
    }
    summary: dict[str, Any] = {
        "scenario": config.run.scenario,
        "mode": config.run.mode,
        "seed": config.run.seed,
    }
    if config.run.teleoperated:
        summary["operator"] = config.run.operator
    sections = {
        rid: _robot_section(config, robot_view(summaries, rid, robot_ids), task_done[rid])
        for rid in robot_ids
    }
    plant_summaries = [summaries.get(name, {}) for name in plants]
    if len(robot_ids) == 1:  # one robot: its section is the run's
        summary.update(sections[robot_ids[0]])
    else:
        summary.update(_robots_verdict(config.run.scenario, sections))
    idle_poll = idle_poll_report(plan.polled_cpus, run_dir)
    machine = machine_section(summaries, plan.polled_cpus, idle_poll)
    # The brakes an injected fault caused are the fault's, not a loss of real time.
    fault_braked = faults.braked_states() if faults is not None else 0
    health = realtime_health(
        config.run.mode,
        overrun_fraction=max(p.get("overrun_fraction", 0.0) for p in plant_summaries),
        realtime_factor=min(p.get("realtime_factor") or 0.0 for p in plant_summaries),
        watchdog_brakes=sum(p.get("stale_commands", 0) for p in plant_summaries)
        - (faults.brakes() if faults else 0),
        braked_steps=max(0, sum(p.get("stale_steps", 0) for p in plant_summaries) - fault_braked),
        steps=sum(p.get("steps", 0) for p in plant_summaries),
        drops=drop_lines(dropped_by),
        unlinked_peers=unlinked,
    )
    summary.update(
        {
            **health.as_dict(),
            "outside": list(outside),
            "summaries_missing": [name for name in services if name not in summaries],
            # Services whose earlier processes wrote a summary (restarted after it).
            "restarted_services": restarted,
            "dropped_messages": dropped,
            "unlinked_peers": unlinked,
            "stack_wall_s": wall_s,
            **idle_poll,
            "machine": machine,
            "refused_privileges": refused_privileges(machine),
            "faults": faults.report(summary.get("success")) if faults is not None else [],
            "run_dir": str(run_dir),
            "services": summaries,
        }
    )
    return summary


def robot_view(
    summaries: Mapping[str, dict[str, Any]], robot_id: str, robot_ids: Sequence[str]
) -> dict[str, dict[str, Any]]:
    """The services' summaries as one robot's run saw them, by service: its own plant,
    controller and eye view (``<service>-<robot_id>`` in a run of several robots), and
    the station's services, whose per-robot figures (a section per robot under
    ``robots``: the operator's task, the recorder's file) are this robot's."""
    view: dict[str, dict[str, Any]] = {}
    for name, summary in summaries.items():
        role, robot = graph.role_of(name), graph.robot_of(name)
        if robot is not None and robot != robot_id:
            continue
        own = summary.get("robots", {}).get(robot_id) if len(robot_ids) > 1 else None
        view[role] = {**summary, **own} if isinstance(own, dict) else summary
    return view


def _robot_section(
    config: Config, view: Mapping[str, dict[str, Any]], task_done: list[float]
) -> dict[str, Any]:
    """One robot's figures, verdict and plant figures, from its services' summaries
    (:func:`robot_view`) and the operator's TASK_DONE values for it."""
    plant, controller = view.get("plant", {}), view.get("controller", {})
    if config.run.teleoperated:
        figures, problems = _grasp_figures(view, task_done)
    else:
        figures = {
            "duration_s": config.run.duration_s,
            **{key: controller.get(key) for key in copied_fields(CONTROLLER, PATH)},
        }
        # A run that stalls or collides is not a good run either (teleop.control.path).
        problems = list(controller.get("motion_problems", []))
        figures["motion_problems"] = problems
    if plant.get("aborted") or plant.get("failure"):
        # The plant ended the run on a failure: whatever the task's figures say, it did
        # not go on to its end.
        problems = [*problems, f"plant: {plant.get('failure') or 'aborted'}"]
    figures["commands_received"] = plant.get("commands_received")
    figures["commands_applied"] = plant.get("commands_applied")
    # The task's criteria (teleop.core.criteria) and the problems: the one verdict, which
    # the summary holds enough to give again (criteria.judge_summary).
    verdict = judge_task(config.run.scenario, figures, problems).summary()
    sim_s = (plant.get("steps") or 0) * config.tick_s
    return {
        **figures,
        **verdict,
        "steps": plant.get("steps"),
        "wall_s": plant.get("wall_s"),
        "realtime_factor": plant.get("realtime_factor"),
        "overrun_fraction": plant.get("overrun_fraction"),
        "commands_clamped": plant.get("commands_clamped"),
        "commands_clamped_by_reason": plant.get("commands_clamped_by_reason"),
        "command_stream": plant.get("command_stream"),
        "stale_commands": plant.get("stale_commands"),
        # The plant's own stops on contact force and tool speed (teleop.sim.protective).
        "protective_stop": plant.get("protective_stop"),
        # The plant ended the run on a failure (its reason), and its restarts.
        "failure": plant.get("failure"),
        "plant_resumes": plant.get("resumes", []),
        "skipped_states": controller.get("skipped_states"),
        "final_state_sha256": plant.get("final_state_sha256"),
        # CPU seconds per simulated second of this robot's own processes (start-up in).
        "cpu_s_per_sim_s": {
            role: round(view[role]["cpu_s"] / sim_s, 4)
            for role in graph.PER_ROBOT
            if role in view and sim_s > 0 and view[role].get("cpu_s") is not None
        },
        "eye_view": _eye_view_summary(view),
        "rrd": view.get("recorder", {}).get("rrd_path"),
    }


def _robots_verdict(scenario: str, sections: Mapping[str, dict[str, Any]]) -> dict[str, Any]:
    """A run of several robots: a section per robot (each judged by itself, its
    ``scenario`` with it so criteria.judge_summary judges it again the same way) and the
    run's verdict: every robot's task succeeded; its problems, each with its robot."""
    return {
        "robots": {rid: {"scenario": scenario, **s} for rid, s in sections.items()},
        "success": all(s.get("success") for s in sections.values()),
        "problems": [f"{rid}: {p}" for rid, s in sections.items() for p in s.get("problems", [])],
        "reasons": [f"{rid}: {r}" for rid, s in sections.items() for r in s.get("reasons", [])],
        "failure": next((s["failure"] for s in sections.values() if s.get("failure")), None),
        "rrd": next((s["rrd"] for s in sections.values() if s.get("rrd")), None),
    }


def _eye_view_summary(summaries: dict[str, dict[str, Any]]) -> dict[str, Any] | None:
    """Frames rendered and received (over SHM), render time, CPU shares, latency."""
    eyeview = summaries.get(EYEVIEW)
    if eyeview is None:
        return None
    recorder = summaries.get("recorder", {})
    received = recorder.get("eye_view", {})
    return {
        "frames_published": eyeview["frames_published"],
        "frames_received": received.get("received"),
        "frames_received_shm": received.get("received_shm"),
        "logged_bytes_per_frame": received.get("logged_bytes_per_frame"),
        "render_ms_p50": eyeview["render_ms_p50"],
        "renderer_cpu_share": eyeview["cpu_share"],
        "recorder_cpu_share": recorder.get("cpu_share"),
        "latency_ms": {k: v for k, v in received.items() if k.endswith("_ms")},
    }


def _grasp_figures(
    summaries: dict[str, dict[str, Any]], task_done: list[float]
) -> tuple[dict[str, Any], list[str]]:
    """The teleoperation task's figures of merit, from the services that measured them
    (an outside service's are None; an outside operator's success is its TASK_DONE's),
    and the problems the run reported: the motion's, and an operator that did not finish."""
    plant, controller = summaries.get("plant", {}), summaries.get("controller", {})
    haptic, operator = summaries.get("haptic", {}), summaries.get("operator")
    said_success = operator.get("success") if operator is not None else task_done[-1:] == [1.0]
    operator = operator or {}
    problems = controller.get("motion_problems", [])
    figures = {
        "motion_problems": problems,
        **{key: controller.get(key) for key in copied_fields(CONTROLLER, GRASP)},
        "object_in_box": plant.get("object_in_box"),
        "object_bin_distance_m": plant.get("object_bin_distance_m"),
        "duration_s": operator.get("task_duration_s"),
        "max_device_force_n": haptic.get("max_rendered_force_n"),
        # The energy the force exchanged with the hand, and what the stabiliser dissipated.
        "passivity": haptic.get("passivity"),
        "max_contact_force_n": plant.get("max_contact_force_n"),
        "obstacle_min_clearance_m": plant.get("obstacle_min_clearance_m"),
        "tool_speed_max_m_s": plant.get("tool_speed_max_m_s"),
        "velocity_tracking_rms_m_s": controller.get("velocity_tracking_rms_m_s"),
        "stale_feedback_events": haptic.get("stale_feedback_events"),
        "max_obstacle_force_n": controller.get("max_obstacle_force_n"),
        "held_weight_n": controller.get("held_weight_n"),
        "phases": operator.get("phases"),
        "operator_failure": operator.get("failure") or None,  # why the operator gave up
    }
    gave_up = f": {figures['operator_failure']}" if figures["operator_failure"] else ""
    said = [] if said_success else [f"the operator did not finish the task{gave_up}"]
    return figures, [*problems, *said]


def _wait_finished(
    finished: threading.Event,
    tool: Latest,
    tracker: RunProgress,
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
    the tool pose stream, the task's phase from the operator's events (``tracker``)."""
    start = time.monotonic()
    sim_s = 0.0
    while not finished.wait(timeout=0.5) and not all(_plant_finished(run_dir, p) for p in plants):
        if time.monotonic() - start > deadline_s:
            raise RunError(f"run did not finish within {deadline_s:g} s: {stack.status()}")
        check()
        latest = tool.get()
        if progress is not None and latest is not None:
            sim_s = int(latest[0]["sim_time_ns"]) * 1e-9
            line = tracker.due(sim_s)
            if line is not None:
                progress(line)
    latest = tool.get()
    if progress is not None and latest is not None:
        progress(tracker.line(int(latest[0]["sim_time_ns"]) * 1e-9) + "   finished")


def _plant_finished(run_dir: Path, plant: str = PLANT) -> bool:
    """True when ``plant``'s summary is on file and says the run finished (or ended on
    a failure: aborted)."""
    path = summary_path(run_dir, plant)
    try:
        summary = json.loads(path.read_text())
        return bool(summary.get("finished") or summary.get("aborted"))
    except (OSError, ValueError):
        return False


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


class _FaultRun:
    """The bus side of fault injection in a run (teleop.run.faults): the plant's states
    recorded and fed to the injector, ready tokens watched for restarts, the run failed
    when a killed plant starts the world over, and the summary's ``faults``."""

    def __init__(self, config: Config, specs: Sequence[FaultSpec]) -> None:
        self.specs = specs
        self.realtime = config.run.mode == "realtime"
        self.arm = build_arm_model(config.robot)  # tool speed from joint state
        self.states = StateLog(self.arm.n_joints)
        self.injector: FaultInjector | None = None
        self._started_ns = 0  # the plant's STARTED stamp, if it came before start()

    def subscribe(self, session: zenoh.Session, topics: Topics, drops: DropCounter) -> list[Any]:
        """The plant's states (the observers' batched copy) and every ready token."""

        def on_state(rec: np.ndarray, rx_ns: int) -> None:
            self.states.add(rec)
            if self.injector is not None:
                self.injector.on_state(int(rec["sim_time_ns"]), int(rec["step"]))

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
        )
        self.injector = FaultInjector(self.specs, hooks, realtime=self.realtime)
        if self._started_ns:
            self.injector.on_started(self._started_ns)
        self.injector.start()

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
        self._started_ns = self._started_ns or t_ns
        if self.injector is not None:
            self.injector.on_started(t_ns)

    def close(self) -> None:
        if self.injector is not None:
            self.injector.close()

    def _speed_at(self, arrays: dict[str, np.ndarray]) -> Callable[[int], float]:
        def speed_at(i: int) -> float:
            jacobian = tool_jacobian(self.arm, arrays["q_rad"][i])
            return float(np.linalg.norm(jacobian[:3] @ arrays["qd_rad_s"][i]))

        return speed_at

    def report(self, success: bool | None) -> list[dict[str, Any]]:
        """The summary's ``faults``: one object per fault (teleop.run.faults)."""
        if self.injector is None:
            return [{"service": s.service, "kind": s.kind, "error": "not injected"}
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
            name = graph.instance_name(exc.missing[0], robot_id, len(robots))
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
    if config.run.robots > 1:
        raise ConfigError(
            f"run.robots={config.run.robots}: teleop up runs one robot; several robots run "
            "with teleop run grasp --robots N"
        )
    run_dir = run_dir.absolute()
    refuse_if_running(run_dir)
    clear_run_results(run_dir)  # a previous stack's checkpoint must not be resumed
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
    # Held until every service listens: then each holds its own.
    with LoopbackPorts() as ports:
        plan = plan_stack(
            Launch.UP, config, config_file, overrides, run_dir, ports, layout,
            endpoint=endpoint, without_timeout_s=without_timeout_s, credentials=credentials,
        )  # fmt: skip
        credentials = plan.credentials
        if config.site.name == ROBOT_SITE and credentials is not None:
            bundle = write_operator_bundle(run_dir, config, overrides, credentials, layout.scenario)
            announce(
                f"operator site: copy {bundle} to the operator's host (it holds private "
                f"keys: scp keeps it 0600), then there: teleop up --site operator --join "
                f"FILE (its router connects to {config.site.listen})"
            )
        stack = Stack(run_dir, plan.programs)
        stack.start(detach=True)
        for text, _ in plan.joins:
            announce(text)
        watcher = site_observer(config.site.name)
        observer = credentials[watcher] if credentials is not None else None
        listener = layout.listener(Launch.UP)
        peers = _listen_endpoints(plan.mesh, [n for n in layout.started if n != listener])
        peers += [bus.peer_listen_endpoint for _, bus in plan.joins]
        _await_ready_detached(stack, config, plan.endpoint, peers, layout.started,
                              layout.outside, without_timeout_s, announce, observer)  # fmt: skip
        if plan.web is not None:  # the page is up: its URL and token, to the person
            announce(plan.web.announcement())
        return stack.status(), plan.endpoint


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
    topics = Topics(config.robot.robot_id)
    session = None
    try:
        session = open_session(watcher, listen=False)
        check = _failure_check(stack)
        _wait_alive(session, [topics], services, stack, check)
        wait_for_outside(session, topics, outside, timeout_s, announce, still_running=check)
    except (OutsideMissing, RunError) as exc:
        stack.stop()
        raise RunError(f"{exc}; stopped the stack") from None
    except BaseException:
        stack.stop()
        raise
    finally:
        close_session(session)
