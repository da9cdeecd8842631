"""Benchmark: what the 3D scene costs the recorder, and whether the plant keeps its period.

Realtime path following on the services, recorder on, alternating runs with the 3D scene
(``recorder.scene3d=true``: geoms, body transforms at ``recorder.scene_rate_hz``, ghost
poses) and without it; everything else (scalars, rates, hops, events) is logged in both.
Reports medians of the recorder's CPU share (process CPU time over wall time, one core
= 1.0), its flush time and the plant's overrun fraction, their ratios, and writes them
to a JSON file.

    .venv/bin/python tests/benchmarks/recorder_cost.py --duration 30 --repeat 3 \\
        --json runs/bench/recorder_cost.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path


def realtime_run(duration_s: float, run_dir: Path, scene3d: bool) -> dict:
    out = run_dir / "summary.json"
    subprocess.run(
        [sys.executable, "-m", "teleop.cli", "run", "path-following", "--mode", "realtime",
         "--duration", str(duration_s), "--run-dir", str(run_dir), "--summary-json", str(out),
         "--set", f"recorder.scene3d={'true' if scene3d else 'false'}", "--quiet"],
        check=True, stdout=subprocess.DEVNULL, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    summary = json.loads(out.read_text())
    recorder = json.loads((run_dir / "recorder.summary.json").read_text())
    return {
        "recorder_cpu_share": recorder["cpu_share"],
        "recorder_flush_wall_s_total": recorder["flush_wall_s_total"],
        "overrun_fraction": summary["overrun_fraction"],
        "realtime_factor": summary["realtime_factor"],
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=30.0, help="simulated s per run")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each kind")
    parser.add_argument("--json", type=Path, default=Path("runs/bench/recorder_cost.json"))
    args = parser.parse_args()
    runs: dict[str, list[dict]] = {"scene": [], "no_scene": []}
    with tempfile.TemporaryDirectory(prefix="bench-") as tmp:
        for i in range(args.repeat):
            for kind, scene3d in (("no_scene", False), ("scene", True)):
                result = realtime_run(args.duration, Path(tmp) / f"{kind}{i}", scene3d)
                runs[kind].append(result)
                print(f"run {i} {kind}: {result}")
    medians = {
        kind: {key: statistics.median(r[key] for r in results) for key in results[0]}
        for kind, results in runs.items()
    }
    base = medians["no_scene"]
    report = {
        "duration_s": args.duration,
        "repeat": args.repeat,
        "runs": runs,
        "medians": medians,
        "ratio_scene_over_no_scene": {
            key: (medians["scene"][key] / base[key] if base[key] else None) for key in base
        },
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps({k: report[k] for k in ("medians", "ratio_scene_over_no_scene")}, indent=2))
    print(f"written {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
