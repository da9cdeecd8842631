"""The ``teleop`` command: a thin shell over the library.

    teleop run path-following --inprocess --duration 60 --seed 0 --summary-json out.json
    teleop run path-following --mode lockstep --duration 20 --rrd out.rrd
    teleop run grasp --mode realtime --seed 0 --rrd out.rrd --summary-json out.json
    teleop up | status | down        (a long-running stack, realtime by default)
    teleop run path-following --mode lockstep --without controller   (bring your own)
    teleop latency --duration 60 --json out.json --png out.png
    teleop run grasp --web | --spawn (watch the run in the web / native Rerun viewer)
    teleop view out.rrd [--web]      (open a saved recording)
    teleop report out.rrd            (the paper's figures as PNG, and a markdown summary)
    teleop sweep path-following --paths 50 --seed 0   (random reachable tasks, success rate)
    teleop sweep grasp --scenes 50 --seed 0

Every command reads the typed config (``--config``, default ``deploy/teleop.toml``)
and applies ``--set dotted.key=value`` overrides; flags such as ``--duration`` are
shorthands for the matching ``--set``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from teleop.core.config import (
    AUTONOMOUS,
    INPUT_DEVICE_OPERATORS,
    OPERATOR_SITE,
    OPERATORS,
    ROBOT_SITE,
    SCENARIOS,
    SCRIPTED,
    SITES,
    TERMINAL_OPERATORS,
    Config,
    ConfigError,
    ModelError,
    load_config,
    scenario_spec,
)
from teleop.core.rundir import (
    LATENCY_RECORDING_FILE,
    LOG_DIR,
    RUN_SUMMARY_FILE,
    WEB_VIEWER_LOG_FILE,
)
from teleop.run.failure import ServiceFailed
from teleop.run.supervise import interrupt_on_signals
from teleop.run.verdict import LOST

if TYPE_CHECKING:
    from teleop.viz.viewer import WebViewer

DEFAULT_RUN_DIR = Path("runs") / "latest"
DEFAULT_UP_DIR = Path("runs") / "up"
DEFAULT_LATENCY_DIR = Path("runs") / "latency"
DEFAULT_LATENCY_DURATION_S = 60.0
# teleop latency --across-sites: one-way delays between the routers (ms), and its report.
DEFAULT_SITE_DELAYS_MS = (12.5, 25.0, 50.0, 100.0)
SITES_REPORT_FILE = "sites.json"
DEFAULT_SWEEP_DIR = Path("runs") / "sweep"

# How long `--without` waits for the services left out (s); teleop.run.outside's default
# (not imported from there: this module stays light until a command runs).
DEFAULT_WITHOUT_TIMEOUT_S = 120.0

# Exit codes: 0 success, 1 the run failed its own checks, 2 bad usage or config, 3 the
# task succeeded but the run lost real time (realtime_verdict "lost": its figures are not
# those of a realtime run; teleop.run.verdict).
EXIT_FAILED = 1
EXIT_USAGE = 2
# A person's run (--operator other than scripted) lasts this long by default (simulated s).
HUMAN_RUN_DURATION_S = 300.0
EXIT_REALTIME_LOST = 3


def _add_config_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help="TOML config file (default: deploy/teleop.toml of this checkout)",
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set control.compensation=false (repeatable)",
    )


def _add_without_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--without",
        action="append",
        default=[],
        metavar="SERVICE",
        help="leave SERVICE out of the stack and run your own in its place (repeatable): "
        "the rest starts, the command prints what yours must do to join (endpoints, "
        "robot id, tokens, streams, and the Zenoh config file to open its session with: "
        "<run-dir>/outside/SERVICE.json5) and waits for it; see docs/protocol.md and "
        "examples/",
    )
    parser.add_argument(
        "--without-timeout",
        type=float,
        default=DEFAULT_WITHOUT_TIMEOUT_S,
        metavar="SECONDS",
        help="how long to wait for the services left out to join (default: %(default)g)",
    )


def _add_web_port_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--web-port", type=int, default=None, help="HTTP port of the web viewer (default: free)"
    )
    parser.add_argument("--grpc-port", type=int, default=None, help="its gRPC port (default: free)")


# The group of subcommands build_parser adds each command to.
Commands = argparse._SubParsersAction


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="teleop",
        description="zenoh-teleop: real-time simulator for teleoperated and autonomous robot arms.",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_run_command(commands)
    _add_latency_command(commands)
    _add_view_command(commands)
    _add_report_command(commands)
    _add_sweep_command(commands)
    _add_up_command(commands)
    _add_stack_state_commands(commands)
    return parser


def _add_run_command(commands: Commands) -> None:
    run = commands.add_parser(
        "run",
        help="run a scenario and print its summary",
        description=(
            "Run a scenario. --inprocess couples plant and controller in one process "
            "(no bus); otherwise the services run as separate processes under supervisord."
        ),
    )
    run.add_argument("scenario", choices=SCENARIOS, help="what to run")
    _add_run_timing_arguments(run)
    _add_run_output_arguments(run)
    _add_run_station_arguments(run)
    _add_without_arguments(run)
    _add_run_fault_arguments(run)
    run.add_argument(
        "--report",
        action="store_true",
        help="after the run, write the figures and summary (see `teleop report`)",
    )
    _add_config_arguments(run)


def _add_run_timing_arguments(run: argparse.ArgumentParser) -> None:
    """teleop run: in one process or as services, which timing, how long, which seed, how
    many robots."""
    where = run.add_mutually_exclusive_group()
    where.add_argument(
        "--inprocess", action="store_true", help="plant and controller in one process, no bus"
    )
    where.add_argument(
        "--mode",
        choices=("lockstep", "realtime"),
        default="realtime",
        help="services timing: realtime keeps wall-clock time; lockstep is deterministic "
        "and as fast as the machine allows (default: realtime)",
    )
    run.add_argument("--duration", type=float, help="simulated seconds (run.duration_s)")
    run.add_argument("--seed", type=int, help="random seed (run.seed)")
    run.add_argument(
        "--robots",
        type=int,
        help="robots on the bus (run.robots, default 1): each its own plant and controller "
        "under its own id (arm0, arm1, ...), one operator station driving them in turn, one "
        "recording per robot, a summary section per robot; grasp in lockstep with the "
        "scripted operator (docs/sites.md, Several robots). Without --duration the run "
        "gets run.duration_s per robot",
    )


def _add_run_output_arguments(run: argparse.ArgumentParser) -> None:
    """teleop run: where its summary, recording and logs go, and what it prints."""
    run.add_argument(
        "--summary-json",
        type=Path,
        help="write the full summary (JSON) here (default: <run-dir>/summary.json)",
    )
    run.add_argument(
        "--json", action="store_true", help="print the full summary (JSON) instead of the short one"
    )
    run.add_argument("--rrd", type=Path, help="Rerun recording to write (services runs)")
    run.add_argument(
        "--run-dir",
        type=Path,
        default=DEFAULT_RUN_DIR,
        help=f"logs and supervisord files of a services run (default: {DEFAULT_RUN_DIR})",
    )
    run.add_argument("--quiet", action="store_true", help="no progress lines on stderr")


def _add_run_station_arguments(run: argparse.ArgumentParser) -> None:
    """teleop run: who drives the handle, and which Rerun viewer watches the run."""
    run.add_argument(
        "--operator",
        choices=OPERATORS,
        help="who drives the handle in teleoperation (run.operator): the scripted operator "
        "(default), or a person: at this terminal's keyboard (keys on screen; works over "
        "ssh -t and in tmux), on a gamepad or a SpaceMouse (Linux input; see "
        "docs/operators.md). A person's run lasts up to 300 s simulated unless --duration "
        "says otherwise",
    )
    viewers = run.add_mutually_exclusive_group()
    viewers.add_argument(
        "--spawn", action="store_true", help="also stream the run to the native Rerun viewer"
    )
    viewers.add_argument(
        "--web",
        action="store_true",
        help="also serve the run in the Rerun web viewer on a loopback port (address "
        "printed); it keeps serving after the run until Ctrl-C",
    )
    _add_web_port_arguments(run)


def _add_run_fault_arguments(run: argparse.ArgumentParser) -> None:
    """teleop run: the faults it injects into its services (docs/faults.md)."""
    run.add_argument(
        "--kill",
        action="append",
        default=[],
        metavar="SERVICE@T",
        help="inject a fault: SIGKILL SERVICE when the plant's sim time reaches T seconds "
        "(supervisord restarts it; repeatable). The summary's `faults` says how fast the "
        "arm braked, the service came back and control resumed; see docs/faults.md",
    )
    run.add_argument(
        "--freeze",
        action="append",
        default=[],
        metavar="SERVICE@T:SECONDS",
        help="inject a fault: SIGSTOP SERVICE at sim time T, SIGCONT SECONDS (wall clock) "
        "later (repeatable)",
    )


def _add_latency_command(commands: Commands) -> None:
    latency = commands.add_parser(
        "latency",
        help="measure the bilateral loop's latency, hop by hop, against the transport floor",
        description=(
            "Run the realtime teleoperation stack (every service and the recorder, the "
            "scripted operator moving) for --duration seconds and report the round trip "
            "(haptic sample -> force rendered) and every hop, against baselines measured in "
            "the same command: a bare Zenoh relay chain with the same legs (paced at 1 kHz "
            "and back to back), the stack with shared memory off, a payload sweep with "
            "shared memory on and off, and the stack with the loop's old timing. With "
            "--across-sites: the round trip between the loop's two ends split across two "
            "sites on this host, directly and through both sites' routers (mutual TLS), "
            "then through a network emulator between the routers per --delays-ms "
            "(docs/sites.md)."
        ),
    )
    _add_latency_stack_arguments(latency)
    _add_latency_sites_arguments(latency)
    latency.add_argument(
        "--run-dir",
        type=Path,
        default=DEFAULT_LATENCY_DIR,
        help=f"logs, summaries and raw stamps of every run (default: {DEFAULT_LATENCY_DIR})",
    )
    _add_config_arguments(latency)


def _add_latency_stack_arguments(latency: argparse.ArgumentParser) -> None:
    """teleop latency: how long the stack and its baselines run, and where the report, its
    figure and its recording go."""
    latency.add_argument(
        "--duration",
        type=float,
        default=None,
        help=f"seconds of the stack run (default: {DEFAULT_LATENCY_DURATION_S:g})",
    )
    latency.add_argument(
        "--baseline-duration",
        type=float,
        default=None,
        help="seconds of each baseline run (paced floor, SHM-off stack, old timing); "
        "default: the duration, at most 20",
    )
    latency.add_argument("--json", type=Path, help="write the report here")
    latency.add_argument("--png", type=Path, help="write the histograms figure here")
    latency.add_argument(
        "--rrd", type=Path, help="Rerun recording of the figures (default: <run-dir>/latency.rrd)"
    )
    latency.add_argument(
        "--sweep-count", type=int, default=None, help="round trips per payload size (default 200)"
    )
    latency.add_argument(
        "--no-old-timing",
        action="store_true",
        help="skip the comparison run with the plant's tick and the device step",
    )


def _add_latency_sites_arguments(latency: argparse.ArgumentParser) -> None:
    """teleop latency --across-sites: the round trip between two sites' routers, the
    delays emulated between them, and how many samples."""
    latency.add_argument(
        "--across-sites",
        action="store_true",
        help="measure the round trip across two sites' routers instead of the stack's loop",
    )
    latency.add_argument(
        "--with-stack",
        action="store_true",
        help="--across-sites: then the realtime grasp split across two sites on this host "
        "(teleop up --site robot and --site operator): its loop's round trip on the operator "
        "site's clock and each way from the clocks' offset estimated from the loop's stamps",
    )
    latency.add_argument(
        "--delays-ms",
        type=_delays_ms,
        default=None,
        help="--across-sites: one-way delays between the routers, comma separated "
        f"(default: {','.join(f'{d:g}' for d in DEFAULT_SITE_DELAYS_MS)})",
    )
    latency.add_argument(
        "--pings",
        type=int,
        default=2000,
        help="--across-sites: samples per path, at 1 kHz (default: 2000)",
    )
    latency.add_argument(
        "--rounds",
        type=int,
        default=3,
        help="--across-sites: alternating rounds of the direct and routed paths (default: 3)",
    )


def _add_view_command(commands: Commands) -> None:
    view = commands.add_parser(
        "view",
        help="open a saved recording in the Rerun viewer",
        description="Open a .rrd in the native Rerun viewer, or serve it in the web viewer.",
    )
    view.add_argument("rrd", type=Path, help="the recording (.rrd)")
    view.add_argument(
        "--web",
        action="store_true",
        help="serve the web viewer on a loopback port and print its address (Ctrl-C stops)",
    )
    _add_web_port_arguments(view)


def _add_report_command(commands: Commands) -> None:
    report = commands.add_parser(
        "report",
        help="write the paper's figures (PNG) and a markdown summary of a recording",
        description=(
            "Read a .rrd back and write the paper's figures as PNG files and report.md "
            "into <stem>_report/ next to it (or --out); a recording of several robots, "
            "one report per robot in <stem>_report/<robot id>/. With the run's summary (the "
            "summary.json beside the recording, or --summary) the report opens with the "
            "run's verdict, judged by the same criteria as teleop run and teleop sweep."
        ),
    )
    report.add_argument("rrd", type=Path, help="the recording (.rrd)")
    report.add_argument("--out", type=Path, help="output directory (default: <stem>_report/)")
    report.add_argument(
        "--summary",
        type=Path,
        help="the run's summary.json (default: the one beside the recording, if any)",
    )
    report.add_argument(
        "--settle-s",
        type=float,
        default=None,
        help="path error statistics start this many seconds into the run "
        "(default: run.settle_s of the config)",
    )


def _add_sweep_command(commands: Commands) -> None:
    sweep = commands.add_parser(
        "sweep",
        help="run many random reachable tasks and report the success rate",
        description=(
            "Draw random tasks that the arm can reach (inverse kinematics within the joint "
            "limits, away from singularities, clear of the table and the bin), run them on "
            "every core and judge each: path following (in process) succeeds with path "
            "error RMS <= 1 mm and max <= 3 mm after settling, path_progress >= 0.95 and "
            "no unintended contact; grasp (lockstep services) with the cube in the bin, "
            "no unintended contact and device force below its 8 N peak. A figure the "
            "build does not report makes its criterion 'unavailable' and the task not a "
            "success. Writes "
            "sweep.json (every task's figures and command line, success rate, failures by "
            "reason) and sweep.md (a table) into --out. Exit code 0 when every task "
            "succeeded, 1 otherwise."
        ),
    )
    sweep.add_argument("kind", choices=SCENARIOS, help="what to sweep")
    sweep.add_argument(
        "--paths", type=int, default=None, help="number of random paths (path-following)"
    )
    sweep.add_argument("--scenes", type=int, default=None, help="number of random scenes (grasp)")
    sweep.add_argument(
        "--seed", type=int, default=0, help="seed of the task generator (default: 0)"
    )
    sweep.add_argument(
        "--workers",
        type=int,
        default=None,
        help="worker processes (default: one per core)",
    )
    sweep.add_argument(
        "--out",
        type=Path,
        default=None,
        help=f"report directory (default: {DEFAULT_SWEEP_DIR}/KIND)",
    )
    sweep.add_argument(
        "--list",
        action="store_true",
        help="print the tasks' command lines and stop (nothing runs)",
    )
    sweep.add_argument(
        "--keep-recordings",
        action="store_true",
        help="grasp: keep each run's Rerun recording (about 50 MB each)",
    )
    _add_config_arguments(sweep)


def _add_up_command(commands: Commands) -> None:
    up = commands.add_parser(
        "up",
        help="start the services under supervisord and leave them running",
        description=(
            "Start plant, controller and recorder under a detached supervisord. The plant "
            "listens on a free loopback port (printed; --endpoint to choose it) and runs "
            "path following until `teleop down`; the recorder writes "
            "<run-dir>/recording.rrd (add --set recorder.spawn=true for a live viewer). "
            "Every service gets this run's credentials (<run-dir>/auth, bus.secure): no "
            "other process or stack can join its bus."
        ),
    )
    up.add_argument(
        "--mode",
        choices=("lockstep", "realtime"),
        help="(default: realtime; --site operator: the robot site's, from its bundle)",
    )
    up.add_argument(
        "--endpoint",
        help="the bus's listening endpoint, e.g. tls/127.0.0.1:7447 (default: a free port); "
        "refused if taken; tcp/127.0.0.1:PORT with --set bus.tls=false",
    )
    up.add_argument("--run-dir", type=Path, default=DEFAULT_UP_DIR, help="(default: %(default)s)")
    _add_up_site_arguments(up)
    up.add_argument(
        "--operator",
        choices=OPERATORS,
        help="who drives the handle of a teleoperated stack (--set 'run.scenario=\"grasp\"'): "
        "the scripted operator (default), a gamepad, a SpaceMouse or the web page (its URL "
        "printed); the keyboard needs teleop run (docs/operators.md)",
    )
    _add_without_arguments(up)
    _add_config_arguments(up)


def _add_up_site_arguments(up: argparse.ArgumentParser) -> None:
    """teleop up: one site of a run across hosts, and how its router links to the others
    (docs/sites.md)."""
    up.add_argument(
        "--site",
        choices=SITES,
        help="start one site of a run across hosts (docs/sites.md): robot (plant, "
        "controller, recorder, eye view) or operator (haptic device, HMD, operator), each "
        "with a Zenoh router that links to the robot site's over mutual TLS; a run of "
        "several robots (--set run.robots=N) has a robot site per robot",
    )
    up.add_argument(
        "--site-listen",
        metavar="tls/ADDRESS:PORT",
        help="--site robot: where its router listens for the other sites' (an address "
        "of this host the others reach); writes <run-dir>/operator-site.json (and "
        "robot-site-<robot>.json per other robot) to hand over",
    )
    up.add_argument(
        "--join",
        type=Path,
        metavar="FILE",
        help="--site operator: the robot site's operator-site.json; --site robot: the "
        "robot-site-<robot>.json it wrote for another robot's site of a run of several "
        "(identities and the run's settings; keep it private)",
    )
    up.add_argument(
        "--connect",
        metavar="tls/ADDRESS:PORT",
        help="with --join: the first robot's site's router (default: the bundle's)",
    )


def _add_stack_state_commands(commands: Commands) -> None:
    for name, text in (
        ("status", "show the state of each service started by `teleop up`"),
        ("down", "stop everything `teleop up` started"),
    ):
        sub = commands.add_parser(name, help=text, description=text)
        sub.add_argument(
            "--run-dir", type=Path, default=DEFAULT_UP_DIR, help="(default: %(default)s)"
        )


def _overrides(args: argparse.Namespace) -> list[str]:
    """The user's --set list, with the shorthand flags turned into their --set form."""
    overrides = list(args.overrides)
    if getattr(args, "duration", None) is not None:
        overrides.append(f"run.duration_s={args.duration}")
    if getattr(args, "seed", None) is not None:
        overrides.append(f"run.seed={args.seed}")
    if getattr(args, "robots", None) is not None:
        overrides.append(f"run.robots={args.robots}")
    return overrides


