"""Benchmark: teleoperation across a delayed link, per force-feedback stabiliser.

Every run is a lockstep ``teleop run grasp`` (every service under supervisord) with
``site.emulated_round_trip_ms``: the operator's and the robot's site that far apart in
sim time (teleop/devices/haptic/loop.py, docs/sites.md). Lockstep runs are
deterministic: the figures do not depend on the machine's load, only the wall time does
(given per run, with the load average). The round trip is exact, the emulated one plus
the loop's own plant step, with no jitter.

1. The grasp task over seeds x round trips x stabilisers: per cell the successes, the
   task time, the peak device force and the passivity observer's least energy.
2. The contact case (deploy/scenarios/press.toml: the gripper pushed down on the table's
   clearance spring for 2.5 s) per round trip and stabiliser, with the spring as
   configured and ten times stiffer (a stiff contact): the observer's least energy, the
   device force's peak-to-peak over the last second of pushing (a sustained
   oscillation) and one figure per spring and round trip (handle height, device force,
   observer energy over time; none against tdpa).

    .venv/bin/python tests/benchmarks/delayed_teleop.py --seeds 5
    .venv/bin/python tests/benchmarks/delayed_teleop.py --seeds 0 --press-round-trips-ms 200

Writes ``results.json``, ``results.md`` and ``press_k<stiffness>_<round trip>ms.png`` into
``--out`` (default runs/bench/delayed_teleop).
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
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after the backend choice)
import numpy as np  # noqa: E402

from teleop.core import markdown  # noqa: E402
from teleop.core.config import STABILISERS, load_config  # noqa: E402
from teleop.viz import entities as r  # noqa: E402
from teleop.viz import rrd  # noqa: E402

PRESS_SCENARIO = "press.toml"
# The contact counts as made once the table's clearance spring pushes this hard (N).
CONTACT_N = 0.1
# The window at the end of the push judged for a sustained oscillation (s).
OSCILLATION_WINDOW_S = 1.0
HANDLE_Z = r.axis_entity(r.ENTITY_HAPTIC_P, "z")


def run_grasp(
    seed: int, round_trip_ms: float, stabiliser: str, run_dir: Path, extra: Sequence[str] = ()
) -> dict[str, Any]:
    """One lockstep run; its summary (``{"error": ...}`` when it wrote none), the wall
    time and the load average before it."""
    out = run_dir / "summary.json"
    command = [
        sys.executable, "-m", "teleop.cli", "run", "grasp", "--mode", "lockstep",
        "--seed", str(seed), "--run-dir", str(run_dir), "--summary-json", str(out), "--quiet",
        "--set", f"site.emulated_round_trip_ms={round_trip_ms:g}",
        "--set", f'teleop.stabiliser="{stabiliser}"', *extra,
    ]  # fmt: skip
    load = os.getloadavg()[0]
    start = time.monotonic()
    result = subprocess.run(
        command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        stdin=subprocess.DEVNULL, check=False,
    )  # fmt: skip
    wall_s = time.monotonic() - start
    if not out.exists():
        return {"error": result.stderr[-2000:], "wall_s": wall_s, "load_before": load}
    summary = json.loads(out.read_text())
    return {**summary, "wall_s": wall_s, "load_before": load}


def grasp_figures(summary: dict[str, Any]) -> dict[str, Any]:
    """What the grasp table keeps of a run's summary."""
    passivity = summary.get("passivity") or {}
    return {
        "success": bool(summary.get("success")),
        "duration_s": summary.get("duration_s"),
        "max_device_force_n": summary.get("max_device_force_n"),
        "observer_min_j": passivity.get("observer_min_j"),
        "dissipated_j": passivity.get("dissipated_j"),
        "failure": summary.get("failure") or summary.get("error"),
        "wall_s": round(summary["wall_s"], 1),
        "load_before": round(summary["load_before"], 2),
    }


def describe_cell(runs: list[dict[str, Any]]) -> dict[str, Any]:
    done = [run["duration_s"] for run in runs if run["success"] and run["duration_s"]]
    minima = [run["observer_min_j"] for run in runs if run["observer_min_j"] is not None]
    return {
        "runs": len(runs),
        "successes": sum(run["success"] for run in runs),
        "task_s_median": statistics.median(done) if done else None,
        "task_s_max": max(done, default=None),
        "max_device_force_n": max((run["max_device_force_n"] or 0.0 for run in runs), default=0),
        "observer_min_j": min(minima, default=None),
    }


