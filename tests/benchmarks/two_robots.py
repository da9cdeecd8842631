"""Benchmark: one operator station driving two robots (``teleop run grasp --robots 2``)
against the same station driving one, measured in the same run.

Per round, alternating: the grasp with one robot (the baseline) and with two, seed 0, in
each mode asked for (``--modes``):

- **lockstep** (deterministic; the figures but wall time do not depend on the load):
  success per robot, and each process's CPU seconds per simulated second once running
  (its start-up apart, reported on its own): a robot's own processes (plant,
  controller) over its own plant's simulated time, the station's (haptic, HMD,
  operator, recorder, eye view) over the run's;
- **realtime**: the same, and the bilateral loop's round trip (handle sampled ->
  controller -> feedback rendered on the handle; ``teleop.bench.latency.analyse`` of the
  haptic service's stamps, after its warm-up), the realtime factor and the share of plant
  steps the watchdog braked. A run that cannot keep real time says so (its verdict),
  and that is the figure.

Measure on a quiet machine: the load average before each run is in the output.

    .venv/bin/python tests/benchmarks/two_robots.py --rounds 2 --json runs/bench/two_robots.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from teleop.bench.loop_stats import analyse
from teleop.bus import graph
from teleop.core.rundir import HAPTIC_TRACE_FILE, RUN_SUMMARY_FILE

RUN_TIMEOUT_S = 1800


def one_run(robots: int, mode: str, run_dir: Path) -> dict[str, Any]:
    """``teleop run grasp --robots N --mode MODE --seed 0``: its figures."""
    command = [sys.executable, "-m", "teleop.cli", "run", "grasp", "--mode", mode, "--seed",
               "0", "--robots", str(robots), "--run-dir", str(run_dir), "--quiet"]  # fmt: skip
    load = os.getloadavg()
    start = time.monotonic()
    done = subprocess.run(
        command, stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=RUN_TIMEOUT_S
    )
    wall_s = time.monotonic() - start
    path = run_dir / RUN_SUMMARY_FILE
    if not path.exists():
        raise RuntimeError(f"no summary (exit {done.returncode}): {done.stderr[-2000:]}")
    summary = json.loads(path.read_text())
    services = summary["services"]
    sections = summary.get("robots") or {"arm0": summary}
    plant_sim_s = {
        rid: services[graph.instance_name("plant", rid, robots)]["sim_time_s"] for rid in sections
    }
    run_sim_s = max(plant_sim_s.values())
    cpu: dict[str, float] = {}
    startup_cpu_s: dict[str, float] = {}
    for name, own in services.items():
        if "cpu_s" not in own:  # the idle pollers
            continue
        robot = graph.robot_of(name)
        sim_s = plant_sim_s[robot] if robot is not None else run_sim_s
        startup_cpu_s[name] = own.get("cpu_s_ready", 0.0)
        cpu[name] = (own["cpu_s"] - startup_cpu_s[name]) / sim_s
    result: dict[str, Any] = {
        "robots": robots,
        "mode": mode,
        "loadavg_before": list(load),
        "wall_s": wall_s,
        "exit_code": done.returncode,
        "success": summary["success"],
        "success_per_robot": {rid: s["success"] for rid, s in sections.items()},
        "task_s": {rid: s.get("duration_s") for rid, s in sections.items()},
        "sim_s": run_sim_s,
        "cpu_per_sim_s": cpu,
        "cpu_per_sim_s_total": sum(cpu.values()),
        "startup_cpu_s": startup_cpu_s,
        "realtime_verdict": summary.get("realtime_verdict"),
        "realtime_problems": summary.get("realtime_problems"),
    }
    if mode == "realtime":
        loop = analyse(np.load(run_dir / HAPTIC_TRACE_FILE)).round_trip_us.to_json()
        result["round_trip_us"] = {k: loop[k] for k in ("count", "p50", "p99", "max")}
        result["realtime_factor"] = {rid: s.get("realtime_factor") for rid, s in sections.items()}
        plants = [services[graph.instance_name("plant", rid, robots)] for rid in sections]
        result["braked_fraction"] = sum(p["stale_steps"] for p in plants) / max(
            sum(p["steps"] for p in plants), 1
        )
    return result


def line(run: dict[str, Any]) -> str:
    text = (
        f"{run['mode']:8s} {run['robots']} robot(s) (load {run['loadavg_before'][0]:.2f}): "
        f"success {run['success_per_robot']}, CPU/sim s {run['cpu_per_sim_s_total']:.2f} ("
        + ", ".join(f"{k} {v:.2f}" for k, v in run["cpu_per_sim_s"].items())
        + f"), wall {run['wall_s']:.0f} s"
    )
    if run["mode"] == "realtime":
        trip = run["round_trip_us"]
        text += (
            f", round trip p50 {trip['p50']} us p99 {trip['p99']} us, realtime factor "
            f"{run['realtime_factor']}, braked {run['braked_fraction']:.1%}, "
            f"verdict {run['realtime_verdict']}"
        )
    return text


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--modes", default="lockstep,realtime", help="comma-separated")
    parser.add_argument("--json", type=Path, default=Path("runs/bench/two_robots.json"))
    args = parser.parse_args()
    modes = [m for m in args.modes.split(",") if m]
    if args.rounds < 1 or not set(modes) <= {"lockstep", "realtime"}:
        parser.error("--rounds >= 1; --modes of lockstep, realtime")
    os.environ.setdefault("RERUN_ANALYTICS", "0")
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="two-robots-") as tmp:
        for index in range(args.rounds):
            for mode in modes:
                for robots in (1, 2):
                    run = one_run(robots, mode, Path(tmp) / f"{mode}{robots}_{index}")
                    runs.append(run)
                    print(f"round {index + 1}/{args.rounds}: {line(run)}", flush=True)
    median: dict[str, Any] = {}
    for mode in modes:
        for robots in (1, 2):
            mine = [r for r in runs if r["mode"] == mode and r["robots"] == robots]
            entry = {
                "cpu_per_sim_s_total": statistics.median(r["cpu_per_sim_s_total"] for r in mine),
                "cpu_per_sim_s": {
                    name: statistics.median(r["cpu_per_sim_s"][name] for r in mine)
                    for name in mine[0]["cpu_per_sim_s"]
                },
                "successes": sum(r["success"] for r in mine),
                "runs": len(mine),
            }
            if mode == "realtime":
                for key in ("p50", "p99"):
                    entry[f"round_trip_{key}_us"] = statistics.median(
                        r["round_trip_us"][key] for r in mine
                    )
                entry["braked_fraction"] = statistics.median(r["braked_fraction"] for r in mine)
            median[f"{mode}_{robots}"] = entry
        one, two = median[f"{mode}_1"], median[f"{mode}_2"]
        median[f"{mode}_cpu_ratio_two_to_one"] = (
            two["cpu_per_sim_s_total"] / one["cpu_per_sim_s_total"]
        )
        if mode == "realtime":
            median["realtime_p99_ratio_two_to_one"] = (
                two["round_trip_p99_us"] / one["round_trip_p99_us"]
            )
    result = {"runs": runs, "median": median, "cpus": len(os.sched_getaffinity(0)),
              "loadavg_after": list(os.getloadavg())}  # fmt: skip
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2))
    print(json.dumps(median, indent=1))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
