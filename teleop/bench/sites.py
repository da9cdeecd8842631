"""The round trip across two sites (``teleop latency --across-sites``): what the sites'
routers add on one host, and the round trip through the network emulator between the
routers, per one-way delay (docs/sites.md).

Two processes play the bilateral loop's two ends with a run's settings (mutual TLS, the
run's certificates and access list, shared memory, the low-latency transport): the
haptic end sends a sample at ``rate_hz`` and times each answer, the controller end
answers each one at once. Paths, the first two in alternating rounds:

- ``direct``: the two ends linked to each other (one host, one site: the floor);
- ``routers``: each end a peer of its own site's router (each router a process of its
  own, :func:`teleop.bus.session.router_config`), the routers linked over TLS;
- ``routers + D ms``: the same, the routers' link through :mod:`teleop.bench.netem`
  with a one-way delay of D ms, compared with the floor plus twice D.

The ends are bare sessions, not the services: the figures are the transport's and the
routers', the floor under any stack split across the sites (``teleop latency`` without
``--across-sites`` measures the stack's own loop on one host).
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from teleop.bench.latency import across_clocks
from teleop.bench.netem import LinkImpairment, running_proxy
from teleop.bench.ping import paced_round_trips_ms
from teleop.bus import graph
from teleop.bus import session as bus
from teleop.bus.access import write_run_credentials
from teleop.bus.topics import Topics
from teleop.core import markdown
from teleop.core.config import OPERATOR_SITE, ROBOT_SITE, BusConfig, SiteConfig
from teleop.core.net import free_loopback_port
from teleop.core.rundir import HAPTIC_TRACE_FILE
from teleop.run.sites import OPERATOR_BUNDLE_FILE
from teleop.run.stack import ended_plant_summary

ROBOT = "sites"  # the robot id of the measurement's keys (no run shares them)
ROBOT_ROUTER, OPERATOR_ROUTER = graph.router_name(ROBOT_SITE), graph.router_name(OPERATOR_SITE)
PARTICIPANTS = ["haptic", "controller", ROBOT_ROUTER, OPERATOR_ROUTER]
DIRECT, ROUTERS = "direct", "routers"
# A process of the measurement that does not stop within this long is killed (s).
STOP_TIMEOUT_S = 10.0


def _endpoint() -> str:
    return f"tls/127.0.0.1:{free_loopback_port()}"


def _bus(files: dict[str, Path], name: str, endpoint: str, own: str = "") -> BusConfig:
    return dataclasses.replace(
        BusConfig(endpoint=endpoint),
        gossip=False,
        peer_listen_endpoint=own,
        credentials_file=str(files[name]),
    )


def _router(bus_config: BusConfig, site: SiteConfig, listen: bool, stop: Any) -> None:
    """A site's router until ``stop`` (a multiprocessing Event) is set."""
    session = zenoh.open(bus.router_config(bus_config, site, listen=listen))
    stop.wait()
    session.close()


def _answerer(bus_config: BusConfig, listen: bool, stop: Any) -> None:
    """The controller's end: every sample straight back, until ``stop`` is set."""
    topics = Topics(ROBOT)
    session = bus.open_session(bus_config, listen=listen)
    back = session.declare_publisher(topics.force_feedback, express=True)
    sub = session.declare_subscriber(
        topics.haptic_state, lambda sample: back.put(sample.payload.to_bytes())
    )
    stop.wait()
    sub.undeclare()
    back.undeclare()
    session.close()


@contextlib.contextmanager
def _processes(*targets: tuple) -> Iterator[None]:
    """Each ``(function, *args)`` in a process of its own until the block ends."""
    ctx = multiprocessing.get_context("spawn")
    stop = ctx.Event()
    procs = [ctx.Process(target=fn, args=(*args, stop), daemon=True) for fn, *args in targets]
    for proc in procs:
        proc.start()
    try:
        yield
    finally:
        stop.set()
        for proc in procs:
            proc.join(timeout=STOP_TIMEOUT_S)
            if proc.is_alive():
                proc.kill()


