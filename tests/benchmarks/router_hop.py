"""Benchmark: what a site's routers add to a round trip, on one host, and the round
trip through the network emulator between the routers, per delay.

Two processes play the loop's two ends with the run's settings (mutual TLS, the
run's certificates and access list, shared memory, the low-latency transport): the
haptic end sends a sample at ``--rate-hz`` and times each answer, the controller end
answers each one at once. Variants, in alternating rounds:

- ``direct``: the two ends linked to each other (one host, one site: the floor);
- ``routers``: each end a peer of its own site's router (each router a process of its
  own, ``teleop.bus.session.router_config``), the routers linked over TLS;
- ``routers+netem D``: the same, the routers' link through ``teleop.bench.netem`` with
  a one-way delay of D ms (``--delays-ms``), compared with the floor plus twice D.

Writes the numbers to a JSON file:

    .venv/bin/python tests/benchmarks/router_hop.py --rounds 3 --pings 2000 \
        --delays-ms 12.5,25,50,100 --json runs/bench/router_hop.json

Measure on a quiet machine (nothing else running); the load average is in the report.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import multiprocessing
import os
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import zenoh

from teleop.bench.netem import LinkImpairment, running_proxy
from teleop.bench.ping import paced_round_trips_ms
from teleop.bus import graph
from teleop.bus import session as bus
from teleop.bus.access import write_run_credentials
from teleop.bus.topics import Topics
from teleop.core.config import OPERATOR_SITE, ROBOT_SITE, BusConfig, SiteConfig
from teleop.core.net import free_loopback_port

ROBOT = "bench"
ROBOT_ROUTER, OPERATOR_ROUTER = graph.router_name(ROBOT_SITE), graph.router_name(OPERATOR_SITE)
PARTICIPANTS = ["haptic", "controller", ROBOT_ROUTER, OPERATOR_ROUTER]


def _endpoint() -> str:
    return f"tls/127.0.0.1:{free_loopback_port()}"


def _bus(files: dict[str, Path], name: str, endpoint: str, own: str = "") -> BusConfig:
    return dataclasses.replace(
        BusConfig(endpoint=endpoint),
        gossip=False,
        peer_listen_endpoint=own,
        credentials_file=str(files[name]),
    )


def _router(bus_config: BusConfig, site: SiteConfig, listen: bool, stop: object) -> None:
    """A site's router until ``stop`` (a multiprocessing Event) is set."""
    session = zenoh.open(bus.router_config(bus_config, site, listen=listen))
    stop.wait()  # type: ignore[attr-defined]
    session.close()


def _answerer(bus_config: BusConfig, listen: bool, stop: object) -> None:
    """The controller's end: every sample straight back, until ``stop`` is set."""
    topics = Topics(ROBOT)
    session = bus.open_session(bus_config, listen=listen)
    back = session.declare_publisher(topics.force_feedback, express=True)
    sub = session.declare_subscriber(
        topics.haptic_state, lambda sample: back.put(sample.payload.to_bytes())
    )
    stop.wait()  # type: ignore[attr-defined]
    sub.undeclare()
    back.undeclare()
    session.close()


@contextlib.contextmanager
def _processes(*targets: tuple) -> Iterator[None]:
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
            proc.join(timeout=10)
            if proc.is_alive():
                proc.kill()


def round_trips_ms(bus_config: BusConfig, pings: int, rate_hz: float) -> np.ndarray:
    """Samples from the haptic end, paced at ``rate_hz``; their round trips (ms)."""
    topics = Topics(ROBOT)
    session = bus.open_session(bus_config, listen=False)
    try:
        return paced_round_trips_ms(
            session, topics.haptic_state, topics.force_feedback, pings, rate_hz
        )
    finally:
        session.close()


def measure(files: dict[str, Path], variant: str, delay_ms: float, args: argparse.Namespace):
    """One variant's round trips (ms)."""
    if variant == "direct":
        endpoint = _endpoint()
        with _processes((_answerer, _bus(files, "controller", endpoint), True)):
            return round_trips_ms(
                _bus(files, "haptic", endpoint, _endpoint()), args.pings, args.rate_hz
            )
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
        haptic = _bus(files, "haptic", operator_mesh, _endpoint())
        return round_trips_ms(haptic, args.pings, args.rate_hz)


def _stats(trips: np.ndarray) -> dict[str, float]:
    return {
        "received": int(trips.size),
        "p50_ms": float(np.median(trips)),
        "p99_ms": float(np.percentile(trips, 99)),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds")
    parser.add_argument("--pings", type=int, default=2000, help="samples per variant and round")
    parser.add_argument("--rate-hz", type=float, default=1000.0, help="samples per second")
    parser.add_argument("--delays-ms", default="", help="one-way delays between the routers (ms)")
    parser.add_argument("--json", type=Path, default=Path("runs/bench/router_hop.json"))
    args = parser.parse_args()
    delays = [float(d) for d in args.delays_ms.split(",") if d]
    report: dict = {"load_average_start": os.getloadavg(), "pings": args.pings,
                    "rate_hz": args.rate_hz, "rounds": []}  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        files = write_run_credentials(Path(tmp), PARTICIPANTS, ROBOT, tls=True)
        for round_index in range(args.rounds):
            order = ["direct", "routers"] if round_index % 2 == 0 else ["routers", "direct"]
            entry = {}
            for variant in order:
                entry[variant] = _stats(measure(files, variant, None, args))
                print(
                    f"round {round_index + 1} {variant}: {json.dumps(entry[variant])}", flush=True
                )
            report["rounds"].append(entry)
        for key in ("p50_ms", "p99_ms"):
            ratios = [r["routers"][key] / r["direct"][key] for r in report["rounds"]]
            report[f"routers_over_direct_{key[:3]}"] = float(np.median(ratios))
        floor_p50 = float(np.median([r["direct"]["p50_ms"] for r in report["rounds"]]))
        report["delays"] = []
        for delay_ms in delays:
            stats = _stats(measure(files, "routers", delay_ms, args))
            stats |= {"delay_ms": delay_ms, "p50_over_floor_plus_2_delays":
                      stats["p50_ms"] / (floor_p50 + 2 * delay_ms)}  # fmt: skip
            report["delays"].append(stats)
            print(f"routers + {delay_ms:g} ms each way: {json.dumps(stats)}", flush=True)
    report["load_average_end"] = os.getloadavg()
    print(f"routers / direct, median over rounds: p50 {report['routers_over_direct_p50']:.2f}, "
          f"p99 {report['routers_over_direct_p99']:.2f}")  # fmt: skip
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    print(f"-> {args.json}")
    lost = [r for rnd in report["rounds"] for r in rnd.values() if r["received"] < args.pings]
    return 1 if lost or any(d["received"] < args.pings for d in report["delays"]) else 0


if __name__ == "__main__":
    sys.exit(main())
