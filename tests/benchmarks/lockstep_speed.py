"""Benchmark: how fast lockstep runs on the services, against the in-process loop.

Both do the same computation (bit-identical final state); the difference is the bus
and the process hand-offs. Runs alternate so that machine noise hits both alike;
the report gives medians and their ratio, and writes them to a JSON file.

    .venv/bin/python tests/benchmarks/lockstep_speed.py --duration 10 --repeat 3 \
        --json runs/bench/lockstep_speed.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from teleop.config import load_config
from teleop.experiments import run_path_following_inprocess


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
        "--set", action="append", default=[], metavar="KEY=VALUE",
        help="config override for the services runs, e.g. cpu.plant=[] (repeatable)",
    )  # fmt: skip
    args = parser.parse_args()
    config = load_config(None, [f"run.duration_s={args.duration}"])
    inprocess, lockstep, compute_us, cycles_us = [], [], [], []
    with tempfile.TemporaryDirectory(prefix="bench-") as tmp:
        for i in range(args.repeat):
            reference = run_path_following_inprocess(config, progress=None)
            inprocess.append(reference["realtime_factor"])
            summary = lockstep_run(args.duration, Path(tmp) / f"run{i}", args.set)
            if summary["final_state_sha256"] != reference["final_state_sha256"]:
                print("lockstep and in-process runs differ: not comparable", file=sys.stderr)
                return 1
            lockstep.append(summary["realtime_factor"])
            compute_us.append(summary["services"]["controller"]["compute_mean_us"])
            cycles_us.append(summary["services"]["plant"]["lockstep_cycle_us"])
            print(
                f"run {i}: in-process {inprocess[-1]:.2f}x, lockstep {lockstep[-1]:.2f}x, "
                f"cycle (median us) {cycles_us[-1]}"
            )
    report = {
        "duration_s": args.duration,
        "repeat": args.repeat,
        "inprocess_realtime_factor": inprocess,
        "lockstep_realtime_factor": lockstep,
        "overrides": args.set,
        "controller_compute_mean_us": compute_us,
        "lockstep_cycle_us": cycles_us,
        "inprocess_median": statistics.median(inprocess),
        "lockstep_median": statistics.median(lockstep),
        "lockstep_over_inprocess": statistics.median(lockstep) / statistics.median(inprocess),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    print(
        f"median: lockstep {report['lockstep_median']:.2f}x real time, in-process "
        f"{report['inprocess_median']:.2f}x, ratio {report['lockstep_over_inprocess']:.2f} "
        f"-> {args.json}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
