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
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from teleop.bench.loop_stats import AcrossClocks, LatencyStats, across_clocks
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
from teleop.core.service_summaries import PlantSummary
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


@dataclass(frozen=True)
class PathTrips:
    """One path's round trips: how many samples came back, their p50 and p99 (ms; NaN if
    none came back). Through the emulator: its one-way ``delay_ms`` and the p50 over the
    floor (the direct path's median p50) plus twice the delay; None on the other paths."""

    received: int
    p50_ms: float
    p99_ms: float
    delay_ms: float | None = None
    p50_over_floor_plus_2_delays: float | None = None

    def to_json(self) -> dict[str, float]:
        return {
            f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None
        }

    @classmethod
    def from_json(cls, content: Mapping[str, float]) -> PathTrips:
        return cls(
            received=int(content["received"]),
            p50_ms=content["p50_ms"],
            p99_ms=content["p99_ms"],
            delay_ms=content.get("delay_ms"),
            p50_over_floor_plus_2_delays=content.get("p50_over_floor_plus_2_delays"),
        )

    @property
    def line(self) -> str:
        """The figures in one line of progress."""
        return f"p50 {self.p50_ms:.3f} ms, p99 {self.p99_ms:.3f} ms, {self.received} back"


def stats(trips_ms: np.ndarray) -> PathTrips:
    """How many came back, their p50 and p99 (ms)."""
    return PathTrips(
        received=int(trips_ms.size),
        p50_ms=float(np.median(trips_ms)) if trips_ms.size else float("nan"),
        p99_ms=float(np.percentile(trips_ms, 99)) if trips_ms.size else float("nan"),
    )


@dataclass(frozen=True)
class SitesReport:
    """The ``teleop latency --across-sites`` report (:func:`measure`): each round's
    paths (by path, in the order measured), each delay through the emulator, the
    routers' median ratios to the direct path (None without a round), the samples that
    never came back, the load average (1, 5, 15 min) before and after, and with
    ``--with-stack`` the realtime grasp across the sites (:func:`measure_stack`)."""

    load_average_start: tuple[float, ...]
    pings: int
    rate_hz: float
    rounds: tuple[Mapping[str, PathTrips], ...]
    delays: tuple[PathTrips, ...]
    routers_over_direct_p50: float | None
    routers_over_direct_p99: float | None
    load_average_end: tuple[float, ...]
    lost: int
    stack: StackAcrossSites | None = None

    def routers_floor_ms(self) -> dict[str, float] | None:
        """The bare ends' round trip through the routers, medians over the rounds
        (``p50_ms``, ``p99_ms``); None without a round."""
        routers = [r[ROUTERS] for r in self.rounds if ROUTERS in r]
        if not routers:
            return None
        return {
            key: float(np.median([getattr(trips, key) for trips in routers]))
            for key in ("p50_ms", "p99_ms")
        }

    @property
    def clean(self) -> bool:
        """Every sample came back, and the stack (if run) succeeded and closed loops."""
        stack_ok = self.stack is None or (self.stack.success and self.stack.loop.loops > 0)
        return not self.lost and stack_ok

    def to_json(self) -> dict[str, Any]:
        stack = {} if self.stack is None else {"stack": self.stack.to_json()}
        return {
            "load_average_start": list(self.load_average_start),
            "pings": self.pings,
            "rate_hz": self.rate_hz,
            "rounds": [{path: t.to_json() for path, t in r.items()} for r in self.rounds],
            "delays": [trips.to_json() for trips in self.delays],
            "routers_over_direct_p50": self.routers_over_direct_p50,
            "routers_over_direct_p99": self.routers_over_direct_p99,
            "load_average_end": list(self.load_average_end),
            "lost": self.lost,
            **stack,
        }

    @classmethod
    def from_json(cls, content: Mapping[str, Any]) -> SitesReport:
        """The record of a report as :meth:`to_json` writes it."""
        return cls(
            load_average_start=tuple(content["load_average_start"]),
            pings=content["pings"],
            rate_hz=content["rate_hz"],
            rounds=tuple(
                {path: PathTrips.from_json(t) for path, t in r.items()} for r in content["rounds"]
            ),
            delays=tuple(PathTrips.from_json(t) for t in content["delays"]),
            routers_over_direct_p50=content.get("routers_over_direct_p50"),
            routers_over_direct_p99=content.get("routers_over_direct_p99"),
            load_average_end=tuple(content["load_average_end"]),
            lost=content["lost"],
            stack=StackAcrossSites.from_json(content["stack"]) if "stack" in content else None,
        )


