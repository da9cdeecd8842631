"""Benchmark: realtime teleoperation across two hosts over a real link that is slow or
breaks.

Every run is the realtime stack split across two sites (tests/e2e/sites.py: two network
namespaces, the operator site's monotonic clock three hours ahead in a time namespace
of its own, the routers over mutual TLS), the routers' link through the network
emulator (``teleop.bench.netem``) in the robot host's namespace. Needs root.

1. **Delay** (``--delays-ms``, one way): the grasp with ``tdpa`` (success, task time,
   the observer's least energy), and the stiff contact of docs/sites.md
   (``press.toml``, the table's spring ten times stiffer) per stabiliser: the
   observer's least W, the peak device force, force and handle peak to peak over the
   last second of the push (from the robot site's recording, as
   tests/benchmarks/delayed_teleop.py measures the emulated round trip).
2. **Cuts** (``--cuts-s``): the grasp with the link cut once for that long, ``--cut-after-s``
   after the routers first linked (mid-task): when the plant's watchdog braked after
   the cut began, the longest the handle still felt a force from the feedback that
   stopped (the haptic device's stale spells), when the plant resumed after the link
   came back, and the outcome.

    .venv/bin/python -m tests.benchmarks.sites_link --out runs/bench/sites_link

Writes ``results.json`` and ``results.md`` into ``--out``. Measure on a quiet machine:
the load average before each run is in the output.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from teleop.bench import sites as sites_bench
from teleop.bench.loop_stats import LatencyStats, across_clocks
from teleop.core import markdown
from teleop.core.config import STABILISERS, load_config
from teleop.core.rundir import HAPTIC_TRACE_FILE
from teleop.run.assemble import grasp_figures, robot_view
from tests.benchmarks.delayed_teleop import PRESS_SCENARIO, press_figures, press_series
from tests.e2e.hosts import two_hosts
from tests.e2e.sites import TwoSites

OPERATOR_CLOCK_AHEAD_S = 3 * 3600
NS_PER_MS = 1_000_000
FLOOR_PINGS = 2000
# The one robot's id: its services' names carry none, so its view takes them all.
ROBOT_ID = "arm0"


def ms_list(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v]


def one_run(
    tmp: Path, name: str, link: Sequence[str], settings: Sequence[str]
) -> tuple[TwoSites, dict[str, Any]]:
    """One realtime run across the two sites; the sites (their summaries read) and the
    run's common figures."""
    load = os.getloadavg()[0]
    start = time.monotonic()
    with contextlib.ExitStack() as stack:
        robot, operator = stack.enter_context(two_hosts())
        sites = stack.enter_context(
            TwoSites(robot, operator, tmp / name, mode="realtime",
                     operator_clock_ahead_s=OPERATOR_CLOCK_AHEAD_S, link=link)
        )  # fmt: skip
        sites.start(settings, strangers=False)
        sites.finish()
    plant, operator_summary = sites.summaries["plant"], sites.summaries["operator"]
    figures, _ = grasp_figures(robot_view(sites.summaries, ROBOT_ID, [ROBOT_ID]), [])
    loop = across_clocks(np.load(sites.operator_dir / HAPTIC_TRACE_FILE))
    return sites, {
        "load_before": round(load, 2),
        "wall_s": round(time.monotonic() - start, 1),
        "success": bool(operator_summary.get("success")) and bool(plant.get("object_in_box")),
        "task_done": bool(operator_summary.get("success")),
        "operator_failure": operator_summary.get("failure") or None,
        "plant_failure": plant.get("failure"),
        "realtime_factor": plant.get("realtime_factor"),
        "watchdog_brakes": plant.get("stale_commands"),
        "braked_steps": plant.get("stale_steps"),
        "steps": plant.get("steps"),
        "duration_s": figures["duration_s"],
        "max_device_force_n": figures["max_device_force_n"],
        "observer_min_j": (figures["passivity"] or {}).get("observer_min_j"),
        "stale_felt_max_ms": sites.summaries["haptic"]["stale_spells"]["felt_max_ms"],
        # The loop across the clocks: round trip on the operator site's, each way from the
        # estimated offset (robot minus operator site, s) within its uncertainty.
        "round_trip_ms": _p50_p99_ms(loop.round_trip_us),
        "operator_to_robot_ms": _p50_p99_ms(loop.operator_to_robot_us),
        "robot_to_operator_ms": _p50_p99_ms(loop.robot_to_operator_us),
        "clock_offset_s": loop.offset_s,
        "clock_offset_uncertainty_ms": (loop.offset_uncertainty_us or 0.0) / 1e3,
    }