def _emit_summary(summary: dict[str, object], path: Path, as_json: bool) -> None:
    """The full summary to ``path``; on stdout the short one for a person (or, with
    ``as_json``, the full JSON)."""
    from teleop.core.summary import summary_text, write_run_summary
    from teleop.run.progress import human_summary

    if as_json:
        print(summary_text(summary), end="")
    else:
        print("\n".join(human_summary(summary, str(path))))
    if path is not None:
        write_run_summary(path, summary)


def _print_line(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _summary_path(args: argparse.Namespace) -> Path:
    summary_json: Path | None = args.summary_json
    return summary_json if summary_json is not None else args.run_dir / RUN_SUMMARY_FILE


def _run(args: argparse.Namespace) -> int:
    overrides = [*_overrides(args), f'run.scenario="{args.scenario}"']
    if args.inprocess:
        if scenario_spec(args.scenario).teleoperated:
            autonomous = ", ".join(AUTONOMOUS)
            raise ConfigError(
                f"--inprocess runs autonomous scenarios only ({autonomous}), not {args.scenario}"
            )
        if args.rrd is not None:
            raise ConfigError("--rrd needs the services run (drop --inprocess)")
    else:
        overrides.append(f'run.mode="{args.mode}"')
        if args.operator is not None:
            overrides.append(f'run.operator="{args.operator}"')
            if args.operator != SCRIPTED and args.duration is None:
                # A person takes longer than the script: give the run room by default.
                overrides.insert(0, f"run.duration_s={HUMAN_RUN_DURATION_S}")
        if args.rrd is not None:
            overrides.append(f'recorder.rrd_path="{args.rrd.absolute()}"')
        if args.spawn:
            overrides.append("recorder.spawn=true")
    if args.inprocess and (
        args.spawn or args.web or args.report or args.without or args.kill or args.freeze
    ):
        raise ConfigError(
            "--spawn, --web, --report, --without, --kill and --freeze need the services "
            "run (drop --inprocess)"
        )
    config = load_config(args.config, overrides)
    if config.run.robots > 1 and args.duration is None:
        # The operator does one robot's task after the other: each gets the usual time.
        overrides.insert(0, f"run.duration_s={config.run.duration_s * config.run.robots}")
        config = load_config(args.config, overrides)
    check_operator(config, args.without)
    # A failed run must not leave the previous run's summary looking like its own.
    _summary_path(args).unlink(missing_ok=True)
    web = None
    if args.web:
        from teleop.viz.viewer import serve_web

        args.run_dir.mkdir(parents=True, exist_ok=True)
        web = serve_web(
            web_port=args.web_port,
            grpc_port=args.grpc_port,
            log_path=args.run_dir / WEB_VIEWER_LOG_FILE,
        )
        overrides.append(f'recorder.grpc_url="{web.grpc_url}"')
        config = load_config(args.config, overrides)
        print(f"web viewer: {web.url}", file=sys.stderr, flush=True)
    try:
        return _run_and_report(args, config, overrides, web)
    finally:
        if web is not None:
            web.stop()


def check_operator(config: Config, without: Sequence[str] = ()) -> None:
    """ConfigError (exit 2, one line) for a person's operator (``run.operator``) this run
    cannot have: no teleoperation, the operator left out, or no terminal for the keys."""
    device = config.run.operator
    if device == SCRIPTED:
        return
    if not config.run.teleoperated:
        raise ConfigError(
            f"--operator {device}: {config.run.scenario} is not teleoperated (no operator to "
            "replace); teleoperated: grasp (run.scenario)"
        )
    if "operator" in without:
        raise ConfigError(f"--operator {device} and --without operator: choose one")
    if device == "keyboard" and not (sys.stdin.isatty() and sys.stdout.isatty()):
        raise ConfigError(
            "keyboard: standard input or output is not a terminal, so no key can be read: "
            "run teleop in a terminal (ssh -t for a remote one, or tmux)"
        )
    if device in INPUT_DEVICE_OPERATORS:  # there, and this user may read it
        from teleop.devices.person.input_devices import DeviceUnavailable, open_input_device

        try:
            open_input_device(device, config).close()
        except DeviceUnavailable as exc:
            raise ConfigError(str(exc)) from None


def _run_and_report(
    args: argparse.Namespace, config: Config, overrides: list[str], web: WebViewer | None
) -> int:
    from teleop.run import experiments

    where = "in process" if args.inprocess else f"on services, {config.run.mode}"
    length = f"{config.run.duration_s:g} s simulated"
    if config.run.teleoperated:
        length = f"until the operator is done (at most {config.run.duration_s:g} s simulated)"
    print(f"{args.scenario} {where}, seed {config.run.seed}: {length}", file=sys.stderr)
    if args.inprocess:
        progress = None if args.quiet else experiments.print_progress
        summary = experiments.run_path_following_inprocess(config, progress=progress)
    else:
        from teleop.run.stack import RunError, run_on_services

        print(f"  logs and summaries in {args.run_dir}", file=sys.stderr)
        try:
            summary = run_on_services(
                config,
                args.config,
                overrides,
                args.run_dir,
                # A person at this terminal's keyboard has the screen: no progress lines.
                None if args.quiet or config.run.operator in TERMINAL_OPERATORS else _print_line,
                without=args.without,
                without_timeout_s=args.without_timeout,
                kills=args.kill,
                freezes=args.freeze,
            )
        except RunError as exc:
            print(f"teleop: {exc}", file=sys.stderr)
            return EXIT_FAILED
    _emit_summary(summary, _summary_path(args), args.json)
    if args.report:
        from teleop.viz.report import write_reports

        if summary.get("rrd"):  # one report per robot, each with its section's verdict
            for report in write_reports(
                Path(str(summary["rrd"])), settle_s=config.run.settle_s, run_summary=summary
            ):
                print(f"report: {report.summary}", file=sys.stderr)
    if web is not None:
        print(f"web viewer: {web.url} (Ctrl-C to stop)", file=sys.stderr, flush=True)
        # This Ctrl-C ends the viewer, not the run: the exit code stays the run's.
        with contextlib.suppress(KeyboardInterrupt):
            web.wait()
    if summary.get("failure"):
        print(f"teleop: the plant ended the run: {summary['failure']}", file=sys.stderr)
        return EXIT_FAILED
    if summary.get("success") is False:
        print("teleop: the task did not succeed", file=sys.stderr)
        for problem in summary.get("motion_problems") or []:
            print(f"  {problem}", file=sys.stderr)
        return EXIT_FAILED
    if summary.get("realtime_verdict") == LOST:
        print("teleop: the run lost real time (see realtime_problems)", file=sys.stderr)
        return EXIT_REALTIME_LOST
    return 0


def _delays_ms(text: str) -> list[float]:
    """``--delays-ms``: comma-separated one-way delays (ms), each >= 0."""
    try:
        delays = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of numbers: {text!r}") from None
    if any(not math.isfinite(d) or d < 0 for d in delays):
        raise argparse.ArgumentTypeError(f"delays must be finite and >= 0 ms: {text!r}")
    return delays


def _latency_across_sites(args: argparse.Namespace) -> int:
    from teleop.bench import sites

    stack_only = {
        "--duration": args.duration, "--baseline-duration": args.baseline_duration,
        "--png": args.png, "--rrd": args.rrd, "--sweep-count": args.sweep_count,
    }  # fmt: skip
    given = [name for name, value in stack_only.items() if value is not None]
    given += ["--no-old-timing"] if args.no_old_timing else []
    if given:
        dropped = ", ".join(given)
        raise ConfigError(f"--across-sites takes none of the one-host stack run's: drop {dropped}")
    if args.pings < 1 or args.rounds < 1:
        raise ConfigError("--pings and --rounds: at least 1")
    if args.config is not None:
        raise ConfigError("--across-sites: no --config (the sites take --set values)")
    delays = DEFAULT_SITE_DELAYS_MS if args.delays_ms is None else args.delays_ms
    print(
        f"latency across sites: {args.rounds} rounds direct and through the routers, then "
        f"{len(delays)} delays, {args.pings} samples each",
        file=sys.stderr,
    )

    def to_stderr(line: str) -> None:
        print(line, file=sys.stderr)

    report = sites.measure(args.pings, 1000.0, args.rounds, delays, progress=to_stderr)
    if args.with_stack:
        stack = sites.measure_stack(args.run_dir / "stack", args.overrides, progress=to_stderr)
        report = dataclasses.replace(report, stack=stack)
    json_path = args.json if args.json is not None else args.run_dir / SITES_REPORT_FILE
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(report.to_json(), indent=2) + "\n")
    print("\n".join(sites.table(report)))
    if report.stack is not None:
        floor = report.routers_floor_ms()
        print("\n" + "\n".join(sites.stack_table(report.stack, floor)))
    print(f"report: {json_path}")
    return 0 if report.clean else 1


