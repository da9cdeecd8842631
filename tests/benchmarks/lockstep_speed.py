"""Benchmark: how fast lockstep runs on the services, against the in-process loop.

Both do the same computation (bit-identical final state); the difference is the bus
and the process hand-offs. Runs alternate so that machine noise hits both alike;
the report gives medians and their ratio, and writes them to a JSON file.

    .venv/bin/python tests/benchmarks/lockstep_speed.py --duration 10 --repeat 3 \
        --delays 0,1 --json runs/bench/lockstep_speed.json

Each round runs every ``plant.lockstep_delay_steps`` value asked for (0: plant and
controller take turns; 1: one state in flight while the plant steps).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from teleop.core.config import load_config
from teleop.run.experiments import run_path_following_inprocess


def lockstep_run(duration_s: float, run_dir: Path, overrides: list[str]) -> dict:
    out = run_dir / "summary.json"
    sets = [arg for override in overrides for arg in ("--set", override)]
    subprocess.run(
        [sys.executable, "-m", "teleop.cli", "run", "path-following", "--mode", "lockstep",
         "--duration", str(duration_s), "--run-dir", str(run_dir), "--summary-json", str(out),
         "--quiet", *sets],
        check=True, stdout=subprocess.DEVNULL, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    return json.loads(out.read_text())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=10.0, help="simulated s per run")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each kind")
    parser.add_argument("--json", type=Path, default=Path("runs/bench/lockstep_speed.json"))
    parser.add_argument(
        "--delays", default="0,1",
        help="plant.lockstep_delay_steps values to compare, each in every round (default 0,1: "
             "plant and controller taking turns vs one state in flight)",
    )  # fmt: skip
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE",
        help="config override for every run, e.g. cpu.plant=[] (repeatable)",
    )  # fmt: skip
    args = parser.parse_args()
    delays = [int(d) for d in args.delays.split(",")]
    runs: dict[int, dict[str, list]] = {
        d: {"inprocess": [], "lockstep": [], "compute_us": [], "cycle_us": []} for d in delays
    }
    with tempfile.TemporaryDirectory(prefix="bench-") as tmp:
        for i in range(args.repeat):
            for delay in delays:
                overrides = [*args.set, f"plant.lockstep_delay_steps={delay}"]
                config = load_config(None, [f"run.duration_s={args.duration}", *overrides])
                reference = run_path_following_inprocess(config, progress=None)
                summary = lockstep_run(args.duration, Path(tmp) / f"run{i}-{delay}", overrides)
                if summary["final_state_sha256"] != reference["final_state_sha256"]:
                    print("lockstep and in-process runs differ: not comparable", file=sys.stderr)
                    return 1
                kept = runs[delay]
                kept["inprocess"].append(reference["realtime_factor"])
                kept["lockstep"].append(summary["realtime_factor"])
                kept["compute_us"].append(summary["services"]["controller"]["compute_mean_us"])
                kept["cycle_us"].append(summary["services"]["plant"]["lockstep_cycle_us"])
                print(
                    f"round {i}, delay {delay}: in-process {kept['inprocess'][-1]:.2f}x, "
                    f"lockstep {kept['lockstep'][-1]:.2f}x, "
                    f"cycle (median us) {kept['cycle_us'][-1]}"
                )
    report: dict = {"duration_s": args.duration, "repeat": args.repeat, "overrides": args.set}
    for delay, kept in runs.items():
        report[f"delay_{delay}"] = {
            **kept,
            "inprocess_median": statistics.median(kept["inprocess"]),
            "lockstep_median": statistics.median(kept["lockstep"]),
            "lockstep_over_inprocess": statistics.median(kept["lockstep"])
            / statistics.median(kept["inprocess"]),
        }
    if len(delays) > 1:
        base = report[f"delay_{delays[0]}"]["lockstep_median"]
        report["lockstep_speedup_over_first_delay"] = {
            str(d): report[f"delay_{d}"]["lockstep_median"] / base for d in delays
        }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    for delay in delays:
        entry = report[f"delay_{delay}"]
        print(
            f"delay {delay}: median lockstep {entry['lockstep_median']:.2f}x real time, "
            f"in-process {entry['inprocess_median']:.2f}x"
        )
    print(f"-> {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