def press_series(run_dir: Path) -> dict[str, rrd.Series]:
    """The handle's height, the device force, the clearance spring's force and the
    observer's energy of a press run, from its recording."""
    sim = rrd.Recording(run_dir / "recording.rrd").scalars(r.TIMELINE_SIM)
    names = {
        "handle_z_m": HANDLE_Z,
        "device_f_n": r.norm_entity("device"),
        "scene_f_n": r.norm_entity("scene"),
        "observed_j": r.ENTITY_PASSIVITY_OBSERVED,
    }
    return {name: sim[entity] for name, entity in names.items() if entity in sim}


def push_window_s(series: dict[str, rrd.Series], summary: dict[str, Any]) -> tuple[float, float]:
    """From the contact (the spring's push above CONTACT_N) to the lift (or the run's end)."""
    scene = series["scene_f_n"]
    touching = scene.t_s[scene.values > CONTACT_N]
    start = float(touching[0]) if len(touching) else float(scene.t_s[-1])
    lift = [p["sim_time_s"] for p in summary.get("phases") or [] if p["name"] == "lift"]
    return start, float(lift[0]) if lift else float(scene.t_s[-1])


def peak_to_peak(series: rrd.Series, start_s: float, end_s: float) -> float | None:
    inside = series.values[(series.t_s >= start_s) & (series.t_s <= end_s)]
    return float(np.ptp(inside)) if len(inside) else None


def press_figures(summary: dict[str, Any], series: dict[str, rrd.Series]) -> dict[str, Any]:
    start, end = push_window_s(series, summary)
    last = max(start, end - OSCILLATION_WINDOW_S)
    passivity = summary.get("passivity") or {}
    return {
        "contact_s": round(start, 3),
        "lift_s": round(end, 3),
        "observer_min_j": passivity.get("observer_min_j"),
        "observed_end_j": passivity.get("observed_j"),
        "dissipated_j": passivity.get("dissipated_j"),
        "max_device_force_n": summary.get("max_device_force_n"),
        "device_f_p2p_last_s_n": peak_to_peak(series["device_f_n"], last, end),
        "handle_z_p2p_last_s_m": peak_to_peak(series["handle_z_m"], last, end),
        "task_done": bool(summary.get("task_done")),
        "wall_s": round(summary["wall_s"], 1),
        "load_before": round(summary["load_before"], 2),
    }


def press_plot(
    runs: dict[str, dict[str, rrd.Series]], title: str, path: Path, contact_s: float
) -> None:
    """Handle height, device force and observer energy of each stabiliser's run."""
    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for stabiliser, series in runs.items():
        for ax, name, scale in zip(
            axes, ("handle_z_m", "device_f_n", "observed_j"), (1e3, 1.0, 1e3), strict=True
        ):
            s = series[name]
            ax.plot(s.t_s - contact_s, s.values * scale, linewidth=1.0, label=stabiliser)
    for ax, label in zip(
        axes, ("handle z (mm)", "device force (N)", "observer W (mJ)"), strict=True
    ):
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[2].axhline(0.0, color="black", linewidth=0.6)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[2].set_xlabel("time from the contact (s)")
    axes[0].set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def ms_list(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v.strip()]