def measure(
    pings: int,
    rate_hz: float,
    rounds: int,
    delays_ms: Sequence[float],
    progress: Callable[[str], None] = lambda line: None,
) -> SitesReport:
    """Direct and through the routers in ``rounds`` alternating rounds, then through the
    routers with each one-way delay of ``delays_ms``; the report, each path's line also
    given to ``progress`` as it is measured."""
    load_average_start = os.getloadavg()
    measured: list[dict[str, PathTrips]] = []
    delayed: list[PathTrips] = []
    with tempfile.TemporaryDirectory(prefix="teleop-sites-") as tmp:
        files = write_run_credentials(Path(tmp), PARTICIPANTS, (ROBOT,), tls=True)
        for index in range(rounds):
            order = [DIRECT, ROUTERS] if index % 2 == 0 else [ROUTERS, DIRECT]
            entry = {path: stats(round_trips_ms(files, path, pings, rate_hz)) for path in order}
            for path in order:
                progress(f"round {index + 1} {path}: {entry[path].line}")
            measured.append(entry)
        ratios = {
            key: [getattr(r[ROUTERS], key) / getattr(r[DIRECT], key) for r in measured]
            for key in ("p50_ms", "p99_ms")
        }
        over_direct = {k: float(np.median(v)) if v else None for k, v in ratios.items()}
        floor_p50 = float(np.median([r[DIRECT].p50_ms for r in measured] or [0.0]))
        for delay_ms in delays_ms:
            trips = stats(round_trips_ms(files, ROUTERS, pings, rate_hz, delay_ms))
            trips = dataclasses.replace(
                trips,
                delay_ms=delay_ms,
                p50_over_floor_plus_2_delays=trips.p50_ms / (floor_p50 + 2 * delay_ms),
            )
            progress(f"routers + {delay_ms:g} ms each way: {trips.line}")
            delayed.append(trips)
    every = [*delayed, *(trips for r in measured for trips in r.values())]
    return SitesReport(
        load_average_start=load_average_start,
        pings=pings,
        rate_hz=rate_hz,
        rounds=tuple(measured),
        delays=tuple(delayed),
        routers_over_direct_p50=over_direct["p50_ms"],
        routers_over_direct_p99=over_direct["p99_ms"],
        load_average_end=os.getloadavg(),
        lost=sum(pings - trips.received for trips in every),
    )


def table(report: SitesReport) -> list[str]:
    """The report as Markdown lines: a row per path (medians over the rounds)."""
    lines = [
        f"Round trip across two sites on this host: {report.pings} samples per path at "
        f"{report.rate_hz:g} Hz, load average {report.load_average_start[0]:.2f} before",
        "",
    ]
    rows = []
    for path in (DIRECT, ROUTERS):
        runs = [r[path] for r in report.rounds]
        if runs:
            p50 = float(np.median([r.p50_ms for r in runs]))
            p99 = float(np.median([r.p99_ms for r in runs]))
            rows.append((path, "0 ms", f"{p50:.3f} ms", f"{p99:.3f} ms", ""))
    rows += [
        ("routers + netem", f"{e.delay_ms:g} ms", f"{e.p50_ms:.2f} ms",
         f"{e.p99_ms:.2f} ms", f"{e.p50_over_floor_plus_2_delays:.2f}")
        for e in report.delays
    ]  # fmt: skip
    header = ("path", "one-way delay", "round trip p50", "p99", "p50 / (floor + 2 x delay)")
    lines += markdown.table(header, rows, "lrrrr")
    if report.routers_over_direct_p50 is not None:
        lines += [
            "",
            f"routers / direct, median over rounds: p50 {report.routers_over_direct_p50:.2f}, "
            f"p99 {report.routers_over_direct_p99:.2f}",
        ]
    if report.lost:
        lines.append(f"{report.lost} samples never came back")
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


