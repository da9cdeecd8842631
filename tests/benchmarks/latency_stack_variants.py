"""Benchmark: scheduling, timing and Zenoh settings on the whole bilateral loop (issue 6, item 6).

``latency_tuning.py`` tries settings on the bare relay chain; this one runs the realtime
teleoperation stack itself (every service, the recorder and the eye view, the scripted
operator shuttling the tool: ``teleop/latency.py:run_stack``) once per variant, each in
a fresh process so that environment settings reach every service. Rounds alternate
the variants so that machine noise hits all alike; the report gives, per variant, the
median over rounds of the round trip's p50 and p99, its ratio to the default measured
in the same rounds, the stack's CPU use and the samples shed, and writes them to JSON.

    .venv/bin/python tests/benchmarks/latency_stack_variants.py --duration 15 --repeat 3 \\
        --json runs/bench/latency_stack_variants.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

# One worker per Zenoh runtime pool (RON syntax of the ZENOH_RUNTIME variable).
ONE_THREAD_RUNTIME = (
    "(app: (worker_threads: 1), acc: (worker_threads: 1), tx: (worker_threads: 1), "
    "rx: (worker_threads: 1), net: (worker_threads: 1))"
)
VARIANTS: dict[str, dict] = {
    "default": {},
    "fifo_off": {"overrides": ["cpu.fifo_priority=0"]},
    "old_timing": {"overrides": ["plant.apply_on_arrival=false", "haptic.render_on_arrival=false"]},
    "shm_off": {"overrides": ["bus.shm=false", 'bus.zenoh_config="local-noshm.json5"']},
    "runtime_1_thread": {"env": {"ZENOH_RUNTIME": ONE_THREAD_RUNTIME}},
    "lowlatency_off": {"overrides": ["bus.lowlatency=false"]},
    "observers_on_cpu0": {"overrides": ["cpu.recorder=[0]", "cpu.eyeview=[0]"]},
    "unpinned": {
        "overrides": ["cpu.plant=[]", "cpu.controller=[]", "cpu.recorder=[]", "cpu.eyeview=[]"]
    },
}


def one_variant(name: str, duration_s: float, run_dir: Path, out: Path) -> None:
    """Child process: run the stack with one variant, write its figures to ``out``."""
    from teleop import latency

    run = latency.run_stack(name, None, VARIANTS[name].get("overrides", []), duration_s, run_dir)
    cpu = latency.cpu_share(run.summary)
    figures = {
        "round_trip": run.analysis["round_trip_us"],
        "cpu_cores": sum(v for v in cpu.values() if v is not None),
        "shed": sum(latency.shed_counters(run.summary["services"]).values()),
    }
    out.write_text(json.dumps(figures))


def run_variant(name: str, duration_s: float, run_dir: Path) -> dict:
    out = run_dir / "figures.json"
    run_dir.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, **VARIANTS[name].get("env", {})}
    subprocess.run(
        [sys.executable, __file__, "--one", name, "--duration", str(duration_s),
         "--out", str(out), "--run-dir", str(run_dir)],
        check=True, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
    )  # fmt: skip
    return json.loads(out.read_text())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=15.0, help="stack seconds per run")
    parser.add_argument("--repeat", type=int, default=3, help="rounds over all variants")
    parser.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated")
    parser.add_argument("--json", type=Path, default=Path("runs/bench/latency_stack_variants.json"))
    parser.add_argument("--one", help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--run-dir", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        one_variant(args.one, args.duration, args.run_dir, args.out)
        return 0
    names = args.variants.split(",")
    unknown = sorted(set(names) - set(VARIANTS))
    if unknown:
        parser.error(f"unknown variants {unknown}; known: {', '.join(VARIANTS)}")
    results: dict[str, list[dict]] = {name: [] for name in names}
    with tempfile.TemporaryDirectory(prefix="stack-variants-") as tmp:
        for round_index in range(args.repeat):
            for name in names:
                figures = run_variant(name, args.duration, Path(tmp) / f"{name}-{round_index}")
                results[name].append(figures)
                rt = figures["round_trip"]
                print(
                    f"round {round_index} {name:18s} round trip p50 {rt['p50']:6.0f} us "
                    f"p99 {rt['p99']:6.0f} us | CPU {figures['cpu_cores']:.2f} cores | "
                    f"shed {figures['shed']}",
                    flush=True,
                )

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