def _round_trips_ms(bus_config: BusConfig, pings: int, rate_hz: float) -> np.ndarray:
    """Samples from the haptic end, paced at ``rate_hz``; their round trips (ms)."""
    topics = Topics(ROBOT)
    session = bus.open_session(bus_config, listen=False)
    try:
        return paced_round_trips_ms(
            session, topics.haptic_state, topics.force_feedback, pings, rate_hz
        )
    finally:
        session.close()


def round_trips_ms(
    files: dict[str, Path], path: str, pings: int, rate_hz: float, delay_ms: float | None = None
) -> np.ndarray:
    """The round trips (ms) of ``pings`` samples on ``path`` (:data:`DIRECT` or
    :data:`ROUTERS`; with ``delay_ms``, the routers' link delayed that much each way)."""
    if path == DIRECT:
        endpoint = _endpoint()
        with _processes((_answerer, _bus(files, "controller", endpoint), True)):
            return _round_trips_ms(_bus(files, "haptic", endpoint, _endpoint()), pings, rate_hz)
    robot_mesh, operator_mesh, site = _endpoint(), _endpoint(), _endpoint()
    site_port = int(site.rpartition(":")[2])
    with contextlib.ExitStack() as stack:
        connect = site
        if delay_ms is not None:
            link = LinkImpairment(delay_s=delay_ms / 1e3)
            proxy = stack.enter_context(running_proxy(("127.0.0.1", site_port), link))
            connect = f"tls/127.0.0.1:{proxy.port}"
        stack.enter_context(
            _processes(
                (_answerer, _bus(files, "controller", robot_mesh), True),
                (
                    _router,
                    _bus(files, ROBOT_ROUTER, robot_mesh, _endpoint()),
                    SiteConfig(ROBOT_SITE, listen=site),
                    False,
                ),
                (
                    _router,
                    _bus(files, OPERATOR_ROUTER, operator_mesh),
                    SiteConfig(OPERATOR_SITE, connect=connect),
                    True,
                ),
            )  # fmt: skip
        )
        return _round_trips_ms(_bus(files, "haptic", operator_mesh, _endpoint()), pings, rate_hz)


def stats(trips_ms: np.ndarray) -> dict[str, float]:
    """How many came back, their p50 and p99 (ms)."""
    return {
        "received": int(trips_ms.size),
        "p50_ms": float(np.median(trips_ms)) if trips_ms.size else float("nan"),
        "p99_ms": float(np.percentile(trips_ms, 99)) if trips_ms.size else float("nan"),
    }


def measure(
    pings: int,
    rate_hz: float,
    rounds: int,
    delays_ms: Sequence[float],
    progress: Callable[[str], None] = lambda line: None,
) -> dict[str, Any]:
    """Direct and through the routers in ``rounds`` alternating rounds, then through the
    routers with each one-way delay of ``delays_ms``; the report (JSON-ready), each path's
    line also given to ``progress`` as it is measured."""
    report: dict[str, Any] = {
        "load_average_start": list(os.getloadavg()),
        "pings": pings,
        "rate_hz": rate_hz,
        "rounds": [],
        "delays": [],
    }
    with tempfile.TemporaryDirectory(prefix="teleop-sites-") as tmp:
        files = write_run_credentials(Path(tmp), PARTICIPANTS, (ROBOT,), tls=True)
        for index in range(rounds):
            order = [DIRECT, ROUTERS] if index % 2 == 0 else [ROUTERS, DIRECT]
            entry = {path: stats(round_trips_ms(files, path, pings, rate_hz)) for path in order}
            for path in order:
                progress(f"round {index + 1} {path}: {_line(entry[path])}")
            report["rounds"].append(entry)
        for key in ("p50_ms", "p99_ms"):
            ratios = [r[ROUTERS][key] / r[DIRECT][key] for r in report["rounds"]]
            report[f"routers_over_direct_{key[:3]}"] = float(np.median(ratios)) if ratios else None
        floor_p50 = float(np.median([r[DIRECT]["p50_ms"] for r in report["rounds"]] or [0.0]))
        for delay_ms in delays_ms:
            entry = stats(round_trips_ms(files, ROUTERS, pings, rate_hz, delay_ms))
            entry |= {
                "delay_ms": delay_ms,
                "p50_over_floor_plus_2_delays": entry["p50_ms"] / (floor_p50 + 2 * delay_ms),
            }
            progress(f"routers + {delay_ms:g} ms each way: {_line(entry)}")
            report["delays"].append(entry)
    report["load_average_end"] = list(os.getloadavg())
    report["lost"] = sum(
        pings - e["received"]
        for e in [*report["delays"], *(v for r in report["rounds"] for v in r.values())]
    )
    return report