def _latency(args: argparse.Namespace) -> int:
    from teleop.bench import latency, loop_stats

    if args.across_sites:
        return _latency_across_sites(args)
    if args.delays_ms is not None or args.with_stack:
        raise ConfigError("--delays-ms and --with-stack: with --across-sites only")
    if args.duration is None:
        args.duration = DEFAULT_LATENCY_DURATION_S
    if args.duration <= loop_stats.WARMUP_S:
        raise ConfigError(f"--duration must exceed the {loop_stats.WARMUP_S:g} s warm-up")
    latency.config_of(args.config, args.overrides)  # bad --set values fail here, exit 2
    kwargs = {}
    if args.sweep_count is not None:
        kwargs["sweep_count"] = args.sweep_count
    print(f"latency: {args.duration:g} s stack run plus baselines", file=sys.stderr)
    print(f"  logs, summaries and raw stamps in {args.run_dir}", file=sys.stderr)
    report, raw = latency.measure(
        args.config,
        args.overrides,
        args.run_dir,
        args.duration,
        baseline_s=args.baseline_duration,
        old_timing=not args.no_old_timing,
        progress=latency.print_progress,
        **kwargs,
    )
    rrd = args.rrd if args.rrd is not None else args.run_dir / LATENCY_RECORDING_FILE
    latency.log_to_rerun(report, raw, rrd)
    report = dataclasses.replace(report, rrd=str(rrd))
    if args.png is not None:
        latency.write_png(report, raw, args.png)
    if args.json is not None:
        latency.write_json(report, args.json)
    for line in report.conclusions:
        print(line)
    return 0


