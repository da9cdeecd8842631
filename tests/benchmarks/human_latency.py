"""Benchmark: from a person's input to the plant's first command that answers it, per
device and timing mode.

Each device drives a real run (``teleop run grasp --operator DEVICE``, a supervisord
stack): the keyboard through a tmux terminal (tests/e2e/terminal.py), the SpaceMouse
through a FIFO named like its hidraw node that gets its HID reports (this machine has no
input device; a gamepad needs a kernel event device and is not measured here), the web
page by the requests its script sends (the browser's own share left out). An
observer session of the run (its read-only credentials, teleop.run.outside) takes every
HAND_INPUT and every PLANT_STATE (the batched copy, with each state's trace stamps).

Inputs alternate every ``--period`` seconds between a move and a stop (keyboard: ``a``
and space; SpaceMouse: the cap pushed left and let go; web: half speed left and none).
For each input at ``t_input`` (this process's monotonic clock, the same clock as every
stamp on one host):

- ``input_to_hand_input``: to the first HAND_INPUT published after it whose target
  changed (terminal or device, the operator service, its pacing to the next decision);
- ``hand_input_to_plant``: from that HAND_INPUT to the first plant step whose command
  answers a haptic sample taken after it, at or after its ``valid_from_tick`` (the
  state's PLANT_APPLIED stamp): the haptic device, the controller and the plant;
- ``input_to_plant``: the two together, input to the plant's first answering command.

``hand_input_to_plant`` is the floor a device cannot beat, measured in the same run; the
report gives p50 and p99 of each, per device and mode, and the load average before each
run:

    .venv/bin/python -m tests.benchmarks.human_latency --inputs 40 \
        --json runs/bench/human_latency.json

Measure on a quiet machine (nothing else running).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import struct
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from teleop.bus.messages import HAND_INPUT, PLANT_STATE, DropCounter, Stage
from teleop.bus.session import subscribe
from teleop.bus.topics import Topics
from teleop.core.config import load_config
from teleop.run.outside import write_observer_config
from tests.e2e.terminal import Terminal

REPO = Path(__file__).resolve().parents[2]
SETTLE_TIMEOUT_S = 300.0
# A run's controls: send(move) gives one input (a move or a stop), end() ends the run.
Controls = tuple[Callable[[bool], None], Callable[[], None]]
Background = subprocess.Popen[bytes]  # a teleop run started in the background


# The parts of the latency (ms), as the module docstring names them.
PARTS = ("input_to_hand_input_ms", "hand_input_to_plant_ms", "input_to_plant_ms")


class Observed:
    """Every HAND_INPUT and PLANT_STATE an observer session of the run took."""

    def __init__(self, run_dir: Path) -> None:
        self.lock = threading.Lock()
        self.hands: list[tuple[int, int, tuple[float, ...]]] = []  # t_source, valid_from, target
        self.states: list[tuple[int, int, int]] = []  # seq, HAPTIC_SAMPLE, PLANT_APPLIED
        self.drops = DropCounter()
        config = zenoh.Config.from_file(str(write_observer_config(run_dir)))
        self.session = zenoh.open(config)
        topics = Topics(load_config().robot.robot_id)
        self.subscribers = [
            subscribe(self.session, topics.hand_input, HAND_INPUT, self._on_hand, self.drops),
            subscribe(self.session, topics.plant_state_batch, PLANT_STATE, self._on_state,
                      self.drops, batched=True),
        ]  # fmt: skip

    def _on_hand(self, rec: np.ndarray, rx_ns: int) -> None:
        with self.lock:
            self.hands.append((int(rec["t_source_ns"]), int(rec["valid_from_tick"]),
                               tuple(float(v) for v in rec["target_p_m"])))  # fmt: skip

    def _on_state(self, rec: np.ndarray, rx_ns: int) -> None:
        trace = rec["trace_ns"]
        with self.lock:
            self.states.append((int(rec["seq"]), int(trace[Stage.HAPTIC_SAMPLE]),
                                int(trace[Stage.PLANT_APPLIED])))  # fmt: skip

    def close(self) -> None:
        for sub in self.subscribers:
            sub.undeclare()
        self.session.close()


def answers(inputs_ns: list[int], observed: Observed) -> dict[str, list[float]]:
    """Per input: device, loop and total latency (ms); inputs with no answer are left out."""
    with observed.lock:
        hands = sorted(observed.hands)
        states = np.array(sorted(observed.states), dtype=np.int64).reshape(-1, 3)
    out: dict[str, list[float]] = {PARTS[0]: [], PARTS[1]: [], PARTS[2]: []}
    for t_input in inputs_ns:
        previous = None
        hand = None
        for t_source, valid_from, target in hands:
            if t_source > t_input and previous is not None and target != previous:
                hand = (t_source, valid_from)
                break
            previous = target
        if hand is None:
            continue
        t_hand, valid_from = hand
        answering = states[(states[:, 0] >= valid_from) & (states[:, 1] >= t_hand)]
        if not len(answering):
            continue
        applied = int(answering[np.argmin(answering[:, 0]), 2])
        out[PARTS[0]].append((t_hand - t_input) / 1e6)
        out[PARTS[1]].append((applied - t_hand) / 1e6)
        out[PARTS[2]].append((applied - t_input) / 1e6)
    return out


def percentiles(values: list[float]) -> dict[str, float] | None:
    if not values:
        return None
    p50, p99 = np.percentile(values, [50, 99])
    return {"p50": round(float(p50), 3), "p99": round(float(p99), 3), "n": len(values)}


def _command(device: str, mode: str, run_dir: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "teleop.cli", "run", "grasp", "--operator", device,
            "--mode", mode, "--duration", "600", "--run-dir", str(run_dir), *extra]  # fmt: skip


def _wait(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {what} within {timeout_s:g} s")
        time.sleep(0.1)


@contextmanager
def keyboard_run(
    mode: str, run_dir: Path
) -> Iterator[tuple[Callable[[bool], None], Callable[[], None]]]:
    """A keyboard run in tmux: (input(move), end())."""
    with Terminal(_command("keyboard", mode, run_dir), REPO) as terminal:
        _wait(lambda: "tool  x" in terminal.screen(), 120.0, "tool on the keyboard's screen")

        def send(move: bool) -> None:
            terminal.press("a" if move else " ")

        def end() -> None:
            terminal.press("q")
            _wait(lambda: terminal.exited() is not None, 120.0, "the run's end")

        yield send, end


@contextmanager
def background_run(
    command: list[str], run_dir: Path
) -> Iterator[tuple[subprocess.Popen[bytes], Path]]:
    """``command`` (a ``teleop run``) in the background, its stderr to a file, once the run
    has started (its first progress line); killed if still running at the end."""
    stderr = run_dir.parent / f"{run_dir.name}.stderr"
    with open(stderr, "w") as err:
        process = subprocess.Popen(command, cwd=REPO, stdin=subprocess.DEVNULL,
                                   stdout=subprocess.DEVNULL, stderr=err)  # fmt: skip
    try:
        _wait(lambda: "  sim " in stderr.read_text(), 120.0, "the run's start")
        yield process, stderr
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


@contextmanager
def spacemouse_run(mode: str, run_dir: Path) -> Iterator[Controls]:
    """A SpaceMouse run on a FIFO standing in for its hidraw node: (input(move), end())."""
    node = run_dir.parent / f"{run_dir.name}-dev" / "hidraw0"  # read as hidraw by its name
    node.parent.mkdir(parents=True)
    os.mkfifo(node)
    fd = os.open(node, os.O_RDWR)
    command = _command("spacemouse", mode, run_dir, "--set", f'spacemouse.device="{node}"')
    try:
        with background_run(command, run_dir) as (process, _):
            os.write(fd, struct.pack("<B3h", 1, 0, 0, 0))  # at rest: the device arms
            time.sleep(0.3)

            def send(move: bool) -> None:
                os.write(fd, struct.pack("<B3h", 1, -200 if move else 0, 0, 0))

            def end() -> None:
                process.terminate()
                process.wait(120)

            yield send, end
    finally:
        os.close(fd)
        node.unlink()


@contextmanager
def web_run(mode: str, run_dir: Path) -> Iterator[Controls]:
    """A web-page run, its page's requests sent by this process (what the page's script
    sends on a key or a drag: the browser's own share is left out): (input(move), end())."""
    with background_run(_command("web", mode, run_dir), run_dir) as (process, stderr):
        found = re.findall(r"web operator: open (http://\S+) ", stderr.read_text())
        assert found, f"no page address in {stderr}"
        base, _, query = found[0].partition("/?")
        token = urllib.parse.parse_qs(query)["token"][0]

        def post(path: str, body: dict[str, Any] | None) -> None:
            data = json.dumps(body).encode() if body is not None else b""
            request = urllib.request.Request(
                base + path, data=data, method="POST",
                headers={"X-Teleop-Token": token, "Content-Type": "application/json"},
            )  # fmt: skip
            with urllib.request.urlopen(request, timeout=10) as answer:
                answer.read()

        def send(move: bool) -> None:
            post("/input", {"v": [0.0, 0.5 if move else 0.0, 0.0], "gripper": False,
                            "clutch": False})  # fmt: skip

        def end() -> None:
            post("/end", None)
            process.wait(120)

        yield send, end


