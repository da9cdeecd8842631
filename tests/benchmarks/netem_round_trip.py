"""Benchmark: a Zenoh round trip through the network emulator, per one-way delay.

Two sessions, linked only through ``teleop.bench.netem`` (as two sites' routers will
be): one answers every ping with a pong, the other sends pings at ``--rate-hz`` and
times each round trip. Each delay's figures are compared with the floor measured in the
same run (the same two sessions linked directly) plus twice the delay, what the
emulator adds by design. Writes the numbers to a JSON file.

    .venv/bin/python tests/benchmarks/netem_round_trip.py --delays-ms 0,10,50,100 \
        --pings 300 --json runs/bench/netem_round_trip.json

Measure on a quiet machine (nothing else running); the load average is in the report.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from teleop.bench.netem import LinkImpairment, running_proxy
from teleop.bench.ping import paced_round_trips_ms
from teleop.bus import session as bus
from teleop.core.config import BusConfig
from teleop.core.net import free_loopback_port

PING, PONG = "teleop/netem/ping", "teleop/netem/pong"


def _bus(endpoint: str) -> BusConfig:
    return BusConfig(endpoint=endpoint, shm=False, zenoh_config="local.json5", secure=False)


def round_trips_ms(connect_port: int, pings: int, rate_hz: float) -> np.ndarray:
    """Pings from a session that connects to ``connect_port``; their round trips (ms)."""
    far = bus.open_session(_bus(f"tcp/127.0.0.1:{connect_port}"), listen=False)
    try:
        return paced_round_trips_ms(far, PING, PONG, pings, rate_hz)
    finally:
        far.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--delays-ms", default="0,10,50,100", help="one-way delays (ms)")
    parser.add_argument("--jitter-ms", type=float, default=0.0, help="+- jitter (ms)")
    parser.add_argument("--pings", type=int, default=300, help="pings per delay")
    parser.add_argument("--rate-hz", type=float, default=100.0, help="pings per second")
    parser.add_argument("--json", type=Path, default=Path("runs/bench/netem_round_trip.json"))
    args = parser.parse_args()
    delays = [float(d) for d in args.delays_ms.split(",")]
    port = free_loopback_port()
    near = bus.open_session(_bus(f"tcp/127.0.0.1:{port}"), listen=True)
    pong = near.declare_publisher(PONG)
    answerer = near.declare_subscriber(PING, lambda s: pong.put(s.payload.to_bytes()))
    report: dict = {"load_average": os.getloadavg(), "pings": args.pings,
                    "rate_hz": args.rate_hz, "jitter_ms": args.jitter_ms}  # fmt: skip
    try:
        floor = round_trips_ms(port, args.pings, args.rate_hz)
        report["floor_ms"] = {
            "p50": float(np.median(floor)),
            "p99": float(np.percentile(floor, 99)),
        }
        print(f"direct: p50 {report['floor_ms']['p50']:.3f} ms, p99 "
              f"{report['floor_ms']['p99']:.3f} ms", flush=True)  # fmt: skip
        report["delays"] = []
        for delay_ms in delays:
            link = LinkImpairment(delay_s=delay_ms / 1e3, jitter_s=args.jitter_ms / 1e3)
            with running_proxy(("127.0.0.1", port), link) as proxy:
                trips = round_trips_ms(proxy.port, args.pings, args.rate_hz)
            expected = report["floor_ms"]["p50"] + 2 * delay_ms
            entry = {
                "delay_ms": delay_ms,
                "received": int(trips.size),
                "p50_ms": float(np.median(trips)),
                "p99_ms": float(np.percentile(trips, 99)),
                "p50_over_floor_plus_2_delays": float(np.median(trips)) / expected,
            }
            report["delays"].append(entry)
            ratio = entry["p50_over_floor_plus_2_delays"]
            print(f"delay {delay_ms:g} ms: {entry['received']}/{args.pings} back, p50 "
                  f"{entry['p50_ms']:.3f} ms, p99 {entry['p99_ms']:.3f} ms, p50 / (floor + "
                  f"2 x delay) = {ratio:.3f}", flush=True)  # fmt: skip
    finally:
        answerer.undeclare()
        pong.undeclare()
        near.close()
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    print(f"-> {args.json}")
    return 0 if all(e["received"] == args.pings for e in report["delays"]) else 1


if __name__ == "__main__":
    sys.exit(main())
