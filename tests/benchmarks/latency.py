"""Benchmark: the bilateral loop's round trip against the transport floor, repeated.

Each repeat is one full ``teleop latency`` measurement (teleop/bench/latency.py): the floor
chain, the stack with SHM on and off, the payload sweep and the old-timing stack, all
in the same minutes. The report gives the medians over repeats of the round trip's
p50/p99, the floor's, their ratio, and the SHM/TCP ratios of the sweep, and writes them
(with every repeat's full report) to a JSON file.

    .venv/bin/python tests/benchmarks/latency.py --duration 60 --repeat 3 \
        --json runs/bench/latency.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
from pathlib import Path

from teleop.bench import latency


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=60.0, help="stack seconds per repeat")
    parser.add_argument("--baseline-duration", type=float, default=None)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--json", type=Path, default=Path("runs/bench/latency.json"))
    args = parser.parse_args()
    reports = []
    with tempfile.TemporaryDirectory(prefix="bench-latency-") as tmp:
        for i in range(args.repeat):
            report, _ = latency.measure(
                None,
                [],
                Path(tmp) / f"r{i}",
                args.duration,
                baseline_s=args.baseline_duration,
                progress=latency.print_progress,
            )
            reports.append(report.to_json())
            for line in report.conclusions:
                print(f"repeat {i}: {line}")

    def med(path: tuple[str, ...]) -> float | None:
        values = []
        for report in reports:
            value = report
            for key in path:
                value = value.get(key) if isinstance(value, dict) else None
            if value is not None:
                values.append(value)
        return statistics.median(values) if values else None

    medians = {
        "round_trip_p50_us": med(("round_trip_us", "p50")),
        "round_trip_p99_us": med(("round_trip_us", "p99")),
        "floor_p50_us": med(("floor_us", "p50")),
        "floor_p99_us": med(("floor_us", "p99")),
        "floor_back_to_back_p99_us": med(("floor_back_to_back_us", "p99")),
        "shm_off_round_trip_p50_us": med(("shm_off_round_trip_us", "p50")),
        "shm_off_round_trip_p99_us": med(("shm_off_round_trip_us", "p99")),
        "old_timing_round_trip_p50_us": med(("old_timing_round_trip_us", "p50")),
        "round_trip_p99_over_floor": med(("overhead", "round_trip", "p99_ratio")),
        "round_trip_p50_over_floor": med(("overhead", "round_trip", "p50_ratio")),
    }
    sweep = {}
    for row_index, row in enumerate(reports[0]["payload_sweep"]):
        ratios = [r["payload_sweep"][row_index]["tcp_over_shm_p50"] for r in reports]
        ratios = [x for x in ratios if x is not None]
        sweep[row["bytes"]] = statistics.median(ratios) if ratios else None
    out = {
        "duration_s": args.duration,
        "repeat": args.repeat,
        "medians": medians,
        "tcp_over_shm_p50_by_bytes": sweep,
        "reports": reports,
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps({"medians": medians, "tcp_over_shm_p50_by_bytes": sweep}, indent=2))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