RUNS = {"keyboard": keyboard_run, "spacemouse": spacemouse_run, "web": web_run}


def settle(load_below: float, timeout_s: float) -> float:
    """Wait until the 1-minute load average is below ``load_below`` (a run's threads
    linger in it for minutes), at most ``timeout_s``; the seconds waited."""
    start = time.monotonic()
    while os.getloadavg()[0] >= load_below and time.monotonic() - start < timeout_s:
        time.sleep(5.0)
    return time.monotonic() - start


def measure(
    device: str, mode: str, inputs: int, period_s: float, work: Path, load_below: float
) -> dict[str, Any]:
    run_dir = work / f"{device}-{mode}"
    waited_s = settle(load_below, SETTLE_TIMEOUT_S)
    load = os.getloadavg()
    times: list[int] = []
    with RUNS[device](mode, run_dir) as (send, end):
        observed = Observed(run_dir)
        try:
            time.sleep(1.0)  # the observer's links
            for i in range(inputs):
                times.append(time.monotonic_ns())
                send(i % 2 == 0)
                time.sleep(period_s)
            time.sleep(1.0)  # the last answers, through the observers' batches
        finally:
            observed.close()
        end()
    found = answers(times, observed)
    return {
        "device": device,
        "mode": mode,
        "load_average_before": [round(v, 2) for v in load],
        "waited_for_load_s": round(waited_s),
        "inputs": inputs,
        "answered": len(found[PARTS[2]]),
        "hand_inputs_seen": len(observed.hands),
        "states_seen": len(observed.states),
        **{part: percentiles(values) for part, values in found.items()},
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--devices", default="keyboard,spacemouse,web")
    parser.add_argument("--modes", default="lockstep", help="comma-separated: lockstep,realtime")
    parser.add_argument("--inputs", type=int, default=40, help="inputs per run")
    parser.add_argument("--period", type=float, default=0.3, help="seconds between inputs")
    parser.add_argument("--json", type=Path, default=Path("runs/bench/human_latency.json"))
    parser.add_argument(
        "--load-below", type=float, default=1.0,
        help="before each run, wait (at most 5 min) for the 1-minute load average to fall "
        "below this: the previous run's threads linger in it",
    )  # fmt: skip
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="human-latency-") as work:
        for mode in args.modes.split(","):
            for device in args.devices.split(","):
                row = measure(device, mode, args.inputs, args.period, Path(work),
                              args.load_below)  # fmt: skip
                print(json.dumps(row), flush=True)
                rows.append(row)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"runs": rows}, indent=2) + "\n")
    print(f"written to {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
