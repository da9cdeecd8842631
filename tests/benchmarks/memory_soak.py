"""Benchmark: a long realtime `teleop up`, its services' memory over time, and what
`teleop down` leaves behind.

Starts `teleop up --mode realtime` (path following until stopped, every service and the
recorder writing its .rrd), samples each service's resident memory (VmRSS of its main
process, from /proc) every --sample-every seconds for --duration seconds, and watches
the plant's loop at the start and at the end: a window of its states from the bus (the
run's read-only observer credentials), the lateness of each state being the gap since
the previous one beyond the bus period (`loop.rate_hz`). Then `teleop down`, and
checks that no process of the stack and no shared-memory segment it made is left.
Reports, per service, the RSS slope after the warm-up (least squares, KB/s; the goal is
under 50 KB/s) and the p99 lateness at start and end. Writes JSON.

    .venv/bin/python tests/benchmarks/memory_soak.py --duration 600 --json runs/soak.json
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from teleop.bus.messages import PLANT_STATE, DropCounter
from teleop.bus.session import close_session, open_session, subscribe
from teleop.bus.topics import Topics
from teleop.core.config import load_config
from teleop.run.supervise import Stack, StackError

DEFAULT_DURATION_S = 600.0
DEFAULT_SAMPLE_EVERY_S = 5.0
# Samples before this are the warm-up (imports, first allocations, caches): not in the slope.
DEFAULT_WARMUP_S = 60.0
# The plant's loop is watched for this long at the start (after the warm-up) and the end.
LATENESS_WINDOW_S = 10.0
SLOPE_GOAL_KB_S = 50.0
SHM_DIR = Path("/dev/shm")
UP_TIMEOUT_S = 300


def teleop(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "teleop.cli", *args],
        capture_output=True, text=True, timeout=UP_TIMEOUT_S, stdin=subprocess.DEVNULL,
    )  # fmt: skip


def rss_kb(pid: int) -> int | None:
    """VmRSS of ``pid`` in KB (None: gone)."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    match = re.search(r"^VmRSS:\s+(\d+) kB", text, re.MULTILINE)
    return int(match[1]) if match else None


def slope_kb_s(t_s: list[float], kb: list[int]) -> float | None:
    """Least-squares slope of RSS over time (KB/s)."""
    if len(t_s) < 2:
        return None
    return float(np.polyfit(np.array(t_s), np.array(kb, float), 1)[0])


def plant_lateness_p99_ms(endpoint: str, observer: Path, window_s: float) -> dict:
    """p50/p99/max of the plant states' lateness (ms) over ``window_s``: each state's gap
    since the previous one beyond the period (its t_source_ns, the plant's clock)."""
    overrides = [f'bus.endpoint="{endpoint}"', "bus.gossip=false",
                 f'bus.credentials_file="{observer}"']  # fmt: skip
    config = load_config(None, overrides)
    stamps: list[int] = []
    lock = threading.Lock()

    def on_state(rec: np.ndarray, rx_ns: int) -> None:
        with lock:
            stamps.append(int(rec["t_source_ns"]))

    session = open_session(config.bus, listen=False)
    topics = Topics(config.robot.robot_id)
    sub = subscribe(session, topics.plant_state_batch, PLANT_STATE, on_state, DropCounter(),
                    batched=True)  # fmt: skip
    try:
        time.sleep(window_s)  # a measurement window, not a wait for an event
    finally:
        close_session(session, sub)
    gaps = np.diff(np.sort(np.array(stamps, np.int64)))
    period_ns = round(config.tick_s * 1e9)  # one state per bus period
    late_ms = np.maximum(gaps - period_ns, 0) / 1e6
    if not len(late_ms):
        return {"states": len(stamps)}
    return {
        "states": len(stamps),
        "p50_ms": round(float(np.percentile(late_ms, 50)), 3),
        "p99_ms": round(float(np.percentile(late_ms, 99)), 3),
        "max_ms": round(float(late_ms.max()), 3),
    }


