"""Benchmark: scheduling, timing and Zenoh settings on the whole bilateral loop (issue 6, item 6).

``latency_tuning.py`` tries settings on the bare relay chain; this one runs the realtime
teleoperation stack itself (every service, the recorder and the eye view, the scripted
operator shuttling the tool: ``teleop/bench/latency.py:run_stack``) once per variant, each in
a fresh process so that environment settings reach every service. Rounds alternate
the variants so that machine noise hits all alike; the report gives, per variant, the
median over rounds of the round trip's p50 and p99, its ratio to the default measured
in the same rounds, the stack's CPU use and the samples shed, and writes them to JSON.

    .venv/bin/python tests/benchmarks/latency_stack_variants.py --duration 15 --repeat 3 \\
        --json runs/bench/latency_stack_variants.json
"""

from __future__ import annotations

import json
import os
import statistics
import sys
from pathlib import Path

from variants import (
    ONE_THREAD_RUNTIME,
    alternate,
    chosen_variants,
    variant_parser,
)

from teleop.bench import latency, run_counts

VARIANTS: dict[str, dict] = {
    "default": {},
    "fifo_off": {"overrides": ["cpu.fifo_priority=0"]},
    "idle_poll_off": {"overrides": ["cpu.idle_poll=false"]},
    "old_timing": {"overrides": list(latency.OLD_TIMING)},
    "shm_off": {"overrides": list(latency.SHM_OFF)},
    "tls": {"overrides": ["bus.tls=true"]},  # every link mutual TLS
    "tls_shm_off": {"overrides": ["bus.tls=true", *latency.SHM_OFF]},  # TLS carries it all
    "runtime_1_thread": {"env": {"ZENOH_RUNTIME": ONE_THREAD_RUNTIME}},
    "lowlatency_off": {"overrides": ["bus.lowlatency=false"]},
    "observers_on_cpu0": {"overrides": ["cpu.recorder=[0]", "cpu.eyeview=[0]"]},
    "haptic_on_cpu0": {"overrides": ["cpu.haptic=[0]"]},  # with the plant
    "haptic_on_cpu1": {"overrides": ["cpu.haptic=[1]"]},  # with the controller
    "unpinned": {
        "overrides": ["cpu.plant=[]", "cpu.controller=[]", "cpu.recorder=[]", "cpu.eyeview=[]"]
    },
}


def one_variant(name: str, duration_s: float, run_dir: Path, out: Path) -> None:
    """Child process: run the stack with one variant, write its figures to ``out``."""
    run = latency.run_stack(name, None, VARIANTS[name].get("overrides", []), duration_s, run_dir)
    cpu = run_counts.cpu_share(run.summary)
    figures = {
        "round_trip": run.analysis.round_trip_us.to_json(),
        "cpu_cores": sum(v for v in cpu.values() if v is not None),
        "shed": run_counts.shed_counters(run.summary).total,
    }
    out.write_text(json.dumps(figures))


def main() -> int:
    parser = variant_parser(__doc__, VARIANTS, Path("runs/bench/latency_stack_variants.json"))
    parser.add_argument("--duration", type=float, default=15.0, help="stack seconds per run")
    args = parser.parse_args()
    if args.one:
        one_variant(args.one, args.duration, args.run_dir, args.out)
        return 0
    names = chosen_variants(parser, args, VARIANTS)

    def describe(figures: dict) -> str:
        rt = figures["round_trip"]
        return (
            f"round trip p50 {rt['p50']:6.0f} us p99 {rt['p99']:6.0f} us | "
            f"CPU {figures['cpu_cores']:.2f} cores | shed {figures['shed']}"
        )

    child_args = ["--duration", str(args.duration)]
    results = alternate(__file__, VARIANTS, names, args.repeat, child_args, describe)

    summary: dict[str, dict[str, float]] = {}
    for name in names:
        runs = results[name]
        summary[name] = {
            "round_trip_p50_us": statistics.median(r["round_trip"]["p50"] for r in runs),
            "round_trip_p99_us": statistics.median(r["round_trip"]["p99"] for r in runs),
            "cpu_cores": statistics.median(r["cpu_cores"] for r in runs),
            "shed": statistics.median(r["shed"] for r in runs),
        }
    if "default" in summary:  # ratios within each round, then their median
        for name in names:
            for pct in ("p50", "p99"):
                ratios = [
                    r["round_trip"][pct] / d["round_trip"][pct]
                    for r, d in zip(results[name], results["default"], strict=True)
                ]
                summary[name][f"round_trip_{pct}_ratio_to_default"] = statistics.median(ratios)
    report = {
        "duration_s": args.duration,
        "repeat": args.repeat,
        "loadavg": os.getloadavg(),
        "medians": summary,
        "runs": results,
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    for name, figures in summary.items():
        line = (
            f"{name:18s} median round trip p50 {figures['round_trip_p50_us']:6.0f} us, "
            f"p99 {figures['round_trip_p99_us']:6.0f} us"
        )
        if "round_trip_p50_ratio_to_default" in figures:
            line += (
                f" (x{figures['round_trip_p50_ratio_to_default']:.2f} / "
                f"x{figures['round_trip_p99_ratio_to_default']:.2f} of default, same rounds)"
            )
        print(line + f", CPU {figures['cpu_cores']:.2f} cores")
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
