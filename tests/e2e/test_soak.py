"""A short soak: a lockstep stack run long enough for a service that keeps what it has
already handled to show it, each service's memory sampled while it runs. A stack kept
up for an hour (`teleop up`) must use the same memory at its end as at its start; the
hour itself is the benchmark's (tests/benchmarks/memory_soak.py, docs/faults.md).
Lockstep, so the run is the same on a slow machine and a fast one."""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

from teleop.core.rundir import segment_paths
from tests.rerun_check import rerun_verify_problems

SIM_S = 180.0
SAMPLE_PERIOD_S = 0.25
# Small segments, so that the recorder closes dozens in the run: its memory rises while
# a segment fills and falls when it closes, and whatever a closed segment leaves behind
# adds up where it shows.
SEGMENT_MB = 2
# Largest growth allowed of a service's anonymous memory per simulated minute, from the
# run's second quarter to its last (the lowest sample of each: a recorder's memory right
# after a segment closed, what the segment left behind). What a loop keeps about itself
# lives in rings taken whole at the start (teleop.core.ring): a plant or controller that
# kept one number per record would grow by about 1 MB a simulated minute at the bus rate.
# The recorder closes about ten segments a simulated minute here, and in a run this
# short its heap's lows still rise as its threads' heaps settle (fragmentation, not a
# Python object: they level off within the hour's benchmark), by 1-6 MB a simulated
# minute from run to run; what this test is for, a Rerun stream kept per segment, would
# leave 4 MB a segment, 40 MB a minute.
MAX_GROWTH_KB_PER_SIM_MIN = {"plant": 512.0, "controller": 512.0, "recorder": 10240.0}
SERVICES = ("plant", "controller", "recorder")  # a lockstep path following's stack


def anon_kb(run_dir: Path) -> dict[str, int]:
    """Anonymous resident memory (KB) of each service process of the run in ``run_dir``
    (what the service allocated; its libraries' pages are not its growth)."""
    found = {}
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            argv = (proc / "cmdline").read_bytes().split(b"\0")
            status = (proc / "status").read_text()
        except OSError:
            continue  # gone meanwhile
        args = [a.decode(errors="replace") for a in argv]
        if str(run_dir) not in args or "-m" not in args:
            continue
        service = args[args.index("-m") + 1].removeprefix("services.")
        match = re.search(r"^RssAnon:\s+(\d+) kB", status, re.MULTILINE)
        if service in SERVICES and match:
            found[service] = int(match[1])
    return found


def growth_kb_per_sim_min(samples: list[dict[str, int]], name: str) -> float:
    """Lowest sample of the last quarter less the lowest of the second, per simulated
    minute between the two (the samples are even in wall time, lockstep's pace even)."""
    quarter = len(samples) // 4
    second = min(s[name] for s in samples[quarter : 2 * quarter])
    last = min(s[name] for s in samples[3 * quarter :])
    return (last - second) / (SIM_S / 2 / 60.0)


def test_no_service_grows_over_a_long_lockstep_run(tmp_path):
    run_dir = tmp_path / "soak"
    samples: list[dict[str, int]] = []
    with subprocess.Popen(
        [sys.executable, "-m", "teleop.cli", "run", "path-following", "--mode", "lockstep",
         "--duration", str(SIM_S), "--run-dir", str(run_dir), "--quiet",
         "--set", f"recorder.segment_mb={SEGMENT_MB}"],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    ) as run:  # fmt: skip
        while run.poll() is None:
            kb = anon_kb(run_dir)
            if set(kb) == set(SERVICES):  # every one up, none gone yet
                samples.append(kb)
            time.sleep(SAMPLE_PERIOD_S)  # the sampling period of a measurement
        stderr = run.stderr.read() if run.stderr else ""
    assert run.returncode == 0, stderr
    assert len(samples) >= 40, f"only {len(samples)} samples of the running stack"
    segments = segment_paths(run_dir / "recording.rrd")
    assert len(segments) >= 8, f"{len(segments)} segments: too few to judge the recorder"
    growth = {name: round(growth_kb_per_sim_min(samples, name)) for name in SERVICES}
    assert all(kb <= MAX_GROWTH_KB_PER_SIM_MIN[name] for name, kb in growth.items()), growth
    assert rerun_verify_problems(run_dir / "recording.rrd") == []