def _p50_p99_ms(figures: LatencyStats | None) -> list[float] | None:
    if figures is None or figures.p50_us is None or figures.p99_us is None:
        return None
    return [figures.p50_us / 1e3, figures.p99_us / 1e3]


def delay_runs(tmp: Path, delay_ms: float, stabilisers: Sequence[str], stiff_k: float) -> list:
    """The grasp with tdpa, then the stiff press per stabiliser, at ``delay_ms`` one way."""
    link = ["--delay-ms", f"{delay_ms:g}"]  # 0: through the emulator all the same
    rows = []
    _, grasp = one_run(tmp, f"grasp-{delay_ms:g}", link,
                       ("--set", 'run.scenario="grasp"', "--set", "run.seed=0",
                        "--set", 'teleop.stabiliser="tdpa"'))  # fmt: skip
    rows.append({"case": "grasp", "delay_ms": delay_ms, "stabiliser": "tdpa", **grasp})
    print(f"grasp, {delay_ms:g} ms one way, tdpa: {grasp}", flush=True)
    for stabiliser in stabilisers:
        sites, run = one_run(tmp, f"press-{delay_ms:g}-{stabiliser}", link,
                             ("--set", 'run.scenario="grasp"', "--set", "run.seed=0",
                              "--set", f'operator.scenario_file="{PRESS_SCENARIO}"',
                              "--set", f"teleop.scene_stiffness_n_per_m={stiff_k:g}",
                              "--set", f'teleop.stabiliser="{stabiliser}"'))  # fmt: skip
        view = robot_view(sites.summaries, ROBOT_ID, [ROBOT_ID])
        summary = {**grasp_figures(view, [])[0], **run}
        series = press_series(sites.robot_dir)
        press = press_figures(summary, series)
        row = {"case": "press", "delay_ms": delay_ms, "stabiliser": stabiliser,
               "stiffness_n_per_m": stiff_k, **run, **press}  # fmt: skip
        rows.append(row)
        print(f"press {stiff_k:g} N/m, {delay_ms:g} ms one way, {stabiliser}: {row}", flush=True)
    return rows


def cut_run(tmp: Path, cut_s: float, after_s: float) -> dict[str, Any]:
    """The grasp with the link cut once for ``cut_s``, ``after_s`` after it first linked."""
    sites, run = one_run(tmp, f"cut-{cut_s:g}", ["--cut", f"{after_s:g}:{cut_s:g}"],
                         ("--set", 'run.scenario="grasp"', "--set", "run.seed=0"))  # fmt: skip
    cuts = sites.proxy_report.get("cuts") or []
    row: dict[str, Any] = {"case": "cut", "cut_s": cut_s, **run, "cuts": cuts}
    if cuts:
        began, ended = cuts[0]["start_ns"], cuts[0]["end_ns"]
        episodes = sites.summaries["plant"].get("watchdog_episodes_ns") or []
        # The brake the cut caused: the first to begin after the cut did.
        brake = next((e for e in episodes if e[0] >= began), None)
        if brake is not None:
            row["brake_after_cut_ms"] = (brake[0] - began) / NS_PER_MS
            row["resumed_after_link_ms"] = (brake[1] - ended) / NS_PER_MS if brake[1] else None
        spells = sites.summaries["haptic"]["stale_spells"]["spells"]
        row["longest_stale_spell_ms"] = max((s["missing_ms"] for s in spells), default=0.0)
    print(f"cut {cut_s:g} s: {row}", flush=True)
    return row


def _table(header: Sequence[str], rows: list[list[str]]) -> str:
    return "\n".join(markdown.table(header, rows))


def _pair(values: list[float] | None) -> str:
    return "-" if values is None else f"{values[0]:.1f} / {values[1]:.1f} ms"


def _first(values: list[float] | None) -> str:
    return "-" if values is None else f"{values[0]:.1f}"