def results_markdown(results: dict[str, Any]) -> str:
    rows = []
    for cell in results["grasp"]:
        d = cell["summary"]
        task = f"{d['task_s_median']:.1f} / {d['task_s_max']:.1f} s" if d["task_s_median"] else "-"
        least = f"{d['observer_min_j'] * 1e3:.2f} mJ" if d["observer_min_j"] is not None else "-"
        rows.append((f"{cell['round_trip_ms']:g} ms", cell["stabiliser"],
                     f"{d['successes']}/{d['runs']}", task, f"{d['max_device_force_n']:.2f} N",
                     least))  # fmt: skip
    header = ("round trip", "stabiliser", "successes", "task time median / max",
              "peak device force", "observer least W")  # fmt: skip
    lines = ["## Grasp across the emulated link", "", *markdown.table(header, rows, "rlrrrr")]
    rows = []
    for run in results["press"]:
        f = run["figures"]
        rows.append((f"{run['stiffness_n_per_m']:g} N/m", f"{run['round_trip_ms']:g} ms",
                     run["stabiliser"], f"{f['observer_min_j'] * 1e3:.2f} mJ",
                     f"{f['max_device_force_n']:.2f} N",
                     f"{f['device_f_p2p_last_s_n']:.3f} N / "
                     f"{f['handle_z_p2p_last_s_m'] * 1e3:.2f} mm",
                     f"{f['dissipated_j'] * 1e3:.1f} mJ"))  # fmt: skip
    header = ("spring", "round trip", "stabiliser", "observer least W", "device force peak",
              "last second: force p-p / handle p-p", "dissipated")  # fmt: skip
    lines += ["", "## Contact case (press.toml)", "", *markdown.table(header, rows, "rrlrrrr")]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=5, help="grasp seeds 0..N-1 (0: none)")
    parser.add_argument(
        "--round-trips-ms",
        type=ms_list,
        default=[0, 25, 50, 100, 200],
        help="grasp: emulated round trips (ms, comma separated)",
    )
    parser.add_argument(
        "--press-round-trips-ms",
        type=ms_list,
        default=[0, 100, 200],
        help="contact case: emulated round trips (ms; empty: none)",
    )
    parser.add_argument(
        "--stiff-factor",
        type=float,
        default=10.0,
        help="the stiff contact's spring, times teleop.scene_stiffness_n_per_m",
    )
    parser.add_argument(
        "--stabilisers",
        type=lambda text: [v for v in text.split(",") if v],
        default=list(STABILISERS),
        help=f"teleop.stabiliser values to compare (default: {','.join(STABILISERS)})",
    )
    parser.add_argument("--out", type=Path, default=Path("runs/bench/delayed_teleop"))
    args = parser.parse_args()  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    spring = load_config().teleop.scene_stiffness_n_per_m
    unknown = sorted(set(args.stabilisers) - set(STABILISERS))
    if unknown:
        parser.error(
            f"--stabilisers: unknown {', '.join(unknown)} (known: {', '.join(STABILISERS)})"
        )
    results: dict[str, Any] = {"stabilisers": args.stabilisers, "grasp": [], "press": []}
    with tempfile.TemporaryDirectory(prefix="delayed-") as tmp:
        for round_trip in args.round_trips_ms if args.seeds else []:
            for stabiliser in args.stabilisers:
                runs = []
                for seed in range(args.seeds):
                    where = Path(tmp) / f"grasp-{round_trip:g}-{stabiliser}-{seed}"
                    runs.append(grasp_figures(run_grasp(seed, round_trip, stabiliser, where)))
                    print(
                        f"grasp {round_trip:g} ms {stabiliser} seed {seed}: {runs[-1]}", flush=True
                    )
                cell = {"round_trip_ms": round_trip, "stabiliser": stabiliser, "runs": runs}
                results["grasp"].append({**cell, "summary": describe_cell(runs)})
    for stiffness in (spring, spring * args.stiff_factor):
        for round_trip in args.press_round_trips_ms:
            series_by: dict[str, dict[str, rrd.Series]] = {}
            contact = 0.0
            for stabiliser in args.stabilisers:
                where = args.out / "press" / f"k{stiffness:g}-{round_trip:g}ms-{stabiliser}"
                summary = run_grasp(0, round_trip, stabiliser, where, [
                    "--set", f'operator.scenario_file="{PRESS_SCENARIO}"',
                    "--set", f"teleop.scene_stiffness_n_per_m={stiffness:g}",
                ])  # fmt: skip
                if "error" in summary:
                    print(f"press run failed: {summary['error']}", file=sys.stderr)
                    return 1
                series = press_series(where)
                figures = press_figures(summary, series)
                series_by[stabiliser] = series
                contact = contact or figures["contact_s"]
                results["press"].append({
                    "stiffness_n_per_m": stiffness, "round_trip_ms": round_trip,
                    "stabiliser": stabiliser, "figures": figures,
                })  # fmt: skip
                print(
                    f"press k {stiffness:g} {round_trip:g} ms {stabiliser}: {figures}", flush=True
                )
            title = (
                f"Pushing on the table's spring ({stiffness:g} N/m), round trip {round_trip:g} ms"
            )
            press_plot(series_by, title, args.out / f"press_k{stiffness:g}_{round_trip:g}ms.png",
                       contact)  # fmt: skip
    (args.out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    (args.out / "results.md").write_text(results_markdown(results))
    print(results_markdown(results))
    print(f"written: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
