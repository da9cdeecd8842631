"""Benchmark: what the operator's eye view costs, A/B against the same run without it.

Realtime path following (recorder on) with the eye view off, on (JPEG frames) and on with
raw RGB frames, interleaved per repeat so that load from other users of the machine hits
every variant alike; optionally the realtime grasp demo off/on, which also measures the
eye-view latency from the HMD sample (path following has no HMD). Reports per run the
plant's realtime factor and overrun fraction, the recorder's and the renderer's CPU
share, frames rendered / received / received over SHM, the per-hop latency (count,
p50, p99 in ms), the .rrd size and the load average; then medians per variant and the
on/off ratios. Writes everything to JSON.

    .venv/bin/python tests/benchmarks/eyeview_cost.py --duration 60 --grasp
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

VARIANTS = {
    "off": ["eyeview.enabled=false"],
    "on": ["eyeview.enabled=true"],
    "on_raw": ["eyeview.enabled=true", "eyeview.jpeg_quality=0"],
}
GRASP_VARIANTS = ("off", "on")


def run(scenario: str, run_dir: Path, duration_s: float, overrides: list[str]) -> dict:
    out = run_dir / "summary.json"
    sets = [arg for o in overrides for arg in ("--set", o)]
    command = [sys.executable, "-m", "teleop.cli", "run", scenario, "--mode", "realtime",
               "--run-dir", str(run_dir), "--summary-json", str(out), "--quiet", *sets]  # fmt: skip
    if scenario == "path-following":
        command += ["--duration", str(duration_s)]
    load_before = os.getloadavg()[0]
    result = subprocess.run(
        command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        stdin=subprocess.DEVNULL,
    )  # fmt: skip
    if not out.exists():
        return {"error": result.stderr[-2000:]}
    summary = json.loads(out.read_text())
    services = summary["services"]
    eye = summary.get("eye_view") or {}
    rrd = Path(summary["rrd"])
    return {
        "realtime_factor": summary["realtime_factor"],
        "overrun_fraction": summary["overrun_fraction"],
        "success": summary.get("success"),
        "recorder_cpu_share": services["recorder"]["cpu_share"],
        "renderer_cpu_share": services.get("eyeview", {}).get("cpu_share"),
        "render_ms_p50": eye.get("render_ms_p50"),
        "frames_published": eye.get("frames_published"),
        "frames_received": eye.get("frames_received"),
        "frames_received_shm": eye.get("frames_received_shm"),
        "logged_bytes_per_frame": eye.get("logged_bytes_per_frame"),
        "latency_ms": eye.get("latency_ms"),
        "rrd_bytes": rrd.stat().st_size if rrd.exists() else None,
        "load_1min_before": load_before,
        "load_1min_after": os.getloadavg()[0],
    }


def median_of(runs: list[dict], key: str) -> float | None:
    values = [r[key] for r in runs if r.get(key) is not None]
    return statistics.median(values) if values else None


def describe(runs_by_variant: dict[str, list[dict]]) -> dict:
    keys = ("realtime_factor", "overrun_fraction", "recorder_cpu_share", "renderer_cpu_share",
            "render_ms_p50", "rrd_bytes", "logged_bytes_per_frame", "frames_received",
            "load_1min_before")  # fmt: skip
    medians = {v: {k: median_of(runs, k) for k in keys} for v, runs in runs_by_variant.items()}
    out: dict = {"medians": medians}
    off = medians.get("off", {})
    for variant, m in medians.items():
        if variant == "off":
            continue
        ratios = {}
        for key in ("realtime_factor", "recorder_cpu_share"):
            if off.get(key) and m.get(key) is not None:
                ratios[f"{key}_on_over_off"] = m[key] / off[key]
        if off.get("rrd_bytes") and m.get("rrd_bytes"):
            ratios["rrd_bytes_added"] = m["rrd_bytes"] - off["rrd_bytes"]
            frames = median_of(runs_by_variant[variant], "frames_received")
            if frames:
                ratios["rrd_bytes_per_frame"] = ratios["rrd_bytes_added"] / frames
        ratios["overrun_fraction_added"] = (m["overrun_fraction"] or 0) - (
            off.get("overrun_fraction") or 0
        )
        out[f"{variant}_vs_off"] = ratios
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=60.0, help="path following, s")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--grasp", action="store_true", help="also the realtime grasp A/B")
    parser.add_argument("--json", type=Path, default=Path("runs/bench/eyeview_cost.json"))
    args = parser.parse_args()
    report: dict = {"duration_s": args.duration, "cpus": os.cpu_count()}
    with tempfile.TemporaryDirectory(prefix="eyeview-") as tmp:
        path_runs: dict[str, list[dict]] = {v: [] for v in VARIANTS}
        grasp_runs: dict[str, list[dict]] = {v: [] for v in GRASP_VARIANTS}
        for i in range(args.repeat):
            for variant, overrides in VARIANTS.items():
                result = run("path-following", Path(tmp) / f"pf-{variant}-{i}", args.duration,
                             overrides)  # fmt: skip
                path_runs[variant].append(result)
                print(f"path-following {variant} #{i}: {json.dumps(result)}", flush=True)
            if args.grasp:
                for variant in GRASP_VARIANTS:
                    result = run("grasp", Path(tmp) / f"grasp-{variant}-{i}", 0.0,
                                 VARIANTS[variant])  # fmt: skip
                    grasp_runs[variant].append(result)
                    print(f"grasp {variant} #{i}: {json.dumps(result)}", flush=True)
    report["path_following"] = {"runs": path_runs, **describe(path_runs)}
    if args.grasp:
        report["grasp"] = {"runs": grasp_runs, **describe(grasp_runs)}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    for name in ("path_following", "grasp"):
        if name in report:
            print(
                name, json.dumps({k: v for k, v in report[name].items() if k != "runs"}, indent=1)
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
