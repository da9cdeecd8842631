"""How much of a CPU another process gets while an idle poller spins on it.

A CPU-bound process in a session of its own spins for ``--seconds`` on one CPU, first
alone (the baseline), then with a poller (services.idle_poll) on the same CPU; the ratio
of the two CPU shares is what the poller costs other work (1.0: nothing). Rounds
alternate the order. Writes JSON::

    .venv/bin/python tests/benchmarks/idle_poll_share.py --rounds 3 \\
        --json runs/bench/idle_poll_share.json
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

# Spins on the CPU given for the seconds given, then prints the share of them it got.
HOG = (
    "import os, sys, time; os.sched_setaffinity(0, {int(sys.argv[1])}); "
    "t0, c0 = time.monotonic(), time.process_time()\n"
    "while time.monotonic() - t0 < float(sys.argv[2]): pass\n"
    "print((time.process_time() - c0) / (time.monotonic() - t0))"
)
POLLER_START_WAIT_S = 10.0


def hog_share(cpu: int, seconds: float) -> float:
    done = subprocess.run(
        [sys.executable, "-c", HOG, str(cpu), str(seconds)],
        capture_output=True,
        text=True,
        check=True,
        start_new_session=True,
    )
    return float(done.stdout)


def with_poller(cpu: int, seconds: float) -> float:
    poller = subprocess.Popen(
        [sys.executable, "-m", "services.idle_poll", "--cpu", str(cpu)],
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + POLLER_START_WAIT_S
        while os.sched_getscheduler(poller.pid) != os.SCHED_IDLE:
            if time.monotonic() > deadline:
                raise RuntimeError("the poller did not start polling")
            time.sleep(0.02)
        return hog_share(cpu, seconds)
    finally:
        poller.send_signal(signal.SIGINT)
        poller.wait(POLLER_START_WAIT_S)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=2.0, help="each measurement's length")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--json", type=Path, default=Path("runs/bench/idle_poll_share.json"))
    args = parser.parse_args()
    cpu = max(os.sched_getaffinity(0))
    alone, polled = [], []
    for round_index in range(args.rounds):
        order = (False, True) if round_index % 2 == 0 else (True, False)
        for poll in order:
            share = with_poller(cpu, args.seconds) if poll else hog_share(cpu, args.seconds)
            (polled if poll else alone).append(share)
    result = {
        "cpu": cpu,
        "share_alone": alone,
        "share_with_poller": polled,
        "ratio_median": statistics.median(polled) / statistics.median(alone),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2) + "\n")
    print(
        f"CPU {cpu}: share alone {statistics.median(alone):.3f}, with a poller "
        f"{statistics.median(polled):.3f}: {result['ratio_median']:.2f}x"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
