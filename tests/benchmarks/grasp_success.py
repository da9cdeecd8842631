"""Benchmark: the grasp-and-place task over many seeds, lockstep and realtime.

Each run is a full `teleop run grasp` (every service under supervisord). Writes the
per-run summaries and the success counts and duration distribution to JSON.

    .venv/bin/python tests/benchmarks/grasp_success.py --lockstep-seeds 20 --realtime-seeds 5
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

# Figures kept per run in the report.
KEYS = (
    "success",
    "object_in_box",
    "duration_s",
    "max_device_force_n",
    "max_contact_force_n",
    "obstacle_min_clearance_m",
    "max_obstacle_force_n",
    "tool_speed_max_m_s",
    "velocity_tracking_rms_m_s",
    "held_weight_n",
    "stale_feedback_events",
    "realtime_factor",
    "final_state_sha256",
)


def grasp_run(mode: str, seed: int, run_dir: Path, extra: list[str]) -> dict:
    out = run_dir / "summary.json"
    result = subprocess.run(
        [sys.executable, "-m", "teleop.cli", "run", "grasp", "--mode", mode, "--seed", str(seed),
         "--run-dir", str(run_dir), "--summary-json", str(out), "--quiet", *extra],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    if not out.exists():
        return {"success": False, "error": result.stderr[-2000:]}
    summary = json.loads(out.read_text())
    return {key: summary.get(key) for key in KEYS}


def describe(runs: list[dict]) -> dict:
    durations = [r["duration_s"] for r in runs if r.get("success") and r.get("duration_s")]
    return {
        "runs": len(runs),
        "successes": sum(bool(r.get("success")) for r in runs),
        "duration_s": {
            "median": statistics.median(durations) if durations else None,
            "min": min(durations, default=None),
            "max": max(durations, default=None),
        },
        "max_device_force_n": max((r.get("max_device_force_n") or 0 for r in runs), default=0),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--lockstep-seeds", type=int, default=20)
    parser.add_argument("--realtime-seeds", type=int, default=5)
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--json", type=Path, default=Path("runs/bench/grasp_success.json"))
    args = parser.parse_args()
    extra = [item for o in args.overrides for item in ("--set", o)]
    report: dict = {"overrides": args.overrides}
    with tempfile.TemporaryDirectory(prefix="grasp-") as tmp:
        for mode, count in (("lockstep", args.lockstep_seeds), ("realtime", args.realtime_seeds)):
            runs = []
            for seed in range(count):
                runs.append(grasp_run(mode, seed, Path(tmp) / f"{mode}{seed}", extra))
                print(f"{mode} seed {seed}: {runs[-1]}", flush=True)
            report[mode] = {"summary": describe(runs), "per_seed": runs}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    for mode in ("lockstep", "realtime"):
        s = report[mode]["summary"]
        print(f"{mode}: {s['successes']}/{s['runs']} succeeded, duration {s['duration_s']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
