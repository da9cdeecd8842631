"""A person at the terminal's keyboard drives the arm (``teleop run grasp --operator
keyboard``): the operator's place in the stack (teleop/devices/person/service.py), read
from the keys of the terminal the launcher runs in. No X server, no input group: it works over SSH
(``ssh -t``) and in tmux.

The screen (curses, redrawn ``keyboard.screen_rate_hz`` times a second) shows the run's
phase (read from the world), the tool's position and speed, the objects, the force the
handle renders as a bar (the emulated handle feels it; the keyboard cannot), the speed
step, gripper and clutch, and the keys. The keys are those of
:data:`teleop.devices.person.intent.DEFAULT_KEYS` (also under ``?``). In a run of several robots
(``--robots``) the screen shows the driven robot's world and tab drives the next one.
"""

from __future__ import annotations

import curses
import sys
import threading
import time
from typing import Any

from teleop.bus.messages import Button
from teleop.bus.service import service_main
from teleop.devices.person.intent import (
    DOWN,
    KEY_HELP,
    LEFT,
    PAGE_DOWN,
    PAGE_UP,
    RIGHT,
    SWITCH,
    SWITCH_HELP,
    TAB,
    UP,
    HandIntent,
    KeyboardIntent,
)
from teleop.devices.person.loop import PHASES
from teleop.devices.person.service import PersonOperatorService

# curses' codes of the special keys, by the names of the key map.
_SPECIAL_KEYS = {
    curses.KEY_UP: UP,
    curses.KEY_DOWN: DOWN,
    curses.KEY_LEFT: LEFT,
    curses.KEY_RIGHT: RIGHT,
    curses.KEY_PPAGE: PAGE_UP,
    curses.KEY_NPAGE: PAGE_DOWN,
    ord("\t"): TAB,
}
# The force bar's width (characters); its full scale is haptic.peak_force_n.
BAR_WIDTH = 30
_AXIS_WORDS = (("forward", "back"), ("left", "right"), ("up", "down"))


class KeyboardOperatorService(PersonOperatorService):
    device = "keyboard"

    def open(self) -> None:
        if not sys.stdin.isatty():
            raise RuntimeError("keyboard: standard input is not a terminal")
        self.keys = KeyboardIntent(self.config.keyboard)
        super().open()

    def intent(self, now_ns: int) -> HandIntent:
        return self.keys.intent(now_ns)  # the caller holds self.lock

    def interact(self, stop: threading.Event) -> None:
        curses.wrapper(self._screen, stop)

    def _screen(self, window: Any, stop: threading.Event) -> None:
        curses.curs_set(0)
        window.keypad(True)
        window.timeout(round(1000 / self.config.keyboard.screen_rate_hz))
        while not stop.is_set():
            code = window.getch()
            now_ns = time.monotonic_ns()
            if code != -1:
                key = _SPECIAL_KEYS.get(code) or (chr(code) if 0 <= code < 256 else "")
                with self.lock:
                    action = self.keys.press(key.lower() if len(key) == 1 else key, now_ns)
                if action is not None:
                    if action.kind == SWITCH:
                        self.switch_robot()
                    self.input_changed(now_ns)
                    if action.kind == "quit":
                        self.end_task()
            self._draw(window, now_ns)

    def take_robot(self, buttons: Button) -> None:
        self.keys.take_robot(buttons)  # the caller holds self.lock

    def _draw(self, window: Any, now_ns: int) -> None:
        with self.lock:
            lines = screen_lines(self, now_ns)
        window.erase()
        height, width = window.getmaxyx()
        for row, line in enumerate(lines[: height - 1]):
            window.addnstr(row, 0, line, width - 1)
        window.refresh()


def screen_lines(service: KeyboardOperatorService, now_ns: int) -> list[str]:
    """The screen's text (the caller holds the service's lock)."""
    cfg = service.config
    view, keys = service.loop.view, service.keys
    intent = keys.intent(now_ns)
    sim_s = max(view.tick, 0) * cfg.tick_s
    robots = len(service.robot_topics)
    driving = f"robot {service.robot_id}" + (f" ({robots} robots)" if robots > 1 else "")
    lines = [
        f"zenoh-teleop keyboard operator   {driving}   {cfg.run.mode}   sim {sim_s:6.1f} s",
    ]
    if view.tick < 0:
        lines.append("waiting for the run to start...")
    elif view.done:
        lines.append(f"task done: {'success' if view.success else 'not a success'}"
                     "   (the run ends in a moment)")  # fmt: skip
    else:
        phase = view.phase_name or "-"
        lines.append(f"phase: {phase} ({view.phase + 1}/{len(PHASES)})   "
                     f"holding: {'yes' if view.holding else 'no'}")  # fmt: skip
    if service.station.settling:
        lines.append(f"switching to robot {service.robot_id}: the handle comes to rest")
    if service.run_over.is_set():
        lines.append("the run has ended")
    if view.tool_p_m is not None:
        x, y, z = view.tool_p_m
        lines.append(f"tool  x {x:+.3f}  y {y:+.3f}  z {z:+.3f} m   "
                     f"speed {view.tool_speed_m_s:.3f} m/s")  # fmt: skip
    for name, p in (view.objects_p_m or {}).items():
        lines.append(f"{name:<5} x {p[0]:+.3f}  y {p[1]:+.3f}  z {p[2]:+.3f} m")
    force_n = view.force_n
    peak_n = cfg.haptic.peak_force_n
    filled = min(BAR_WIDTH, round(BAR_WIDTH * force_n / peak_n)) if peak_n > 0 else 0
    lines.append(f"force [{'#' * filled}{'.' * (BAR_WIDTH - filled)}] {force_n:4.1f} N")
    top_m_s = cfg.teleop.max_tool_speed_m_s * keys.speed_fraction
    moving = [
        _AXIS_WORDS[axis][0 if v > 0 else 1]
        for axis, v in enumerate(intent.velocity_fraction)
        if v != 0.0
    ]
    lines.append(
        f"speed step {keys.speed_index + 1}/{len(cfg.keyboard.speed_steps)} "
        f"({top_m_s:.2f} m/s)   gripper {'CLOSED' if keys.gripper_closed else 'open'}   "
        f"clutch {'ON' if keys.clutch else 'off'}   moving: {' '.join(moving) or 'no'}"
    )
    if keys.show_help:
        lines += ["", *KEY_HELP, *([SWITCH_HELP] if robots > 1 else [])]
    return lines


if __name__ == "__main__":
    sys.exit(service_main(KeyboardOperatorService))
