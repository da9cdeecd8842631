"""docs/latency.md from a ``teleop latency --json`` report: the figures are never hand-kept.

``python -m teleop.bench.doc REPORT.json [--out docs/latency.md]`` renders the report's
round trip against the transport floor measured in the same run, hop by hop, with its
conclusions. The same report always gives the same document.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from teleop.bench.loop_stats import HOPS
from teleop.core import markdown

HEADER = """# Latency of the bilateral loop

Rendered by `python -m teleop.bench.doc` from a `teleop latency --json` report; do not
edit by hand: run `teleop latency --duration 60 --json out.json` and render again.

The round trip runs from the haptic handle's sample to the feedback force set on its
motors: handle -> controller -> plant -> controller -> handle, four transport hops and
the stages between them (docs/realtime.md explains each). The **floor** is a bare Zenoh
relay chain with the same four legs, Zenoh config, QoS, payload size, CPUs and
scheduling, doing no work, paced at the bus rate and measured in the same minutes as the
stack (half before it, half after). On a shared machine only figures taken together
compare: read the ratios, not the absolute times."""


def _us(value: Any) -> str:
    return "n/a" if value is None else f"{float(value):.0f}"


def _ratio(value: Any) -> str:
    return "n/a" if value is None else f"{float(value):.2f}x"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return markdown.table(header, rows, "r" * len(header))  # figures, every column


def render(report: Mapping[str, Any]) -> str:
    """The Markdown document of one report."""
    machine = report.get("machine", {})
    lines = [HEADER, "", "## This run", ""]
    lines.append(
        f"- measured: {report.get('date_utc', 'n/a')}, {machine.get('cpus', 'n/a')} CPUs, "
        f"load average before / after {machine.get('loadavg_before', 'n/a')} / "
        f"{machine.get('loadavg_after', 'n/a')}"
    )
    lines.append(
        f"- stack run {report.get('duration_s', 'n/a')} s, baselines "
        f"{report.get('baseline_duration_s', 'n/a')} s each"
    )
    lines += ["", "## Round trip (us)", ""]
    overhead = report.get("overhead", {})
    round_trip = overhead.get("round_trip", {})
    series = [
        ("stack, shared memory", report.get("round_trip_us", {})),
        ("floor, shared memory", report.get("floor_us", {})),
        ("stack, shared memory off", report.get("shm_off_round_trip_us", {})),
        ("floor, shared memory off", report.get("floor_shm_off_us", {})),
        ("stack, old timing (plant tick + device step)", report.get("old_timing_round_trip_us")),
    ]
    rows = [
        [name, _us(s.get("p50")), _us(s.get("p99")), _us(s.get("max")), str(s.get("count", 0))]
        for name, s in series
        if s
    ]
    lines += _table(["series", "p50", "p99", "max", "loops"], rows)
    lines += [
        "",
        f"Stack over floor: p50 {_ratio(round_trip.get('p50_ratio'))}, "
        f"p99 {_ratio(round_trip.get('p99_ratio'))}.",
        "",
        "## Hop by hop (us)",
        "",
    ]
    hops, floor_hops = report.get("hops", {}), report.get("floor_hops", {})
    rows = []
    for hop in HOPS:
        mine, base = hops.get(hop.name, {}), floor_hops.get(hop.name, {})
        ratio = overhead.get(hop.name, {})
        rows.append(
            [
                f"{hop.name} ({hop.kind})",
                _us(mine.get("p50")),
                _us(mine.get("p99")),
                _us(base.get("p50")),
                _us(base.get("p99")),
                _ratio(ratio.get("p50_ratio")),
                _ratio(ratio.get("p99_ratio")),
            ]
        )
    lines += _table(
        ["hop", "stack p50", "stack p99", "floor p50", "floor p99", "p50 ratio", "p99 ratio"],
        rows,
    )
    lines += ["", "A ratio is n/a where the floor has no such wait (below its resolution).", ""]
    lines += ["## Conclusions", ""]
    lines += [f"- {line}" for line in report.get("conclusions", [])]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m teleop.bench.doc",
        description="Render docs/latency.md from a `teleop latency --json` report.",
    )
    parser.add_argument("report", type=Path, help="the JSON report of `teleop latency`")
    parser.add_argument("--out", type=Path, help="write here (default: standard output)")
    args = parser.parse_args(argv)
    try:
        report = json.loads(args.report.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        print(f"error: {args.report}: {exc}", file=sys.stderr)
        return 2
    if not isinstance(report, dict) or "round_trip_us" not in report:
        print(f"error: {args.report} is not a `teleop latency --json` report", file=sys.stderr)
        return 2
    text = render(report)
    if args.out is None:
        sys.stdout.write(text)
    else:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