def _view(args: argparse.Namespace) -> int:
    from teleop.viz import viewer

    if not args.rrd.is_file():
        raise FileNotFoundError(f"no recording {args.rrd}")
    if not args.web:
        return viewer.open_native(args.rrd)
    with viewer.serve_web(args.rrd, web_port=args.web_port, grpc_port=args.grpc_port) as web:
        print(f"web viewer: {web.url} (Ctrl-C to stop)", flush=True)
        return web.wait()


def _report(args: argparse.Namespace) -> int:
    from teleop.core.summary import SummaryError, read_run_summary
    from teleop.viz.report import write_reports
    from teleop.viz.rrd import NotARecording

    settle_s = args.settle_s if args.settle_s is not None else load_config().run.settle_s
    try:
        run_summary = read_run_summary(args.summary) if args.summary is not None else None
        reports = write_reports(args.rrd, args.out, settle_s=settle_s, run_summary=run_summary)
    except (NotARecording, SummaryError) as exc:
        print(f"teleop: {exc}", file=sys.stderr)
        return EXIT_USAGE
    for report in reports:
        for figure in report.figures:
            print(figure)
        print(report.summary)
    return 0


def _sweep(args: argparse.Namespace) -> int:
    from teleop.run import sweep

    tasks = sweep.kind_of(args.kind).tasks
    count_flag = f"--{tasks}"
    count = getattr(args, tasks)
    if any(getattr(args, k.tasks) is not None for k in sweep.SWEEP_KINDS if k.tasks != tasks):
        raise ConfigError(f"sweep {args.kind}: the number of tasks is {count_flag}")
    if count is None or count < 1:
        raise ConfigError(f"sweep {args.kind}: {count_flag} N (N >= 1) is required")
    if args.workers is not None and args.workers < 1:
        raise ConfigError("--workers must be >= 1")
    config_file = str(args.config) if args.config is not None else None
    load_config(config_file, args.overrides)  # bad --set values fail here, exit 2
    if args.list:
        generated = sweep.generate(args.kind, count, args.seed, config_file, args.overrides)
        for task in generated.tasks:
            print(task.command(args.overrides, config_file))
        return 0
    out = args.out if args.out is not None else DEFAULT_SWEEP_DIR / args.kind
    report = sweep.run_sweep(
        args.kind,
        count,
        args.seed,
        out,
        config_file=config_file,
        overrides=args.overrides,
        workers=args.workers,
        keep_recordings=args.keep_recordings,
    )
    rate = report["success_rate"]
    print(f"{args.kind}: {report['successes']}/{report['tasks']} succeeded ({rate:.0%})")
    if report["failures_by_reason"]:
        print(f"  failures by reason: {report['failures_by_reason']}")
    if report["criteria_unavailable"]:
        print(f"  not measured by this build: {', '.join(report['criteria_unavailable'])}")
    print(f"  report: {out / sweep.REPORT_MARKDOWN}, {out / sweep.REPORT_JSON}")
    return 0 if report["successes"] == report["tasks"] else EXIT_FAILED


