"""Benchmark: an hour of `teleop up`: each service's memory and CPU, the loop's round
trip, the records lost and the recording's size, minute by minute; then what `teleop
down` leaves behind.

Starts `teleop up --mode realtime`: path following until stopped, or with --scenario
grasp the teleoperated stack (haptic device, HMD, scripted operator, eye view) playing
deploy/scenarios/grasp_loop.toml (the cube into the bin and back, over and over); every
service and the recorder writing its segments. Every --sample-every seconds: each
service's anonymous resident memory (RssAnon of its main process, /proc). Every minute:
each service's CPU (/proc utime + stime) over the simulated time the plant advanced (its
running summary), the records its running summary counts as dropped, the plant's stale
commands, and the recording's bytes on disk (every segment). All along, an observer on
the bus (the run's read-only credentials) takes every plant state: its lateness beyond
the bus period; in path following its round trip is the plant's state sent -> the
controller's command for it back at the plant (one host clock: the state the controller
answered is the newest one sent before the command's CONTROLLER_RX stamp); in the grasp,
the handle's sample -> the plant's state with the command made from it applied, sent
(PLANT_STATE_TX - HAPTIC_SAMPLE: the loop but its way back to the handle, which an
observer linked to the plant alone cannot see). p50/p99 per minute. At the end `teleop
down`, Rerun's check of every segment, and no process or shared-memory segment left.
Reports per service the memory at 1, 10, 30 and 60 minutes and the slope after the warm-
up (least squares, KB/s; the goal is under 10 KB/s). Writes JSON, its tables as markdown
and a plot (.md and .png beside it); `--markdown-from FILE.json` renders the tables of
an earlier report.

    .venv/bin/python tests/benchmarks/memory_soak.py --duration 3600 --json runs/soak.json
"""

from __future__ import annotations

import argparse
import bisect
import collections
import itertools
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

from teleop.bus.messages import PLANT_STATE, DropCounter, Stage
from teleop.bus.session import close_session, open_session, subscribe
from teleop.bus.topics import Topics
from teleop.core import markdown
from teleop.core.config import load_config
from teleop.core.rundir import incarnation_paths, segment_paths
from teleop.run.stack import IDLE_POLL
from teleop.run.supervise import Stack, StackError
from tests.rerun_check import rerun_verify_problems

DEFAULT_DURATION_S = 3600.0
DEFAULT_SAMPLE_EVERY_S = 5.0
# Samples before this are the warm-up (imports, first allocations, caches): not in the slope.
DEFAULT_WARMUP_S = 60.0
SLOPE_GOAL_KB_S = 10.0
MINUTE_S = 60.0
MARKS_MIN = (1, 10, 30, 60)
SHM_DIR = Path("/dev/shm")
UP_TIMEOUT_S = 300
CLOCK_TICKS_S = os.sysconf("SC_CLK_TCK")
GRASP_LOOP = "grasp_loop.toml"  # deploy/scenarios/
SENT_KEPT = 256  # the newest states' send stamps an answer is matched against


def teleop(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "teleop.cli", *args],
        capture_output=True, text=True, timeout=UP_TIMEOUT_S, stdin=subprocess.DEVNULL,
    )  # fmt: skip


def anon_kb(pid: int) -> int | None:
    """RssAnon of ``pid`` in KB (None: gone)."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    match = re.search(r"^RssAnon:\s+(\d+) kB", text, re.MULTILINE)
    return int(match[1]) if match else None


def cpu_s(pid: int) -> float | None:
    """User + system CPU of ``pid`` so far (s; None: gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS_S  # utime, stime


def slope_kb_s(t_s: list[float], kb: list[int]) -> float | None:
    """Least-squares slope of memory over time (KB/s)."""
    if len(t_s) < 2:
        return None
    return float(np.polyfit(np.array(t_s), np.array(kb, float), 1)[0])


def running_summary(run_dir: Path, service: str) -> dict:
    """The newest running summary of ``service`` ({} if none yet)."""
    for path in reversed(incarnation_paths(run_dir, service)):
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError):
            continue  # replaced meanwhile
    return {}


