"""Benchmark: the bus rate (``loop.rate_hz``) against what it costs and what it keeps.

Per rate (``--rates``, default 100 200 250 500 1000 Hz; physics and force rendering stay
at 1 kHz), rounds alternating over the rates so a drifting machine touches all alike:

- the **realtime grasp** on the services (``teleop run grasp --mode realtime``), as this
  user or, ``--ordinary-user``, as ``nobody`` (no SCHED_FIFO, default limits): each
  service's CPU seconds per simulated second while running (its summary's ``cpu_s``
  less ``cpu_s_ready``, over the plant's sim time) and at start-up (``cpu_s_ready``),
  the sum, the verdict and the task's success;
- the **lockstep grasp** (seed 0): its speed against real time, the ratio to 1000 Hz's
  in the same round;
- **in-process path following** (the paper's path, ``--path-s`` s): the path error's RMS
  after settling, and its speed against bare ``mj_step`` of the same scene in the same
  round (the host's floor).

Writes JSON (``--json``) and a markdown table (``--markdown``); prints both. A machine
with other work on it gives other figures: run it alone, and note the load average it
prints with each round.

    .venv/bin/python -m tests.benchmarks.rate_sweep --rounds 2 --ordinary-user \\
        --json runs/bench/rate_sweep.json --markdown runs/bench/rate_sweep.md
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import mujoco

from teleop.core.config import load_config
from teleop.run.experiments import run_path_following_inprocess
from tests.e2e.users import UserEnv, ordinary_user

ROOT = Path(__file__).resolve().parents[2]
TELEOP = Path(sys.executable).with_name("teleop")
RUN_TIMEOUT_S = 600
SERVICES = ("plant", "controller", "haptic", "hmd", "operator", "recorder", "eyeview")


def load_average() -> float:
    return os.getloadavg()[0]


def run_grasp(rate_hz: float, mode: str, seed: int, user: UserEnv | None) -> dict[str, Any]:
    """One grasp on the services at ``rate_hz`` (as ``user``, or as this process's
    user); its summary and wall time."""
    parent = user.home if user is not None else Path(tempfile.gettempdir())
    run_dir = Path(tempfile.mkdtemp(prefix=f"rate{int(rate_hz)}_", dir=parent))
    out = run_dir / "summary.json"
    args = [
        "run", "grasp", "--mode", mode, "--seed", str(seed),
        "--run-dir", str(run_dir / "run"), "--summary-json", str(out),
        "--set", f"loop.rate_hz={rate_hz:g}",
    ]  # fmt: skip
    if user is not None:
        run_dir.chmod(0o777)
        command = user.argv(["-m", "teleop.cli", *args])
    else:
        command = [str(TELEOP), *args]
    start = time.monotonic()
    subprocess.run(command, cwd=parent, capture_output=True, timeout=RUN_TIMEOUT_S, check=False)
    wall_s = time.monotonic() - start
    summary = json.loads(out.read_text()) if out.exists() else {}
    return {"summary": summary, "wall_s": wall_s}


def cpu_figures(summary: dict[str, Any]) -> dict[str, Any]:
    """Per service running and start-up CPU, and the sum, per simulated second."""
    services = summary.get("services", {})
    sim_s = services.get("plant", {}).get("sim_time_s") or 0.0
    running, startup = {}, {}
    for name in SERVICES:
        section = services.get(name)
        if not section or not sim_s:
            continue
        ready = section.get("cpu_s_ready") or 0.0
        running[name] = round((section.get("cpu_s", 0.0) - ready) / sim_s, 3)
        startup[name] = round(ready, 2)
    return {
        "running_cpu_s_per_sim_s": running,
        "startup_cpu_s": startup,
        "all_cpu_s_per_sim_s": round(sum(running.values()), 3),
    }


def bare_mujoco_speed(seconds: float) -> float:
    """Bare ``mj_step`` of the scene against real time (the host's floor)."""
    config = load_config()
    model = mujoco.MjModel.from_xml_path(str(config.robot.scene_path))
    data = mujoco.MjData(model)
    steps = round(seconds / model.opt.timestep)
    start = time.perf_counter()
    for _ in range(steps):
        mujoco.mj_step(model, data)
    return seconds / (time.perf_counter() - start)


def path_figures(rate_hz: float, seconds: float) -> dict[str, Any]:
    config = load_config(None, [f"loop.rate_hz={rate_hz:g}", f"run.duration_s={seconds:g}"])
    summary = run_path_following_inprocess(config, progress=None)
    floor = bare_mujoco_speed(min(seconds, 10.0))
    return {
        "path_error_rms_m": summary["path_error_rms_m"],
        "inprocess_speed": round(summary["realtime_factor"], 2),
        "bare_mj_step_speed": round(floor, 1),
        "inprocess_over_bare": round(summary["realtime_factor"] / floor, 4),
    }


def one_round(rates: list[float], args: argparse.Namespace, user: UserEnv | None) -> dict[str, Any]:
    found: dict[str, Any] = {}
    for rate in rates:
        load = load_average()
        realtime = run_grasp(rate, "realtime", args.seed, user)
        lockstep = run_grasp(rate, "lockstep", 0, None)
        summary = realtime["summary"]
        lock_summary = lockstep["summary"]
        entry = {
            "load_average_1min": round(load, 2),
            **cpu_figures(summary),
            "realtime_verdict": summary.get("realtime_verdict"),
            "realtime_problems": summary.get("realtime_problems"),
            "success": summary.get("success"),
            "lockstep_success": lock_summary.get("success"),
            "lockstep_speed": round(lock_summary.get("realtime_factor") or 0.0, 2),
            **path_figures(rate, args.path_s),
        }
        print(f"{rate:g} Hz: {json.dumps(entry)}", flush=True)
        found[f"{rate:g}"] = entry
    return found


def median_table(rounds: list[dict[str, Any]], rates: list[float]) -> dict[str, Any]:
    """Per rate, the median of each number over the rounds (the last round's verdicts)."""
    table: dict[str, Any] = {}
    for rate in rates:
        key = f"{rate:g}"
        entries = [r[key] for r in rounds]
        row: dict[str, Any] = {
            "verdicts": [e["realtime_verdict"] for e in entries],
            "successes": [e["success"] for e in entries],
        }
        for name in ("all_cpu_s_per_sim_s", "lockstep_speed", "path_error_rms_m",
                     "inprocess_over_bare", "load_average_1min"):  # fmt: skip
            row[name] = statistics.median(e[name] for e in entries)
        row["running_cpu_s_per_sim_s"] = {
            s: statistics.median(e["running_cpu_s_per_sim_s"].get(s, 0.0) for e in entries)
            for s in SERVICES
        }
        row["startup_cpu_s"] = {
            s: statistics.median(e["startup_cpu_s"].get(s, 0.0) for e in entries) for s in SERVICES
        }
        table[key] = row
    full = table.get("1000")
    for row in table.values():
        if full:
            row["cpu_over_1000"] = round(
                row["all_cpu_s_per_sim_s"] / full["all_cpu_s_per_sim_s"], 3
            )
            row["lockstep_over_1000"] = round(row["lockstep_speed"] / full["lockstep_speed"], 2)
    return table


def markdown(table: dict[str, Any]) -> str:
    head = (
        "| bus rate (Hz) | " + " | ".join(SERVICES) + " | all | vs 1000 Hz | verdicts | "
        "lockstep speed | path RMS (mm) | in-process / bare mj_step | load |"
    )
    lines = [head, "| " + " | ".join(["---:"] * (len(SERVICES) + 8)) + " |"]
    for rate, row in table.items():
        cells = [f"{row['running_cpu_s_per_sim_s'][s]:.2f}" for s in SERVICES]
        lines.append(
            f"| {rate} | " + " | ".join(cells) + f" | {row['all_cpu_s_per_sim_s']:.2f} | "
            f"{row.get('cpu_over_1000', '-')} | {', '.join(map(str, row['verdicts']))} | "
            f"{row['lockstep_speed']:.2f}x | {row['path_error_rms_m'] * 1e3:.3f} | "
            f"{row['inprocess_over_bare']:.3f} | {row['load_average_1min']:.2f} |"
        )
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rates", type=float, nargs="+", default=[100, 200, 250, 500, 1000])
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0, help="the realtime grasp's seed")
    parser.add_argument(
        "--ordinary-user",
        action="store_true",
        help="run the realtime grasp as nobody (no SCHED_FIFO, default limits)",
    )
    parser.add_argument("--path-s", type=float, default=30.0, help="in-process path (sim s)")
    parser.add_argument("--json", type=Path, default=ROOT / "runs/bench/rate_sweep.json")
    parser.add_argument("--markdown", type=Path, default=ROOT / "runs/bench/rate_sweep.md")
    args = parser.parse_args()
    with contextlib.ExitStack() as stack:
        user = stack.enter_context(ordinary_user()) if args.ordinary_user else None
        rounds = [one_round(args.rates, args, user) for _ in range(args.rounds)]
    table = median_table(rounds, args.rates)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"rounds": rounds, "median": table}, indent=2) + "\n")
    text = markdown(table)
    args.markdown.parent.mkdir(parents=True, exist_ok=True)
    args.markdown.write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