def _site_overrides(args: argparse.Namespace) -> tuple[list[str], dict[str, Path] | None]:
    """``teleop up``'s site options as overrides (a joining site's from its bundle
    first), and a joining site's credentials; SiteError on a bad combination. The first
    robot's site listens (``--site-listen``) and makes every identity; the operator site
    and, in a run of several robots, each other robot's site join with the bundle it
    wrote for them."""
    from teleop.run.sites import SiteError, join_site

    if args.site is None:
        if args.site_listen or args.join or args.connect:
            raise SiteError("--site-listen, --join and --connect go with --site")
        return [], None
    if args.site_listen and (args.join or args.site == OPERATOR_SITE):
        raise SiteError("--site-listen is the first robot's site's: a site that joins connects")
    if args.join is None:
        if args.site == OPERATOR_SITE:
            raise SiteError(
                "--site operator needs --join FILE: the robot site's operator-site.json"
            )
        if args.connect:
            raise SiteError("--connect goes with --join (a site that joins the first robot's)")
        listen = [f"site.listen={json.dumps(args.site_listen)}"] if args.site_listen else []
        return [f'site.name="{ROBOT_SITE}"', *listen], None
    joined = join_site(args.site, args.join, args.run_dir)
    connect = args.connect or joined.connect
    site = [f'site.name="{args.site}"', f"site.connect={json.dumps(connect)}"]
    return [*joined.overrides, *site], joined.credentials