@dataclass(frozen=True)
class StackAcrossSites:
    """The realtime grasp split across two sites (:func:`measure_stack`): its
    outcome as the plant's summary gives it (``braked_steps``: the plant's steps braked by
    the watchdog) and the loop on the two clocks."""

    success: bool
    failure: str | None
    realtime_factor: float | None
    braked_steps: int | None
    steps: int | None
    loop: AcrossClocks

    def to_json(self) -> dict[str, Any]:
        """The JSON object: the outcome, then the loop's figures at the same level."""
        outcome = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "loop"}
        return outcome | self.loop.to_json()

    @classmethod
    def from_json(cls, content: Mapping[str, Any]) -> StackAcrossSites:
        return cls(
            success=content["success"],
            failure=content.get("failure"),
            realtime_factor=content.get("realtime_factor"),
            braked_steps=content.get("braked_steps"),
            steps=content.get("steps"),
            loop=AcrossClocks.from_json(content),
        )


def measure_stack(
    run_dir: Path, settings: Sequence[str] = (), progress: Callable[[str], None] = print
) -> StackAcrossSites:
    """The realtime grasp (seed 0) split across two sites on this host (``teleop up
    --site robot`` and ``--site operator``, their routers over mutual TLS on loopback),
    each site on its own clock as far as the stack knows: the loop's round trip on the
    operator site's clock, each way across from the clocks' offset estimated from the
    loop's stamps (:func:`teleop.bench.loop_stats.across_clocks`), and the run's outcome.
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
        plant = PlantSummary.from_json(wait_plant_end(robot_dir, STACK_RUN_TIMEOUT_S))
    finally:
        for site_dir in reversed(started):
            subprocess.run([sys.executable, "-m", "teleop.cli", "down", "--run-dir",
                            str(site_dir)], capture_output=True, timeout=120)  # fmt: skip
    return StackAcrossSites(
        success=bool(plant.object_in_box) and bool(plant.finished),
        failure=plant.failure,
        realtime_factor=plant.realtime_factor,
        braked_steps=plant.stale_steps,
        steps=plant.steps,
        loop=across_clocks(np.load(operator_dir / HAPTIC_TRACE_FILE)),
    )


def stack_table(stack: StackAcrossSites, floor_routers_ms: Mapping[str, float] | None) -> list[str]:
    """The stack's loop across the sites as Markdown lines, beside the routers' floor
    (``p50_ms``, ``p99_ms``: :meth:`SitesReport.routers_floor_ms`)."""
    loop = stack.loop
    if not loop.loops:
        return ["the stack across the sites closed no loop"]

    def ms(figures: LatencyStats | None, key: str) -> str:
        value_us = None if figures is None else figures.percentile_us(key)
        return "n/a" if value_us is None else f"{value_us / 1e3:.2f} ms"

    rows = [
        ("round trip (operator site's clock)", ms(loop.round_trip_us, "p50"),
         ms(loop.round_trip_us, "p99")),
        ("operator site -> robot site", ms(loop.operator_to_robot_us, "p50"),
         ms(loop.operator_to_robot_us, "p99")),
        ("robot site (controller, plant, controller)", ms(loop.robot_site_us, "p50"),
         ms(loop.robot_site_us, "p99")),
        ("robot site -> operator site", ms(loop.robot_to_operator_us, "p50"),
         ms(loop.robot_to_operator_us, "p99")),
    ]  # fmt: skip
    if floor_routers_ms is not None:
        rows.append(("floor: bare ends through the routers", f"{floor_routers_ms['p50_ms']:.2f} ms",
                     f"{floor_routers_ms['p99_ms']:.2f} ms"))  # fmt: skip
    lines = [
        f"The realtime grasp across two sites: {'success' if stack.success else 'failed'}, "
        f"realtime factor {stack.realtime_factor:.3f}, {stack.braked_steps} of "
        f"{stack.steps} steps braked; {loop.loops} loops",
        "",
        *markdown.table(("path", "p50", "p99"), rows, "lrr"),
        "",
        f"clocks' offset (robot minus operator site) {loop.offset_s:+.6f} s, +- "
        f"{loop.offset_uncertainty_us / 1e3:.2f} ms (each way within that)",
    ]
    return lines
