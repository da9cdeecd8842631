"""Benchmark: where to render the eye view — a thread in the plant or a process of its own.

Two measurements, each against a baseline taken in the same run:

1. GIL: while a second thread renders frames back to back, how long is the main
   thread (a tight Python loop) kept from running? If MuJoCo held the GIL while it
   draws, the longest gap would be about one render; if it releases it, gaps stay
   near the interpreter's switch interval.
2. A plant-like loop: 1 kHz on absolute deadlines, a few ``mj_step`` per tick, in
   interleaved windows alone, with the renderer as a thread of the same process, and
   with the renderer as a separate process at ``eyeview.nice`` or at SCHED_IDLE (all
   at ``eyeview.rate_hz``); reports per variant the median over windows of the fraction
   of ticks that wake more than 0.9 ms late (what the plant counts as overruns) and of
   the p99 lateness.

Mesa's software rasteriser (llvmpipe) uses one thread per CPU unless ``LP_NUM_THREADS``
says otherwise; run it with the value to compare. Writes JSON.

    LP_NUM_THREADS=1 .venv/bin/python tests/benchmarks/eyeview_placement.py --windows 10
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

from services.eyeview import lower_priority
from teleop.core.config import load_config
from teleop.viz.eyeview import EyeRenderer

TICK_S = 0.001  # the plant's period
LATE_S = 0.0009  # a tick this late is an overrun for the plant's loop timer
STEPS_PER_TICK = 3  # mj_step calls per tick: about the plant's work per tick
GIL_PROBE_S = 2.0
IDLE_POLL_S = 0.01  # renderer threads poll their on/off event this often (s)
START_TIMEOUT_S = 60.0


def _render_frames(stop: threading.Event, active: threading.Event, render_ms: list[float]) -> None:
    """Render at ``eyeview.rate_hz`` while ``active`` is set, until ``stop``."""
    config = load_config()
    eye = EyeRenderer(config)
    cfg = config.eyeview
    p_m = np.array(cfg.fixed_p_m)
    period_s = 1.0 / cfg.rate_hz
    ready.set()
    try:
        while not stop.is_set():
            if not active.wait(IDLE_POLL_S):
                continue
            start = time.perf_counter()
            eye.render(p_m, cfg.fixed_yaw_rad, cfg.fixed_pitch_rad)
            render_ms.append((time.perf_counter() - start) * 1e3)
            time.sleep(max(0.0, period_s - (time.perf_counter() - start)))
    finally:
        eye.close()


ready = threading.Event()  # set by _render_frames once its renderer is built


def _render_process(
    stop: mp.Event, active: mp.Event, started: mp.Event, report: mp.Queue, idle: bool
) -> None:
    lower_priority(load_config().eyeview.nice, idle)
    render_ms: list[float] = []
    local_stop, local_active = threading.Event(), threading.Event()

    def mirror() -> None:  # mp events -> thread events, so the render loop is shared code
        while not stop.is_set():
            if active.wait(IDLE_POLL_S):
                local_active.set()
            else:
                local_active.clear()
        local_stop.set()

    threading.Thread(target=mirror, daemon=True).start()
    threading.Thread(target=lambda: (ready.wait(), started.set()), daemon=True).start()
    _render_frames(local_stop, local_active, render_ms)
    report.put(statistics.median(render_ms) if render_ms else 0.0)


def gil_probe() -> dict:
    """Longest stall of a pure-Python main thread while another thread renders."""
    stop, active = threading.Event(), threading.Event()
    render_ms: list[float] = []
    active.set()
    thread = threading.Thread(target=_render_frames, args=(stop, active, render_ms))
    thread.start()
    while not render_ms:  # renderer built and one frame done
        time.sleep(IDLE_POLL_S)
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


def plant_like_loop(seconds: float) -> np.ndarray:
    """Wake-up lateness (s) of every tick of a 1 kHz loop doing a plant's work per tick."""
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
            mujoco.mj_step(MODEL, DATA)
    return np.array(late)


MODEL = mujoco.MjModel.from_xml_path(str(load_config().robot.scene_path))
DATA = mujoco.MjData(MODEL)


def windows(count: int, window_s: float) -> dict:
    """Interleave 1 kHz windows: alone, with the render thread, with a render process at
    ``eyeview.nice``, with a render process at SCHED_IDLE.

    Every renderer stays built for the whole run and renders only in its own windows, so
    slow changes of the machine's load hit every variant alike.
    """
    stop, thread_active = threading.Event(), threading.Event()
    thread_ms: list[float] = []
    thread = threading.Thread(target=_render_frames, args=(stop, thread_active, thread_ms))
    thread.start()
    ctx = mp.get_context("spawn")
    pstop, report = ctx.Event(), ctx.Queue()
    procs = {}
    for variant, idle in (("render_process_nice", False), ("render_process_idle", True)):
        active, started = ctx.Event(), ctx.Event()
        proc = ctx.Process(target=_render_process, args=(pstop, active, started, report, idle))
        proc.start()
        procs[variant] = (proc, active, started)
    ready.wait(START_TIMEOUT_S)
    for _, _, started in procs.values():
        started.wait(START_TIMEOUT_S)
    events = {"alone": None, "render_thread": thread_active}
    events.update({variant: active for variant, (_, active, _) in procs.items()})
    late: dict[str, list[float]] = {variant: [] for variant in events}
    p99: dict[str, list[float]] = {variant: [] for variant in events}
    try:
        for _ in range(count):
            for variant, event in events.items():
                if event is not None:
                    event.set()
                lateness = plant_like_loop(window_s)
                if event is not None:
                    event.clear()
                late[variant].append(float(np.mean(lateness > LATE_S)))
                p99[variant].append(float(np.percentile(lateness, 99) * 1e3))
    finally:
        stop.set()
        pstop.set()
        thread.join()
        process_ms = [report.get(timeout=START_TIMEOUT_S) for _ in procs]
        for proc, _, _ in procs.values():
            proc.join(START_TIMEOUT_S)
    out = {
        variant: {
            "late_fraction_median": statistics.median(late[variant]),
            "late_fraction_per_window": late[variant],
            "lateness_p99_ms_median": statistics.median(p99[variant]),
        }
        for variant in events
    }
    out["render_thread"]["render_ms_p50"] = statistics.median(thread_ms)
    out["render_ms_p50_processes"] = process_ms
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--windows", type=int, default=10, help="windows per variant")
    parser.add_argument("--window-s", type=float, default=1.0)
    parser.add_argument("--json", type=Path, default=Path("runs/bench/eyeview_placement.json"))
    args = parser.parse_args()
    report: dict = {
        "load_1min_before": os.getloadavg()[0],
        "lp_num_threads": os.environ.get("LP_NUM_THREADS", "(Mesa default: one per CPU)"),
        "gil": gil_probe(),
    }
    ready.clear()
    report["loop"] = windows(args.windows, args.window_s)
    report["load_1min_after"] = os.getloadavg()[0]
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    summary = {
        k: {kk: vv for kk, vv in v.items() if "per_window" not in kk} if isinstance(v, dict) else v
        for k, v in report["loop"].items()
    }
    print(
        json.dumps(
            {"gil": report["gil"], "loop": summary, "lp": report["lp_num_threads"]}, indent=1
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