def results_markdown(rows: list[dict[str, Any]]) -> str:
    def num(value: Any, fmt: str, scale: float = 1.0) -> str:
        return "-" if value is None else format(value * scale, fmt)

    grasp = [r for r in rows if r["case"] == "grasp"]
    press = [r for r in rows if r["case"] == "press"]
    cuts = [r for r in rows if r["case"] == "cut"]
    parts = []
    if grasp:
        parts.append(_table(
            ["one way", "stabiliser", "success", "task time", "observer's least W",
             "round trip p50 / p99", "out, back p50 (+- offset)", "realtime factor",
             "braked steps", "load before"],
            [[f"{r['delay_ms']:g} ms", r["stabiliser"], str(r["success"]),
              num(r["duration_s"], ".1f"), num(r["observer_min_j"], ".2f", 1e3) + " mJ",
              _pair(r["round_trip_ms"]),
              f"{_first(r['operator_to_robot_ms'])}, {_first(r['robot_to_operator_ms'])} "
              f"(+- {r['clock_offset_uncertainty_ms']:.1f})",
              num(r["realtime_factor"], ".3f"), f"{r['braked_steps']} / {r['steps']}",
              num(r["load_before"], ".2f")] for r in grasp],
        ))  # fmt: skip
    if press:
        parts.append(_table(
            ["one way", "stabiliser", "observer's least W", "peak device force",
             "force / handle peak to peak", "load before"],
            [[f"{r['delay_ms']:g} ms", r["stabiliser"],
              num(r["observer_min_j"], ".2f", 1e3) + " mJ", num(r["max_device_force_n"], ".2f"),
              f"{num(r['device_f_p2p_last_s_n'], '.2f')} N / "
              f"{num(r['handle_z_p2p_last_s_m'], '.1f', 1e3)} mm",
              num(r["load_before"], ".2f")] for r in press],
        ))  # fmt: skip
    if cuts:
        parts.append(_table(
            ["cut", "brake after the cut", "stale force felt (longest)", "resumed after the link",
             "outcome", "load before"],
            [[f"{r['cut_s']:g} s", num(r.get("brake_after_cut_ms"), ".0f") + " ms",
              num(r["stale_felt_max_ms"], ".0f") + " ms",
              num(r.get("resumed_after_link_ms"), ".0f") + " ms",
              "success" if r["success"] else (r["operator_failure"] or r["plant_failure"]
                                              or "failed"),
              num(r["load_before"], ".2f")] for r in cuts],
        ))  # fmt: skip
    return "\n\n".join(parts) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--delays-ms",
        type=ms_list,
        default=[0.0, 12.5, 25.0, 50.0],
        help="one-way delays of the link (ms, comma separated; empty: none; 0: through the "
        "emulator undelayed, the baseline)",
    )
    parser.add_argument(
        "--stabilisers",
        type=lambda t: [v for v in t.split(",") if v],
        default=list(STABILISERS),
        help="the press's stabilisers",
    )
    parser.add_argument(
        "--stiff-factor",
        type=float,
        default=10.0,
        help="the press's spring, times teleop.scene_stiffness_n_per_m",
    )
    parser.add_argument(
        "--cuts-s",
        type=ms_list,
        default=[0.5, 5.0],
        help="link cuts to try, one run each (s; empty: none)",
    )
    parser.add_argument(
        "--cut-after-s",
        type=float,
        default=15.0,
        help="when a cut begins, after the routers first linked (s)",
    )
    parser.add_argument("--out", type=Path, default=Path("runs/bench/sites_link"))
    args = parser.parse_args()  # fmt: skip
    unknown = sorted(set(args.stabilisers) - set(STABILISERS))
    if unknown:
        parser.error(f"--stabilisers: unknown {', '.join(unknown)}")
    if os.geteuid() != 0:
        parser.error("needs root (network and time namespaces)")
    args.out.mkdir(parents=True, exist_ok=True)
    stiff_k = load_config().teleop.scene_stiffness_n_per_m * args.stiff_factor
    rows: list[dict[str, Any]] = []
    # The floor under the stack's loop in the same run: two bare ends through the same
    # routers (teleop latency --across-sites), at the bus rate, per delay.
    rate_hz = load_config().loop.rate_hz
    floor = sites_bench.measure(
        FLOOR_PINGS,
        rate_hz,
        1,
        [d for d in args.delays_ms if d],
        progress=lambda line: print("floor:", line, flush=True),
    )
    with tempfile.TemporaryDirectory(prefix="sites-link-") as tmp:
        for delay_ms in args.delays_ms:
            rows += delay_runs(Path(tmp), delay_ms, args.stabilisers, stiff_k)
        for cut_s in args.cuts_s:
            rows.append(cut_run(Path(tmp), cut_s, args.cut_after_s))
    (args.out / "results.json").write_text(json.dumps({"floor": floor, "runs": rows}, indent=1))
    text = "\n".join(sites_bench.table(floor)) + "\n\n" + results_markdown(rows)
    (args.out / "results.md").write_text(text)
    print(text)
    print(f"written: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
