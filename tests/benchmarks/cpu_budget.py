"""Benchmark: what the realtime stack asks of the CPUs, and what the kernel does when
the loops fill them.

Per round, alternating:

- **baseline**: a SCHED_FIFO probe thread pinned to each CPU (a 1 ms sleep loop above
  every service's priority, ``--probe-priority``) on the machine as it is, no stack;
- **stack**: the same probes beside ``teleop run grasp --mode realtime --seed 0`` (every
  service under supervisord).

From the stack run: each service's CPU seconds per simulated second (its summary's
``cpu_s``, start-up included, over the plant's simulated time), the realtime factor, the
share of the plant's steps the watchdog braked and its stalls. From the probes: the
wake-up gaps over 4 ms (a 1 ms sleep that took longer), how many and how long. A probe
above every service can only be held off by the kernel: gaps of about 50 ms are its
guard for starved normally scheduled tasks (RT throttling, ``sched_rt_runtime_us``, and
on recent kernels the fair server), which stops every realtime task on a CPU for tens
of ms once they keep it busy. The baseline's gaps are the floor measured in the same run.

Needs root (SCHED_FIFO). Writes JSON.

    .venv/bin/python tests/benchmarks/cpu_budget.py --rounds 3 --json runs/bench/cpu_budget.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

# A gap longer than this (ms) between two wake-ups of a 1 ms sleep loop is counted.
GAP_MS = 4.0
# Gaps at least this long (ms) are the kernel's guard (its quantum is 50 ms).
GUARD_GAP_MS = 40.0
# The probes start this long after the stack (s): past its start-up, into the task.
PROBE_DELAY_S = 8.0
PROBE_S = 12.0
RUN_TIMEOUT_S = 300


def probe(cpu: int, priority: int, duration_s: float, out: list[float]) -> None:
    """Sleep 1 ms at a time under SCHED_FIFO on ``cpu`` for ``duration_s``; append each
    gap over GAP_MS (ms) to ``out``."""
    os.sched_setaffinity(0, {cpu})
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    end_ns = time.monotonic_ns() + int(duration_s * 1e9)
    last_ns = time.monotonic_ns()
    while last_ns < end_ns:
        time.sleep(0.001)
        now_ns = time.monotonic_ns()
        gap_ms = (now_ns - last_ns) / 1e6
        if gap_ms > GAP_MS:
            out.append(gap_ms)
        last_ns = now_ns


def probe_all(priority: int, duration_s: float) -> dict[str, Any]:
    """Probes on every CPU of this process at once; their gaps per CPU."""
    cpus = sorted(os.sched_getaffinity(0))
    gaps: dict[int, list[float]] = {cpu: [] for cpu in cpus}
    threads = [
        threading.Thread(target=probe, args=(cpu, priority, duration_s, gaps[cpu])) for cpu in cpus
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return {
        str(cpu): {
            "gaps": len(found),
            "guard_gaps": sum(1 for g in found if g >= GUARD_GAP_MS),
            "max_ms": max(found, default=0.0),
            "per_s": len(found) / duration_s,
        }
        for cpu, found in gaps.items()
    }


def stack_round(run_dir: Path, priority: int) -> dict[str, Any]:
    """One realtime grasp with the probes beside it."""
    command = [sys.executable, "-m", "teleop.cli", "run", "grasp", "--mode", "realtime",
               "--seed", "0", "--run-dir", str(run_dir), "--quiet"]  # fmt: skip
    process = subprocess.Popen(
        command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    time.sleep(PROBE_DELAY_S)
    gaps = probe_all(priority, PROBE_S)
    _, stderr = process.communicate(timeout=RUN_TIMEOUT_S)
    summary_path = run_dir / "summary.json"
    if not summary_path.exists():
        raise RuntimeError(
            f"the run wrote no summary (exit {process.returncode}): {stderr[-2000:]}"
        )
    summary = json.loads(summary_path.read_text())
    services = summary["services"]
    plant = services["plant"]
    sim_s = plant["steps"] * 1e-3
    cpu = {name: s.get("cpu_s", 0.0) / sim_s for name, s in services.items()}
    # The same without each service's start-up (CPU until it declared itself ready).
    running = {
        name: (s.get("cpu_s", 0.0) - (s.get("cpu_s_ready") or 0.0)) / sim_s
        for name, s in services.items()
    }
    startup = {name: s.get("cpu_s_ready") for name, s in services.items()}
    return {
        "exit_code": process.returncode,
        "success": summary.get("success"),
        "realtime_verdict": summary.get("realtime_verdict"),
        "realtime_factor": plant["realtime_factor"],
        "braked_fraction": plant["stale_steps"] / max(plant["steps"], 1),
        "stalls": plant.get("arrival", {}).get("stalls"),
        "cpu_per_sim_s": cpu,
        "cpu_per_sim_s_total": sum(cpu.values()),
        "running_cpu_per_sim_s": running,
        "running_cpu_per_sim_s_total": sum(running.values()),
        "startup_cpu_s": startup,
        "sim_s": sim_s,
        "probe_gaps": gaps,
    }


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--probe-priority", type=int, default=80, help="above the services")
    parser.add_argument("--json", type=Path, default=Path("runs/bench/cpu_budget.json"))
    args = parser.parse_args()
    if os.geteuid() != 0:
        parser.error("needs root (the probes run under SCHED_FIFO)")
    if args.rounds < 1:
        parser.error("--rounds must be >= 1")
    os.environ.setdefault("RERUN_ANALYTICS", "0")
    rounds: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="cpu-budget-") as tmp:
        for index in range(args.rounds):
            loadavg_before = os.getloadavg()
            baseline = probe_all(args.probe_priority, PROBE_S)
            stack = stack_round(Path(tmp) / f"run{index}", args.probe_priority)
            rounds.append(
                {"loadavg_before": loadavg_before, "baseline_probe_gaps": baseline, "stack": stack}
            )
            cpus = stack["running_cpu_per_sim_s"]
            print(
                f"round {index + 1}/{args.rounds} (load average before "
                f"{loadavg_before[0]:.2f}): CPU/sim s {stack['cpu_per_sim_s_total']:.2f} with "
                f"start-up, {stack['running_cpu_per_sim_s_total']:.2f} running ("
                + ", ".join(f"{k} {v:.2f}" for k, v in cpus.items())
                + f"), realtime factor {stack['realtime_factor']:.3f}, braked "
                f"{stack['braked_fraction']:.1%}, probe guard gaps with stack "
                f"{sum(g['guard_gaps'] for g in stack['probe_gaps'].values())}, baseline "
                f"{sum(g['guard_gaps'] for g in baseline.values())} (in {PROBE_S:g} s)",
                flush=True,
            )
    stacks = [r["stack"] for r in rounds]
    result = {
        "rounds": rounds,
        "median": {
            "cpu_per_sim_s_total": statistics.median(s["cpu_per_sim_s_total"] for s in stacks),
            "running_cpu_per_sim_s_total": statistics.median(
                s["running_cpu_per_sim_s_total"] for s in stacks
            ),
            "running_cpu_per_sim_s": {
                name: statistics.median(s["running_cpu_per_sim_s"].get(name, 0.0) for s in stacks)
                for name in stacks[0]["running_cpu_per_sim_s"]
            },
            "cpu_per_sim_s": {
                name: statistics.median(s["cpu_per_sim_s"].get(name, 0.0) for s in stacks)
                for name in stacks[0]["cpu_per_sim_s"]
            },
            "realtime_factor": statistics.median(s["realtime_factor"] for s in stacks),
            "braked_fraction": statistics.median(s["braked_fraction"] for s in stacks),
        },
        "cpus": len(os.sched_getaffinity(0)),
        "probe_s": PROBE_S,
        "loadavg_after": os.getloadavg(),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2))
    median = result["median"]
    print(
        f"median: CPU/sim s {median['cpu_per_sim_s_total']:.2f} with start-up, "
        f"{median['running_cpu_per_sim_s_total']:.2f} running, on {result['cpus']} CPUs, "
        f"realtime factor {median['realtime_factor']:.3f}, braked {median['braked_fraction']:.1%}"
    )
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