def _up(args: argparse.Namespace) -> int:
    from teleop.run.sites import SiteError, check_site, robot_bundle_file
    from teleop.run.stack import RunError, start_detached

    try:
        site_overrides, credentials = _site_overrides(args)
    except SiteError as exc:
        print(f"teleop: {exc}", file=sys.stderr)
        return EXIT_USAGE
    mode = args.mode or ("" if credentials is not None else "realtime")
    overrides = [*site_overrides, *args.overrides, *([f'run.mode="{mode}"'] if mode else [])]
    if args.operator is not None:
        overrides.append(f'run.operator="{args.operator}"')
    config = load_config(args.config, overrides)
    if config.run.operator in TERMINAL_OPERATORS:
        raise ConfigError(
            f"--operator {config.run.operator}: teleop up runs the stack detached, with no "
            f"terminal for the keys; drive it with teleop run grasp --operator "
            f"{config.run.operator}"
        )
    check_operator(config, args.without)
    try:
        check_site(config)
        if config.site.robot and credentials is None:  # its identities are the hub's
            raise SiteError(
                f"the site of robot {config.site.robot} joins the first robot's: --join "
                f"{robot_bundle_file(config.site.robot)} (the first robot's site wrote it)"
            )
    except SiteError as exc:
        print(f"teleop: {exc}", file=sys.stderr)
        return EXIT_USAGE
    try:
        status, endpoint = start_detached(
            config,
            args.config,
            overrides,
            args.run_dir,
            args.endpoint,
            without=args.without,
            without_timeout_s=args.without_timeout,
            credentials=credentials,
        )
    except RunError as exc:
        print(f"teleop: {exc}", file=sys.stderr)
        return EXIT_FAILED
    for name, state in status.items():
        print(f"{name:12s} {state}")
    print(f"bus: {endpoint}   logs: {args.run_dir / LOG_DIR}   stop: teleop down")
    return 0


