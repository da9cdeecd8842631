"""Benchmark: where to render the eye view — a thread in the plant or a process of its own.

Two measurements, each against a baseline taken in the same run:

1. GIL: while a second thread renders frames back to back, how long is the main
   thread (a tight Python loop) kept from running? If MuJoCo held the GIL while it
   draws, the longest gap would be about one render; if it releases it, gaps stay
   near the interpreter's switch interval.
2. A plant-like loop: 1 kHz on absolute deadlines, a few ``mj_step`` per tick, run
   alone, with the renderer as a thread of the same process, and with the renderer
   as a separate process at ``eyeview.nice``; reports the fraction of ticks that wake
   more than 0.9 ms late (what the plant counts as overruns) and p99 lateness.

Writes medians over ``--repeat`` rounds to JSON.

    .venv/bin/python tests/benchmarks/eyeview_placement.py --seconds 10 --repeat 3
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import sys
import threading
import time
from pathlib import Path

import mujoco
import numpy as np

from teleop.config import load_config
from teleop.eyeview import EyeRenderer

TICK_S = 0.001  # the plant's period
LATE_S = 0.0009  # a tick this late is an overrun for the plant's loop timer
STEPS_PER_TICK = 3  # mj_step calls per tick: about the plant's work per tick
GIL_PROBE_S = 2.0


def _render_frames(stop: threading.Event, render_ms: list[float], paced: bool) -> None:
    config = load_config()
    eye = EyeRenderer(config)
    cfg = config.eyeview
    p_m = np.array(cfg.fixed_p_m)
    period_s = 1.0 / cfg.rate_hz
    try:
        while not stop.is_set():
            start = time.perf_counter()
            eye.render(p_m, cfg.fixed_yaw_rad, cfg.fixed_pitch_rad)
            render_ms.append((time.perf_counter() - start) * 1e3)
            if paced:
                stop.wait(max(0.0, period_s - (time.perf_counter() - start)))
    finally:
        eye.close()


def _render_process(stop: mp.Event, report: mp.Queue, nice: int) -> None:
    os.nice(nice)
    render_ms: list[float] = []
    flag = threading.Event()
    watcher = threading.Thread(target=lambda: (stop.wait(), flag.set()), daemon=True)
    watcher.start()
    _render_frames(flag, render_ms, paced=True)
    report.put(statistics.median(render_ms) if render_ms else 0.0)


def gil_probe() -> dict:
    """Longest stall of a pure-Python main thread while another thread renders."""
    stop = threading.Event()
    render_ms: list[float] = []
    thread = threading.Thread(target=_render_frames, args=(stop, render_ms, False))
    thread.start()
    while not render_ms:  # renderer built and one frame done
        time.sleep(0.01)
    gaps: list[float] = []
    end = time.perf_counter() + GIL_PROBE_S
    last = time.perf_counter()
    while last < end:
        now = time.perf_counter()
        gaps.append(now - last)
        last = now
    stop.set()
    thread.join()
    return {
        "render_ms_p50": statistics.median(render_ms),
        "main_thread_max_gap_ms": max(gaps) * 1e3,
        "switch_interval_ms": sys.getswitchinterval() * 1e3,
    }


def plant_like_loop(seconds: float) -> dict:
    model = mujoco.MjModel.from_xml_path(str(load_config().robot.scene_path))
    data = mujoco.MjData(model)
    late = []
    deadline = time.perf_counter()
    end = deadline + seconds
    while deadline < end:
        deadline += TICK_S
        pause = deadline - time.perf_counter()
        if pause > 0:
            time.sleep(pause)
        late.append(time.perf_counter() - deadline)
        for _ in range(STEPS_PER_TICK):
            mujoco.mj_step(model, data)
    lateness = np.array(late)
    return {
        "late_fraction": float(np.mean(lateness > LATE_S)),
        "lateness_p99_ms": float(np.percentile(lateness, 99) * 1e3),
    }


def one_round(seconds: float) -> dict:
    out = {"alone": plant_like_loop(seconds)}
    stop = threading.Event()
    render_ms: list[float] = []
    thread = threading.Thread(target=_render_frames, args=(stop, render_ms, True))
    thread.start()
    out["render_thread"] = plant_like_loop(seconds)
    stop.set()
    thread.join()
    out["render_thread"]["render_ms_p50"] = statistics.median(render_ms)
    ctx = mp.get_context("spawn")
    pstop, report = ctx.Event(), ctx.Queue()
    proc = ctx.Process(target=_render_process, args=(pstop, report, load_config().eyeview.nice))
    proc.start()
    time.sleep(2.0)  # let it import and build its renderer (not a sync point of the result)
    out["render_process"] = plant_like_loop(seconds)
    pstop.set()
    out["render_process"]["render_ms_p50"] = report.get(timeout=30)
    proc.join(30)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--json", type=Path, default=Path("runs/bench/eyeview_placement.json"))
    args = parser.parse_args()
    report: dict = {"load_1min_before": os.getloadavg()[0], "gil": gil_probe(), "rounds": []}
    for i in range(args.repeat):
        report["rounds"].append(one_round(args.seconds))
        print(f"round {i}: {json.dumps(report['rounds'][-1])}", flush=True)
    report["medians"] = {
        variant: {
            key: statistics.median(r[variant][key] for r in report["rounds"])
            for key in report["rounds"][0][variant]
        }
        for variant in ("alone", "render_thread", "render_process")
    }
    report["load_1min_after"] = os.getloadavg()[0]
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps({k: report[k] for k in ("gil", "medians")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
