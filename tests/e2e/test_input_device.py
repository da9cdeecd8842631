"""A person on a SpaceMouse drives the arm (``teleop run grasp --operator spacemouse``),
with the device's own HID reports: a FIFO named like its hidraw node stands in for it
(this machine has no input devices), and the test writes the reports a SpaceMouse sends
(report 1: translation, little-endian int16 X, Y, Z; the device's Z points down) while
the service, under supervisord, reads and decodes them. Pushing the cap down and to the
left moves the tool down and to the left; after the service is killed and restarted,
pushing it forward moves the tool forward."""

from __future__ import annotations

import contextlib
import json
import os
import selectors
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
TRANSLATION = 1  # report id


def _report(x: int, y: int, z: int) -> bytes:
    return struct.pack("<B3h", TRANSLATION, x, y, z)


def _push(fd: int, x: int, y: int, z: int, seconds: float, period_s: float = 0.016) -> None:
    """One report every ``period_s`` (a SpaceMouse reports about every 8-16 ms)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        os.write(fd, _report(x, y, z))
        time.sleep(period_s)


def _wait_for_line(process: subprocess.Popen[str], text: str, timeout_s: float) -> list[str]:
    """Lines of the process's stderr up to the first holding ``text``."""
    assert process.stderr is not None
    selector = selectors.DefaultSelector()
    selector.register(process.stderr, selectors.EVENT_READ)
    lines: list[str] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if selector.select(timeout=0.5):
            line = process.stderr.readline()
            if not line:
                break
            lines.append(line)
            if text in line:
                return lines
    raise AssertionError(f"no {text!r} on stderr within {timeout_s:g} s:\n{''.join(lines)}")