def _status(args: argparse.Namespace) -> int:
    from teleop.run.supervise import Stack, StackError

    try:
        status = Stack.attach(args.run_dir).status()
    except StackError as exc:
        print(f"teleop: nothing running in {args.run_dir}: {exc}", file=sys.stderr)
        return EXIT_FAILED
    for name, state in status.items():
        print(f"{name:12s} {state}")
    for line in _site_link_lines(args.run_dir, status):
        print(line)
    return 0 if all(state == "RUNNING" for state in status.values()) else EXIT_FAILED


def _site_link_lines(run_dir: Path, status: dict[str, str]) -> list[str]:
    """One site of a run across hosts: whether its router sees the other site, from the
    router's running summary (written every 2 s)."""
    from teleop.bus.graph import is_router
    from teleop.core.rundir import incarnation_paths

    lines = []
    running = [name for name, state in status.items() if state == "RUNNING"]
    for router in filter(is_router, running):
        paths = incarnation_paths(run_dir, router)
        try:
            summary = json.loads(paths[-1].read_text()) if paths else None
        except (OSError, ValueError):
            summary = None
        if summary is None:
            lines.append(f"{router}: no summary yet")
            continue
        linked = "linked" if summary.get("other_site_linked") else "NOT linked"
        lines.append(
            f"{router}: the other site is {linked} (links {summary.get('other_site_links')}, "
            f"losses {summary.get('other_site_losses')}; as of its summary, every 2 s)"
        )
    return lines