def _line(entry: dict[str, float]) -> str:
    return f"p50 {entry['p50_ms']:.3f} ms, p99 {entry['p99_ms']:.3f} ms, {entry['received']} back"


def table(report: dict[str, Any]) -> list[str]:
    """The report as Markdown lines: a row per path (medians over the rounds)."""
    lines = [
        f"Round trip across two sites on this host: {report['pings']} samples per path at "
        f"{report['rate_hz']:g} Hz, load average {report['load_average_start'][0]:.2f} before",
        "",
    ]
    rows = []
    for path in (DIRECT, ROUTERS):
        runs = [r[path] for r in report["rounds"]]
        if runs:
            p50 = float(np.median([r["p50_ms"] for r in runs]))
            p99 = float(np.median([r["p99_ms"] for r in runs]))
            rows.append((path, "0 ms", f"{p50:.3f} ms", f"{p99:.3f} ms", ""))
    rows += [
        ("routers + netem", f"{e['delay_ms']:g} ms", f"{e['p50_ms']:.2f} ms",
         f"{e['p99_ms']:.2f} ms", f"{e['p50_over_floor_plus_2_delays']:.2f}")
        for e in report["delays"]
    ]  # fmt: skip
    header = ("path", "one-way delay", "round trip p50", "p99", "p50 / (floor + 2 x delay)")
    lines += markdown.table(header, rows, "lrrrr")
    if report.get("routers_over_direct_p50") is not None:
        lines += [
            "",
            f"routers / direct, median over rounds: p50 {report['routers_over_direct_p50']:.2f}, "
            f"p99 {report['routers_over_direct_p99']:.2f}",
        ]
    if report["lost"]:
        lines.append(f"{report['lost']} samples never came back")
    return lines


# -- the stack's own loop across the two sites -------------------------------------------

# The realtime grasp split across the sites: its plant's end is waited for this long (s).
STACK_RUN_TIMEOUT_S = 300.0
STACK_SETTINGS = ('run.scenario="grasp"', "run.seed=0")


