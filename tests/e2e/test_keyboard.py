"""A person at the terminal's keyboard does the grasp (``teleop run grasp --operator
keyboard``) in a real terminal: tmux runs the command, the test reads the screen as a
person would (tool, cube and bin positions, phase, holding) and presses keys until the
cube lies in the bin. The screens before, while holding the cube and after the release
are kept in the run directory; the run's summary must say success, with the phases read
from the world."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh

from teleop.bus.messages import HAND_INPUT, DropCounter
from teleop.bus.session import subscribe
from teleop.bus.topics import Topics
from teleop.core.config import load_config
from teleop.core.summary import RunSummary
from teleop.run.outside import write_observer_config
from teleop.viz.report import verdict_text
from tests.e2e.terminal import Terminal

REPO = Path(__file__).resolve().parents[2]
NUMBER = r"([+-]\d+\.\d+)"
# Keys of the default key map (teleop.devices.person.intent.DEFAULT_KEYS) per (axis, direction).
MOVE_KEYS = {(0, 1): "w", (0, -1): "s", (1, 1): "a", (1, -1): "d", (2, 1): "r", (2, -1): "f"}
SPEEDS = load_config().keyboard.speed_steps


@dataclass
class Screen:
    text: str
    tool: tuple[float, float, float] | None
    objects: dict[str, tuple[float, float, float]]
    phase: str | None
    holding: bool | None
    speed_step: int | None
    done: str | None  # "success" / "not a success" once the task is done

    @classmethod
    def read(cls, text: str) -> Screen:
        positions = {}
        for name in ("tool", "cube", "bin"):
            m = re.search(rf"^{name}\s+x {NUMBER}\s+y {NUMBER}\s+z {NUMBER}", text, re.M)
            if m:
                positions[name] = tuple(float(v) for v in m.groups())
        phase = re.search(r"phase: (\w+)", text)
        holding = re.search(r"holding: (yes|no)", text)
        step = re.search(r"speed step (\d+)/", text)
        done = re.search(r"task done: (success|not a success)", text)
        return cls(
            text,
            positions.pop("tool", None),  # type: ignore[arg-type]
            positions,  # type: ignore[arg-type]
            phase.group(1) if phase else None,
            holding.group(1) == "yes" if holding else None,
            int(step.group(1)) if step else None,
            done.group(1) if done else None,
        )


def _observer_hears_hand_inputs(run_dir: Path, timeout_s: float = 10.0) -> bool:
    heard = threading.Event()
    config = zenoh.Config.from_file(str(write_observer_config(run_dir)))
    session = zenoh.open(config)
    try:
        topics = Topics(load_config().robot.robot_id)
        sub = subscribe(session, topics.hand_input, HAND_INPUT, lambda rec, rx: heard.set(),
                        DropCounter())  # fmt: skip
        try:
            return heard.wait(timeout_s)
        finally:
            sub.undeclare()
    finally:
        session.close()


def where(condition: Callable[[Screen], bool]) -> Callable[[str], Screen | None]:
    """A screen reader for Terminal.wait_for: the screen once ``condition`` holds."""
    return lambda text: screen if condition(screen := Screen.read(text)) else None


def hold_until(terminal: Terminal, key: str, condition: Callable[[Screen], bool],
               timeout_s: float, what: str) -> Screen:  # fmt: skip
    """Hold ``key`` (a press every 0.1 s, as a held key repeats) until the screen shows
    ``condition``, then space: as a person does. A lockstep run that lags takes the keys
    as they are when it catches up, so a fixed number of taps may all go by while the run
    stands still (a busy machine), and the space after them stops it before it moved."""
    deadline = time.monotonic() + timeout_s
    while True:
        terminal.press(key)
        time.sleep(0.1)
        screen = Screen.read(terminal.screen())
        if condition(screen):
            terminal.press(" ")
            return screen
        if time.monotonic() > deadline:
            raise AssertionError(f"no {what} within {timeout_s:g} s; the screen:\n{screen.text}")


class Driver:
    """Moves the tool by keys, one axis at a time, watching the screen."""

    def __init__(self, terminal: Terminal) -> None:
        self.terminal = terminal

    def look(self) -> Screen:
        return Screen.read(self.terminal.screen())

    def speed(self, step: int) -> None:
        for _ in range(2 * len(SPEEDS)):
            now = self.look().speed_step
            if now == step:
                return
            self.terminal.press("+" if now is None or now < step else "-")
            time.sleep(0.15)

    def move_to(self, target: tuple[float, float, float], tolerance_m: float,
                timeout_s: float = 60.0) -> Screen:  # fmt: skip
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            screen = self.look()
            assert screen.tool is not None, screen.text
            error = [t - p for t, p in zip(target, screen.tool, strict=True)]
            axis = max(range(3), key=lambda i: abs(error[i]))
            if abs(error[axis]) < tolerance_m:
                self.terminal.press(" ")
                return screen
            distance = abs(error[axis])
            # Fast far away, slow near (0.1, 0.05, 0.025 m/s): faster steps can overshoot.
            self.speed(3 if distance > 0.06 else 2 if distance > 0.02 else 1)
            self.terminal.press(MOVE_KEYS[axis, 1 if error[axis] > 0 else -1])
            time.sleep(0.1)
            after = self.look()
            assert after.tool is not None, after.text
            left = target[axis] - after.tool[axis]
            if abs(left) < tolerance_m or left * error[axis] < 0:  # there, or past it
                self.terminal.press(" ")
                time.sleep(0.3)
        raise AssertionError(f"the tool did not reach {target}:\n{self.terminal.screen()}")


def test_a_person_at_the_keyboard_puts_the_cube_in_the_bin(tmp_path):
    run_dir = tmp_path / "keyboard"
    command = [sys.executable, "-m", "teleop.cli", "run", "grasp", "--operator", "keyboard",
               "--mode", "lockstep", "--duration", "150", "--run-dir", str(run_dir)]  # fmt: skip
    screens = run_dir / "screens"
    with Terminal(command, REPO) as terminal:
        drive = Driver(terminal)
        start = terminal.wait_for(
            where(lambda s: s.tool is not None and "cube" in s.objects),
            120.0,
            "tool and cube on the screen",
        )
        assert start.phase == "reach" and start.holding is False
        # A by-hand observer of the run hears the keyboard operator, which supervisord
        # does not run (teleop.run.outside links it to the launcher's terminal programs).
        assert _observer_hears_hand_inputs(run_dir), "no HAND_INPUT reached the observer"
        screens.mkdir(parents=True)
        (screens / "before.txt").write_text(start.text)
        cube, bin_p = start.objects["cube"], start.objects["bin"]
        drive.move_to((cube[0], cube[1], 0.15), 0.004)
        drive.move_to(cube, 0.004)  # the tool point at the cube's centre
        time.sleep(0.5)
        terminal.press("g")
        holding = terminal.wait_for(where(lambda s: bool(s.holding)), 20.0, "a grasp")
        assert holding.phase == "carry"
        (screens / "holding.txt").write_text(holding.text)
        time.sleep(0.8)  # the grip settles
        drive.move_to((cube[0], cube[1], 0.25), 0.01)
        drive.move_to((bin_p[0], bin_p[1], 0.25), 0.015)
        terminal.press("g")
        # Released over the bin: the phase says so (the task ends 0.5 s of sim time later,
        # and the run a moment after that, when the summary replaces the screen).
        after = terminal.wait_for(
            where(lambda s: s.phase == "placed" or s.done is not None), 30.0, "the release"
        )
        (screens / "after.txt").write_text(after.text)
        assert after.holding is not True
        code = terminal.wait_for(lambda _: terminal.exited(), 60.0, "the run's end")
        final = terminal.screen()
    print(f"screens: {sorted(str(p) for p in screens.iterdir())}")
    assert code == 0, final
    assert "success: the cube is in the bin" in final
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["success"] is True and summary["object_in_box"] is True
    assert [p["name"] for p in summary["phases"]] == ["reach", "carry", "placed"]
    operator = summary["services"]["operator"]
    assert operator["device"] == "keyboard" and operator["success"] is True
    latency = operator["input_to_hand_ms"]
    print(f"key press -> hand input: {latency}")
    assert latency["inputs"] > 10
    # The tool went where the keys took it: over the bin, the cube below it.
    end = operator["tool_end_m"]
    assert abs(end[0] - bin_p[0]) < 0.03 and abs(end[1] - bin_p[1]) < 0.03
    # The same verdict as a scripted run's, as the report gives it (teleop report renders
    # this section from the run's summary; its figures are tested on a scripted run).
    assert "- task: success" in "\n".join(verdict_text(RunSummary.from_json(summary)))
    assert (run_dir / "recording.rrd").stat().st_size > 0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["grasp", "--operator", "keyboard"], "keyboard: standard input or output is not a"),
        (["path-following", "--operator", "keyboard"], "path-following is not teleoperated"),
        (
            ["grasp", "--operator", "gamepad", "--set", 'gamepad.device="/nonexistent/event7"'],
            "/nonexistent/event7: no such device",
        ),
        (
            [
                "grasp",
                "--operator",
                "spacemouse",
                "--set",
                'spacemouse.device="/nonexistent/hidraw7"',
            ],
            "/nonexistent/hidraw7: no such device",
        ),
    ],
)
def test_a_device_that_cannot_be_read_is_refused_in_one_line(tmp_path, args, message):
    result = subprocess.run(
        [sys.executable, "-m", "teleop.cli", "run", *args, "--run-dir", str(tmp_path)],
        capture_output=True, text=True, stdin=subprocess.DEVNULL, timeout=60, cwd=REPO,
    )  # fmt: skip
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], result.stderr


def test_a_person_switches_robots_with_tab_and_each_moves_only_while_driven(tmp_path):
    """Two robots, one keyboard: the keys move arm0; tab, and the same keys move arm1
    while arm0 holds still; q ends both tasks (not a success)."""
    run_dir = tmp_path / "two"
    command = [sys.executable, "-m", "teleop.cli", "run", "grasp", "--operator", "keyboard",
               "--robots", "2", "--mode", "lockstep", "--duration", "60",
               "--run-dir", str(run_dir)]  # fmt: skip
    with Terminal(command, REPO) as terminal:
        first = terminal.wait_for(
            where(lambda s: s.tool is not None and "robot arm0 (2 robots)" in s.text),
            120.0,
            "arm0's tool on the screen",
        )
        assert "tab: drive the next robot" in first.text
        moved = hold_until(
            terminal,
            "w",  # forward, arm0
            lambda s: s.tool is not None and s.tool[0] > first.tool[0] + 0.01,
            30.0,
            "arm0's tool forward",
        )
        (run_dir / "arm0.txt").write_text(moved.text)
        time.sleep(0.5)  # the handle comes to rest: the haptic device switches there
        terminal.press("\t")
        second = terminal.wait_for(
            where(
                lambda s: (
                    s.tool is not None
                    and "robot arm1 (2 robots)" in s.text
                    and "switching" not in s.text
                )
            ),
            30.0,
            "arm1 driven, the handle at rest",
        )
        hold_until(
            terminal,
            "a",  # left, arm1
            lambda s: s.tool is not None and s.tool[1] > second.tool[1] + 0.01,
            30.0,
            "arm1's tool to the left",
        )
        terminal.press("q")
        code = terminal.wait_for(lambda _: terminal.exited(), 60.0, "the run's end")
        final = terminal.screen()
    assert code == 1, final  # ended by the person: no success
    summary = json.loads((run_dir / "summary.json").read_text())
    operator = summary["services"]["operator"]
    assert operator["device"] == "keyboard"
    assert [(s["from"], s["to"]) for s in operator["robot_switches"]] == [(0, 1)]
    assert [s["robot"] for s in summary["services"]["haptic"]["robot_switches"]] == [1]
    arm0, arm1 = (operator["robots"][r] for r in ("arm0", "arm1"))
    assert arm0["failure"] == arm1["failure"] == "ended by the person"
    # Each tool moved along its own robot's keys only: arm0 forward, arm1 left.
    d0 = [e - s for e, s in zip(arm0["tool_end_m"], arm0["tool_start_m"], strict=True)]
    d1 = [e - s for e, s in zip(arm1["tool_end_m"], arm1["tool_start_m"], strict=True)]
    assert d0[0] > 0.01 and abs(d0[1]) < 0.005, d0
    assert d1[1] > 0.01 and abs(d1[0]) < 0.005, d1