def _down(args: argparse.Namespace) -> int:
    from teleop.run.supervise import Stack, StackError

    try:
        Stack.attach(args.run_dir).stop()
    except StackError as exc:
        print(f"teleop: nothing running in {args.run_dir}: {exc}", file=sys.stderr)
        return EXIT_FAILED
    print(f"stopped the stack in {args.run_dir}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``teleop`` console script."""
    os.environ.setdefault("RERUN_ANALYTICS", "0")
    args = build_parser().parse_args(argv)
    try:
        handler = {
            "run": _run,
            "latency": _latency,
            "view": _view,
            "report": _report,
            "sweep": _sweep,
            "up": _up,
            "status": _status,
            "down": _down,
        }[args.command]
        # SIGINT and SIGTERM raise KeyboardInterrupt from the start, so every command's
        # clean-up runs (servers, stacks) whatever this process inherited: a background
        # job starts with SIGINT ignored, and SIGTERM would end it without unwinding.
        with interrupt_on_signals():
            return handler(args)
    except (ConfigError, ModelError, FileNotFoundError) as exc:
        print(f"teleop: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except ServiceFailed as exc:
        if not exc.reported:
            print(f"teleop: the run failed:\n{exc.block()}", file=sys.stderr)
        return EXIT_FAILED
    except RuntimeError as exc:  # the stack's and the runner's errors: the message says why
        if type(exc).__module__.partition(".")[0] != "teleop":
            raise
        print(f"teleop: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        print("teleop: interrupted", file=sys.stderr)
        return 130
    return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