def mapped_shm() -> set[str]:
    """Names under /dev/shm that some process maps now."""
    names = set()
    for maps in Path("/proc").glob("[0-9]*/maps"):
        try:
            text = maps.read_text()
        except OSError:
            continue
        names.update(re.findall(r"/dev/shm/(\S+)", text))
    return names


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=DEFAULT_DURATION_S, help="s")
    parser.add_argument("--sample-every", type=float, default=DEFAULT_SAMPLE_EVERY_S, help="s")
    parser.add_argument("--warmup", type=float, default=DEFAULT_WARMUP_S, help="s")
    parser.add_argument("--json", type=Path, required=True)
    parser.add_argument("--run-dir", type=Path)
    args = parser.parse_args()
    run_dir = args.run_dir or Path(tempfile.mkdtemp(prefix="soak-"))
    shm_before = set(os.listdir(SHM_DIR))
    up = teleop("up", "--mode", "realtime", "--run-dir", str(run_dir))
    if up.returncode != 0:
        print(up.stderr, file=sys.stderr)
        return 1
    endpoint = re.search(r"bus: (\S+)", up.stdout)[1]
    observer = run_dir / "auth" / "observer.json"
    stack = Stack.attach(run_dir)
    pids = {info["name"]: int(info["pid"]) for info in stack.process_infos()}
    samples: dict[str, list[tuple[float, int]]] = {name: [] for name in pids}
    report: dict = {"duration_s": args.duration, "warmup_s": args.warmup, "run_dir": str(run_dir)}
    start = time.monotonic()
    lateness_start: dict = {}

    def watch_start() -> None:
        lateness_start.update(plant_lateness_p99_ms(endpoint, observer, LATENESS_WINDOW_S))

    watcher = threading.Timer(args.warmup, watch_start)
    watcher.start()
    try:
        while (elapsed := time.monotonic() - start) < args.duration - LATENESS_WINDOW_S:
            for name, pid in pids.items():
                kb = rss_kb(pid)
                if kb is not None:
                    samples[name].append((elapsed, kb))
            time.sleep(args.sample_every)  # the sampling period of a measurement
        watcher.join()
        report["lateness_start"] = lateness_start
        report["lateness_end"] = plant_lateness_p99_ms(endpoint, observer, LATENESS_WINDOW_S)
        report["restarts"] = {
            info["name"]: int(info["pid"]) != pids[info["name"]] for info in stack.process_infos()
        }
    finally:
        down = teleop("down", "--run-dir", str(run_dir))
    report["down_exit_code"] = down.returncode
    services = {}
    for name, rows in samples.items():
        warm = [(t, kb) for t, kb in rows if t >= args.warmup]
        slope = slope_kb_s([t for t, _ in warm], [kb for _, kb in warm])
        services[name] = {
            "rss_start_mb": round(rows[0][1] / 1024, 1) if rows else None,
            "rss_end_mb": round(rows[-1][1] / 1024, 1) if rows else None,
            "slope_kb_s": None if slope is None else round(slope, 2),
            "within_goal": slope is not None and slope < SLOPE_GOAL_KB_S,
            "samples": rows,
        }
    report["services"] = services
    left = [name for name, pid in pids.items() if rss_kb(pid) is not None]
    try:
        Stack.attach(run_dir)
        supervisord_left = True
    except StackError:
        supervisord_left = False
    report["processes_left"] = left + (["supervisord"] if supervisord_left else [])
    new_shm = set(os.listdir(SHM_DIR)) - shm_before
    # Another run on the machine may own new segments too: ours are those nobody maps.
    report["shm_segments_left"] = sorted(new_shm - mapped_shm())
    report["shm_segments_new_but_mapped"] = sorted(new_shm & mapped_shm())
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    for name, figures in services.items():
        print(f"{name:14s} RSS {figures['rss_start_mb']} -> {figures['rss_end_mb']} MB, "
              f"slope {figures['slope_kb_s']} KB/s")  # fmt: skip
    print(f"plant lateness start {report['lateness_start']}, end {report['lateness_end']}")
    print(f"left after down: processes {report['processes_left']}, "
          f"shm {report['shm_segments_left']}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