def _teleop(args: Sequence[str], timeout_s: float) -> subprocess.CompletedProcess[str]:
    """``teleop ARGS`` in a process of its own; a failure raises, saying why."""
    done = subprocess.run(
        [sys.executable, "-m", "teleop.cli", *args],
        capture_output=True, text=True, timeout=timeout_s, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    if done.returncode != 0:
        raise RuntimeError(f"teleop {' '.join(args[:3])}: {(done.stderr or done.stdout)[-1500:]}")
    return done


def wait_plant_end(run_dir: Path, timeout_s: float, plant: str = graph.PLANT) -> dict[str, Any]:
    """The summary of ``plant`` (an instance in a run of several robots: ``plant-arm1``)
    once it says the run finished or aborted (polled each second; the launcher's own
    wait, without a bus session)."""
    deadline = time.monotonic() + timeout_s
    while (summary := ended_plant_summary(run_dir, plant)) is None:
        if time.monotonic() > deadline:
            raise RuntimeError(f"the plant did not finish within {timeout_s:g} s ({run_dir})")
        time.sleep(1.0)
    return summary


def measure_stack(
    run_dir: Path, settings: Sequence[str] = (), progress: Callable[[str], None] = print
) -> dict[str, Any]:
    """The realtime grasp (seed 0) split across two sites on this host (``teleop up
    --site robot`` and ``--site operator``, their routers over mutual TLS on loopback),
    each site on its own clock as far as the stack knows: the loop's round trip on the
    operator site's clock, each way across from the clocks' offset estimated from the
    loop's stamps (:func:`teleop.bench.latency.across_clocks`), and the run's outcome.
    ``settings``: more ``--set`` values for both sites."""
    robot_dir, operator_dir = run_dir / "robot", run_dir / "operator"
    listen = f"tls/127.0.0.1:{free_loopback_port()}"
    sets = [item for value in (*STACK_SETTINGS, *settings) for item in ("--set", value)]
    started: list[Path] = []
    try:
        progress(f"the realtime grasp across two sites: robot site in {robot_dir}")
        _teleop(["up", "--mode", "realtime", "--site", "robot", "--site-listen", listen,
                 "--run-dir", str(robot_dir), *sets], STACK_RUN_TIMEOUT_S)  # fmt: skip
        started.append(robot_dir)
        progress(f"operator site in {operator_dir}")
        _teleop(["up", "--site", "operator", "--join", str(robot_dir / OPERATOR_BUNDLE_FILE),
                 "--run-dir", str(operator_dir)], STACK_RUN_TIMEOUT_S)  # fmt: skip
        started.append(operator_dir)
        plant = wait_plant_end(robot_dir, STACK_RUN_TIMEOUT_S)
    finally:
        for site_dir in reversed(started):
            subprocess.run([sys.executable, "-m", "teleop.cli", "down", "--run-dir",
                            str(site_dir)], capture_output=True, timeout=120)  # fmt: skip
    loop = across_clocks(np.load(operator_dir / HAPTIC_TRACE_FILE))
    return {
        "success": bool(plant.get("object_in_box")) and bool(plant.get("finished")),
        "failure": plant.get("failure"),
        "realtime_factor": plant.get("realtime_factor"),
        "braked_steps": plant.get("stale_steps"),
        "steps": plant.get("steps"),
        **loop.to_json(),
    }


def stack_table(stack: dict[str, Any], floor_routers_ms: dict[str, float] | None) -> list[str]:
    """The stack's loop across the sites as Markdown lines, beside the routers' floor."""
    if not stack.get("loops"):
        return ["the stack across the sites closed no loop"]

    def ms(figures: dict[str, Any], key: str) -> str:
        return f"{figures[key] / 1e3:.2f} ms"

    rows = [
        ("round trip (operator site's clock)", ms(stack["round_trip_us"], "p50"),
         ms(stack["round_trip_us"], "p99")),
        ("operator site -> robot site", ms(stack["operator_to_robot_us"], "p50"),
         ms(stack["operator_to_robot_us"], "p99")),
        ("robot site (controller, plant, controller)", ms(stack["robot_site_us"], "p50"),
         ms(stack["robot_site_us"], "p99")),
        ("robot site -> operator site", ms(stack["robot_to_operator_us"], "p50"),
         ms(stack["robot_to_operator_us"], "p99")),
    ]  # fmt: skip
    if floor_routers_ms is not None:
        rows.append(("floor: bare ends through the routers", f"{floor_routers_ms['p50_ms']:.2f} ms",
                     f"{floor_routers_ms['p99_ms']:.2f} ms"))  # fmt: skip
    lines = [
        f"The realtime grasp across two sites: {'success' if stack['success'] else 'failed'}, "
        f"realtime factor {stack['realtime_factor']:.3f}, {stack['braked_steps']} of "
        f"{stack['steps']} steps braked; {stack['loops']} loops",
        "",
        *markdown.table(("path", "p50", "p99"), rows, "lrr"),
        "",
        f"clocks' offset (robot minus operator site) {stack['offset_s']:+.6f} s, +- "
        f"{stack['offset_uncertainty_us'] / 1e3:.2f} ms (each way within that)",
    ]
    return lines