class RoundTrips:
    """Every plant state from the bus: its round trip (state sent -> the command that
    answers it back at the plant) and its lateness beyond the bus period, by minute of
    the observer's clock."""

    def __init__(self, period_ns: int, path_following: bool) -> None:
        self.period_ns = period_ns
        self.path_following = path_following
        self.lock = threading.Lock()
        self.sent_ns: collections.deque[int] = collections.deque(maxlen=SENT_KEPT)
        self.round_trip_ns: dict[int, list[int]] = collections.defaultdict(list)
        self.late_ns: dict[int, list[int]] = collections.defaultdict(list)
        self.start_ns = time.monotonic_ns()
        self.states = 0

    def __call__(self, rec: np.ndarray, rx_ns: int) -> None:
        trace = rec["trace_ns"]
        tx_ns, rx_controller_ns, rx_plant_ns = (
            int(trace[Stage.PLANT_STATE_TX]), int(trace[Stage.CONTROLLER_RX]),
            int(trace[Stage.PLANT_RX]),
        )  # fmt: skip
        minute = int((rx_ns - self.start_ns) // (MINUTE_S * 1e9))
        with self.lock:
            self.states += 1
            if self.sent_ns:
                self.late_ns[minute].append(max(tx_ns - self.sent_ns[-1] - self.period_ns, 0))
            sampled_ns = int(trace[Stage.HAPTIC_SAMPLE])
            if not self.path_following and 0 < sampled_ns <= tx_ns:
                self.round_trip_ns[minute].append(tx_ns - sampled_ns)
            if self.path_following and rx_controller_ns > 0 and rx_plant_ns > 0:
                i = bisect.bisect_right(self.sent_ns, rx_controller_ns)
                if i:
                    self.round_trip_ns[minute].append(rx_plant_ns - self.sent_ns[i - 1])
            if tx_ns > 0 and (not self.sent_ns or tx_ns > self.sent_ns[-1]):
                self.sent_ns.append(tx_ns)

    def minute(self, m: int) -> dict:
        with self.lock:
            trips = np.array(self.round_trip_ns.get(m, []), float) / 1e6
            late = np.array(self.late_ns.get(m, []), float) / 1e6
        out: dict = {"states": int(late.size + (m == 0))}
        if trips.size:
            out["round_trip_p50_ms"] = round(float(np.percentile(trips, 50)), 3)
            out["round_trip_p99_ms"] = round(float(np.percentile(trips, 99)), 3)
        if late.size:
            out["late_p99_ms"] = round(float(np.percentile(late, 99)), 3)
            out["late_max_ms"] = round(float(late.max()), 3)
        return out


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


def minute_row(
    run_dir: Path, pids: dict[str, int], before: dict, trips: RoundTrips, m: int
) -> dict:
    """One minute's figures: CPU per simulated s per service, drops, stale commands,
    recording bytes, round trip; ``before`` (the last minute's counters) is updated."""
    plant = running_summary(run_dir, "plant")
    sim_s = plant.get("sim_time_s", 0.0)
    row: dict = {"minute": m + 1, "sim_s": round(sim_s, 1), **trips.minute(m)}
    sim_step = sim_s - before.get("sim_s", 0.0)
    cpu: dict[str, float | None] = {}
    dropped = 0
    for name, pid in pids.items():
        now = cpu_s(pid)
        last = before.get(("cpu", name))
        known = now is not None and last is not None and sim_step > 0
        cpu[name] = round((now - last) / sim_step, 3) if known else None
        before[("cpu", name)] = now
        dropped += int(running_summary(run_dir, name).get("dropped_messages", 0) or 0)
    row["cpu_s_per_sim_s"] = cpu
    # The idle pollers run at SCHED_IDLE: they take only CPU nothing else wants.
    row["cpu_all"] = round(
        sum(v for name, v in cpu.items() if v is not None and not name.startswith(IDLE_POLL)), 3
    )
    row["dropped_records"] = dropped
    row["stale_commands"] = plant.get("stale_commands")
    paths = segment_paths(run_dir / "recording.rrd")
    row["recording_mb"] = round(sum(p.stat().st_size for p in paths if p.exists()) / 1e6, 1)
    row["segments"] = len(paths)
    before["sim_s"] = sim_s
    return row


def _mean(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return round(float(np.mean(known)), 3) if known else None


def report_markdown(report: dict) -> str:
    """The report's two tables: each service's memory and CPU, the loop's figures over
    the first and the last ten minutes (or the run's first and last tenth)."""
    minutes = report["minutes"]
    span = max(1, min(10, len(minutes) // 2))
    first, last = minutes[:span], minutes[-span:]
    marks = [f"{m}_min_mb" for m in MARKS_MIN]
    header = ("service", *(f"{m} min" for m in MARKS_MIN), "slope after warm-up",
              f"CPU s per sim s, first / last {span} min")  # fmt: skip
    rows = []
    for name, figures in report["services"].items():
        cpu_first = _mean([r["cpu_s_per_sim_s"].get(name) for r in first])
        cpu_last = _mean([r["cpu_s_per_sim_s"].get(name) for r in last])
        rows.append((name, *(f"{figures[m]} MB" if m in figures else "-" for m in marks),
                     f"{figures['slope_kb_s']} KB/s", f"{cpu_first} / {cpu_last}"))  # fmt: skip
    lines = markdown.table(header, rows, "l" + "r" * (len(header) - 1))

    def row(label: str, key: str) -> tuple[object, ...]:
        return label, _mean([r.get(key) for r in first]), _mean([r.get(key) for r in last])

    per_min = [b["recording_mb"] - a["recording_mb"] for a, b in itertools.pairwise(minutes)]
    end = minutes[-1] if minutes else {}
    loop = [
        row("CPU s per simulated s, every service (idle pollers apart)", "cpu_all"),
        row("round trip p50 (ms, mean of the minutes)", "round_trip_p50_ms"),
        row("round trip p99 (ms, mean of the minutes)", "round_trip_p99_ms"),
        row("plant state lateness p99 (ms)", "late_p99_ms"),
        ("recording written (MB per minute)", _mean(per_min[:span]), _mean(per_min[-span:])),
        ("records dropped, stale commands (whole run)",
         f"{end.get('dropped_records')}, {end.get('stale_commands')}", ""),
    ]  # fmt: skip
    lines += ["", *markdown.table(("", f"first {span} min", f"last {span} min"), loop, "lrr")]
    return "\n".join(lines) + "\n"


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 10), sharex=True)
    for name, figures in report["services"].items():
        rows = figures["samples"]
        if rows:
            t, kb = zip(*rows, strict=True)
            axes[0].plot(np.array(t) / 60, np.array(kb) / 1024, label=name)
    axes[0].set_ylabel("anonymous memory (MB)")
    axes[0].legend(fontsize=7, ncol=3)
    minutes = report["minutes"]
    m = [r["minute"] for r in minutes]
    for key in ("round_trip_p50_ms", "round_trip_p99_ms"):
        axes[1].plot(m, [r.get(key, np.nan) for r in minutes], marker=".", label=key)
    axes[1].set_ylabel("round trip (ms)")
    axes[1].legend(fontsize=7)
    axes[2].plot(m, [r["recording_mb"] for r in minutes], marker=".", color="C0")
    axes[2].set_ylabel("recording on disk (MB)", color="C0")
    cpu_axis = axes[2].twinx()
    cpu_axis.plot(m, [r["cpu_all"] for r in minutes], marker=".", color="C1")
    cpu_axis.set_ylabel("CPU s per simulated s (all)", color="C1")
    cpu_axis.set_ylim(bottom=0)
    axes[2].set_xlabel("minute")
    fig.suptitle(f"teleop up, realtime {report.get('scenario', 'path-following')}")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=DEFAULT_DURATION_S, help="s")
    parser.add_argument("--sample-every", type=float, default=DEFAULT_SAMPLE_EVERY_S, help="s")
    parser.add_argument("--warmup", type=float, default=DEFAULT_WARMUP_S, help="s")
    parser.add_argument("--json", type=Path, help="where the report goes (required to run)")
    parser.add_argument("--run-dir", type=Path)
    parser.add_argument("--scenario", choices=("path-following", "grasp"), default="path-following",
                        help="grasp: the grasp loop, teleoperated")  # fmt: skip
    parser.add_argument(
        "--markdown-from", type=Path, help="print this report's tables, run nothing"
    )
    args = parser.parse_args()
    if args.markdown_from:
        report = json.loads(args.markdown_from.read_text())
        print(report_markdown(report), end="")
        plot(report, args.markdown_from.with_suffix(".png"))
        return 0
    if args.json is None:
        parser.error("--json FILE is required to run the soak")
    run_dir = args.run_dir or Path(tempfile.mkdtemp(prefix="soak-"))
    shm_before = set(os.listdir(SHM_DIR))
    scenario = []
    if args.scenario == "grasp":
        scenario = [
            "--set",
            'run.scenario="grasp"',
            "--set",
            f'operator.scenario_file="{GRASP_LOOP}"',
        ]
    up = teleop("up", "--mode", "realtime", "--run-dir", str(run_dir), *scenario)
    if up.returncode != 0:
        print(up.stderr, file=sys.stderr)
        return 1
    endpoint = re.search(r"bus: (\S+)", up.stdout)[1]
    stack = Stack.attach(run_dir)
    pids = {info["name"]: int(info["pid"]) for info in stack.process_infos()}
    observer = run_dir / "auth" / "observer.json"
    config = load_config(None, [f'bus.endpoint="{endpoint}"', "bus.gossip=false",
                                f'bus.credentials_file="{observer}"'])  # fmt: skip
    trips = RoundTrips(round(config.tick_s * 1e9), args.scenario == "path-following")
    session = open_session(config.bus, listen=False)
    topics = Topics(config.robot.robot_id)
    subs = [subscribe(session, topics.plant_state_batch, PLANT_STATE, trips, DropCounter(),
                      batched=True)]  # fmt: skip
    samples: dict[str, list[tuple[float, int]]] = {name: [] for name in pids}
    report: dict = {"scenario": args.scenario, "duration_s": args.duration,
                    "warmup_s": args.warmup, "run_dir": str(run_dir),
                    "load_average_start": os.getloadavg()}  # fmt: skip
    minutes: list[dict] = []
    before: dict = {}
    for name, pid in pids.items():
        before[("cpu", name)] = cpu_s(pid)
    start = time.monotonic()
    try:
        while (elapsed := time.monotonic() - start) < args.duration:
            for name, pid in pids.items():
                kb = anon_kb(pid)
                if kb is not None:
                    samples[name].append((round(elapsed, 1), kb))
            if elapsed >= (len(minutes) + 1) * MINUTE_S:
                minutes.append(minute_row(run_dir, pids, before, trips, len(minutes)))
                last = minutes[-1]
                print(f"minute {last['minute']}: CPU {last['cpu_all']} s/sim s, round trip "
                      f"p50 {last.get('round_trip_p50_ms')} p99 {last.get('round_trip_p99_ms')} "
                      f"ms, recording {last['recording_mb']} MB, dropped "
                      f"{last['dropped_records']}", flush=True)  # fmt: skip
            time.sleep(args.sample_every)  # the sampling period of a measurement
        report["restarts"] = {
            info["name"]: int(info["pid"]) != pids[info["name"]] for info in stack.process_infos()
        }
        report["load_average_end"] = os.getloadavg()
    finally:
        close_session(session, *subs)
        down = teleop("down", "--run-dir", str(run_dir))
    report["down_exit_code"] = down.returncode
    report["minutes"] = minutes
    report["rerun_verify"] = rerun_verify_problems(run_dir / "recording.rrd")
    services = {}
    for name, rows in samples.items():
        warm = [(t, kb) for t, kb in rows if t >= args.warmup]
        slope = slope_kb_s([t for t, _ in warm], [kb for _, kb in warm])
        at = {}
        for mark in MARKS_MIN:
            taken = [kb for t, kb in rows if t <= mark * MINUTE_S]
            if taken and rows[-1][0] >= mark * MINUTE_S - args.sample_every:
                at[f"{mark}_min_mb"] = round(taken[-1] / 1024, 1)
        services[name] = {
            **at,
            "end_mb": round(rows[-1][1] / 1024, 1) if rows else None,
            "slope_kb_s": None if slope is None else round(slope, 2),
            "within_goal": slope is not None and slope < SLOPE_GOAL_KB_S,
            "samples": rows,
        }
    report["services"] = services
    left = [name for name, pid in pids.items() if anon_kb(pid) is not None]
    try:
        Stack.attach(run_dir)
        supervisord_left = True
    except StackError:
        supervisord_left = False
    report["processes_left"] = left + (["supervisord"] if supervisord_left else [])
    new_shm = set(os.listdir(SHM_DIR)) - shm_before
    # Another run on the machine may own new segments too: ours are those nobody maps.
    report["shm_segments_left"] = sorted(new_shm - mapped_shm())
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    plot(report, args.json.with_suffix(".png"))
    args.json.with_suffix(".md").write_text(report_markdown(report))
    for name, figures in services.items():
        marks = ", ".join(f"{k.removesuffix('_mb')} {v}" for k, v in figures.items()
                          if k.endswith("_min_mb"))  # fmt: skip
        print(f"{name:14s} MB at {marks}; slope {figures['slope_kb_s']} KB/s")
    print(f"rerun rrd verify: {report['rerun_verify'] or 'every segment passes'}")
    print(f"left after down: processes {report['processes_left']}, "
          f"shm {report['shm_segments_left']}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