@contextlib.contextmanager
def spacemouse_run(tmp_path: Path, *args: str) -> Iterator[tuple[subprocess.Popen, int, Path]]:
    """``teleop run grasp --operator spacemouse ARGS`` reading a FIFO named like a hidraw
    node, once the run has started: (the run's process, the FIFO's fd to write reports
    to, the run directory). On the way out the run is killed if still going."""
    node = tmp_path / "hidraw0"
    os.mkfifo(node)
    # Read-write: the FIFO always has a writer, so the service never reads its end.
    fd = os.open(node, os.O_RDWR)
    run_dir = tmp_path / "run"
    command = [sys.executable, "-m", "teleop.cli", "run", "grasp", "--operator", "spacemouse",
               "--mode", "lockstep", "--run-dir", str(run_dir), *args,
               "--set", f'spacemouse.device="{node}"']  # fmt: skip
    process = subprocess.Popen(
        command, cwd=REPO, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        _wait_for_line(process, "  sim ", 120.0)  # the run has started
        yield process, fd, run_dir
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
        os.close(fd)


def test_a_spacemouse_pushed_down_and_left_moves_the_tool_down_and_left(tmp_path):
    with spacemouse_run(tmp_path, "--duration", "6") as (process, fd, run_dir):
        _push(fd, 0, 0, 0, 0.3)  # at rest: the device arms
        _push(fd, -250, 0, 250, 1.5)  # left (-X) and down (+Z)
        _push(fd, 0, 0, 0, 0.5)
        _, stderr = process.communicate(timeout=120)
    # No task done: the run ends at its duration, not a success (exit 1), not a crash.
    assert process.returncode == 1, stderr
    summary = json.loads((run_dir / "summary.json").read_text())
    operator = summary["services"]["operator"]
    assert operator["device"] == "spacemouse" and operator["device_lost"] is None
    start, end = operator["tool_start_m"], operator["tool_end_m"]
    moved = [e - s for s, e in zip(start, end, strict=True)]
    print(f"the tool moved {moved} m; device input -> hand input {operator['input_to_hand_ms']}")
    assert moved[1] > 0.05 and moved[2] < -0.05, moved  # left (+y) and down
    assert abs(moved[0]) < 0.5 * min(abs(moved[1]), abs(moved[2])), moved
    assert summary["dropped_messages"] == 0


def test_a_killed_spacemouse_service_comes_back_and_drives_again(tmp_path):
    """The operator's service SIGKILLed mid-run (a fault injected at 1.5 s of sim time):
    supervisord restarts it, it joins the run under way at its newest tick, and the cap
    pushed forward after the restart moves the tool forward."""
    run = spacemouse_run(tmp_path, "--duration", "12", "--kill", "operator@1.5")
    with run as (process, fd, run_dir):
        log = run_dir / "logs" / "operator.log"
        deadline = time.monotonic() + 60.0
        while (log.read_text() if log.exists() else "").count("running (robot") < 2:
            assert time.monotonic() < deadline, "the operator's service did not come back"
            time.sleep(0.2)
        _push(fd, 0, 0, 0, 0.3)  # at rest: the new process arms
        _push(fd, 0, -250, 0, 1.5)  # forward (-Y)
        _push(fd, 0, 0, 0, 0.5)
        _, stderr = process.communicate(timeout=120)
    assert process.returncode == 1, stderr  # no task done, no failure
    summary = json.loads((run_dir / "summary.json").read_text())
    operator = summary["services"]["operator"]
    assert operator["joined_at_tick"] is not None and operator["joined_at_tick"] > 0
    assert summary["restarted_services"].get("operator") == 1
    start, end = operator["tool_start_m"], operator["tool_end_m"]
    moved = [e - s for s, e in zip(start, end, strict=True)]
    print(f"after the restart the tool moved {moved} m")
    assert moved[0] > 0.05 and abs(moved[1]) < 0.5 * moved[0], moved


def _buttons(fd: int, mask: int) -> None:
    """A buttons report (report 3: bit i is BTN_0 + i held), alone in the FIFO: the reads
    before and after it take whole reports (a hidraw node gives one report per read)."""
    time.sleep(0.5)
    os.write(fd, struct.pack("<BB", 3, mask))
    time.sleep(0.5)


def test_a_spacemouse_button_switches_robots_and_each_moves_only_while_driven(tmp_path):
    """``--robots 2`` with BTN_1 as the robot switch: the cap pushed left moves arm0;
    a press of BTN_1, and the cap pushed left moves arm1 while arm0 holds still."""
    switch = ("--robots", "2", "--set", 'spacemouse.switch_buttons=["BTN_1"]',
              "--set", "spacemouse.clutch_buttons=[]")  # fmt: skip
    with spacemouse_run(tmp_path, "--duration", "12", *switch) as (process, fd, run_dir):
        _push(fd, 0, 0, 0, 0.3)  # at rest: the device arms
        _push(fd, -250, 0, 0, 1.5)  # left (-X): arm0
        _push(fd, 0, 0, 0, 0.5)
        _buttons(fd, 0b10)  # BTN_1 pressed ...
        _buttons(fd, 0)  # ... and released
        time.sleep(1.5)  # the hand asks for no motion until the handle rests (0.25 s sim)
        _push(fd, -250, 0, 0, 1.5)  # left: arm1
        _push(fd, 0, 0, 0, 0.5)
        _, stderr = process.communicate(timeout=120)
    assert process.returncode == 1, stderr  # no task done: the run ends at its duration
    summary = json.loads((run_dir / "summary.json").read_text())
    operator = summary["services"]["operator"]
    assert [(s["from"], s["to"]) for s in operator["robot_switches"]] == [(0, 1)]
    assert [s["robot"] for s in summary["services"]["haptic"]["robot_switches"]] == [1]
    for robot_id in ("arm0", "arm1"):
        section = operator["robots"][robot_id]
        moved = [e - s for s, e in zip(section["tool_start_m"], section["tool_end_m"], strict=True)]
        print(f"{robot_id}'s tool moved {moved} m")
        # A robot not driven gets a centred handle: it holds still (0 mm).
        assert moved[1] > 0.02 and abs(moved[0]) < 0.5 * moved[1], (robot_id, moved)
