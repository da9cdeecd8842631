"""A person at the web page drives the arm (``teleop run grasp --operator web``): the
stack runs under supervisord, the launcher prints the page's URL with the run's token,
headless Chromium opens it (over the DevTools protocol, as tests/e2e/test_viewer.py
does) and the test acts as a person: a held 'f' presses the tool down to the table until
the force bar rises, a held key moves it back along the table, a mouse drag on the view
moves it right; a request without the token gets 403; 'q' ends the run. What moved is read from
the page's own state (``window.teleop``) and checked against the run's summary. The
screenshot, taken as the force shows, is kept in the run directory.

Needs Debian's Chromium (``make chromium``): skipped without it, unless
TELEOP_REQUIRE_CHROMIUM=1 makes that a failure."""

from __future__ import annotations

import base64
import contextlib
import json
import queue
import re
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.e2e.test_viewer import (
    CHROMIUM,
    REQUIRE_CHROMIUM,
    DevTools,
    _reader,
    _wait_line,
    headless_browser,
)

REPO = Path(__file__).resolve().parents[2]
URL_LINE = re.compile(r"web operator: open (http://\S+) ")
# The stack's start on a loaded 2-core machine (imports, models, links), then the page.
START_TIMEOUT_S = 90.0
PAGE_TIMEOUT_S = 20.0
EXIT_TIMEOUT_S = 40.0
POLL_S = 0.1
# How long a key or a drag is held (s of wall time: the run is paced by the person's clock).
HOLD_S = 1.2
# Least displacement (m) a held input must give along its axis, and its share of the
# displacement (the view frame follows the head's yaw, so the world axes are near, not on).
MIN_MOVE_M = 0.02
# A tool slower than this (m/s) is at rest: what it moves on is below a millimetre.
REST_SPEED_M_S = 0.002
MIN_AXIS_SHARE = 0.8
# Drag: from the view's centre, this far to the right (CSS px; the page's full scale is 120).
DRAG_PX = 100
# The table's push-back (N, up in the view frame) the handle must render once the tool
# presses down on it (the controller's scene spring within clearance.slowdown_m: about
# 1.2 N there, under 0.1 N up before).
MIN_FORCE_N = 0.5
FORCE_TIMEOUT_S = 12.0
# The tool point is this low (m, world z; the table's top at 0) when the table pushes back.
TABLE_NEAR_M = 0.06
# DevTools key events of the keys used: key, code, Windows virtual key code.
KEYS = {
    "s": ("s", "KeyS", 83),
    "f": ("f", "KeyF", 70),
    "q": ("q", "KeyQ", 81),
    "+": ("+", "Equal", 187),
    "-": ("-", "Minus", 189),
    "Tab": ("Tab", "Tab", 9),
}


def _requires_chromium() -> None:
    if CHROMIUM is None:
        if REQUIRE_CHROMIUM:
            pytest.fail("TELEOP_REQUIRE_CHROMIUM=1 but no chromium: run `make chromium`")
        pytest.skip("no chromium (install it with `make chromium`)")


class Page:
    """The web operator's page in headless Chromium, driven as a person would."""

    def __init__(self, tools: DevTools) -> None:
        self.tools = tools

    def evaluate(self, expression: str) -> Any:
        reply = self.tools.call("Runtime.evaluate", expression=expression, returnByValue=True)
        assert "exceptionDetails" not in reply, reply
        return reply["result"].get("value")

    def state(self) -> dict[str, Any]:
        return self.evaluate("(window.teleop && window.teleop.state) || null") or {}

    def wait(self, what: str, condition: Callable[[dict[str, Any]], bool], timeout_s: float):
        """The page's state once ``condition`` holds (polled: the page updates at 20 Hz)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            state = self.state()
            if state and condition(state):
                return state
            time.sleep(POLL_S)
        raise AssertionError(f"{what}: not within {timeout_s} s; page state {self.state()}")

    def key(self, name: str, down: bool) -> None:
        key, code, vk = KEYS[name]
        event: dict[str, Any] = {"type": "keyDown" if down else "keyUp", "key": key,
                                 "code": code, "windowsVirtualKeyCode": vk}  # fmt: skip
        if down and len(key) == 1:
            event["text"] = key
        self.tools.call("Input.dispatchKeyEvent", **event)

    def press(self, name: str) -> None:
        self.key(name, True)
        self.key(name, False)

    def mouse(self, kind: str, x: float, y: float, *, held: bool) -> None:
        self.tools.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left",
                        buttons=1 if held else 0, clickCount=1)  # fmt: skip


def _moved(before: list[float], after: list[float], axis: int, sign: float) -> tuple[float, float]:
    """The displacement along ``axis`` (signed as asked) and its share of the whole."""
    delta = [a - b for a, b in zip(after, before, strict=True)]
    norm = sum(d * d for d in delta) ** 0.5
    return sign * delta[axis], (abs(delta[axis]) / norm if norm else 0.0)


@contextlib.contextmanager
def _web_run(run_dir: Path, *extra: str) -> Iterator[dict[str, Any]]:
    """``teleop run grasp --operator web`` (lockstep, the eye view on) with ``extra``
    arguments, its URL read from its stderr; stopped if the test leaves it running."""
    command = [sys.executable, "-m", "teleop.cli", "run", "grasp", "--operator", "web",
               "--mode", "lockstep", "--duration", "60",
               "--run-dir", str(run_dir), "--quiet", *extra]  # fmt: skip
    process = subprocess.Popen(
        command, cwd=REPO, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=_reader, args=(process.stderr, lines), daemon=True).start()
    try:
        url = _wait_line(lines, URL_LINE, START_TIMEOUT_S)
        yield {"process": process, "url": url, "run_dir": run_dir, "lines": lines}
    finally:
        if process.poll() is None:  # Ctrl-C: the launcher stops the stack it started
            process.send_signal(signal.SIGINT)
            process.wait(EXIT_TIMEOUT_S)


@pytest.fixture
def web_run(tmp_path) -> Iterator[dict[str, Any]]:
    with _web_run(tmp_path / "run") as run:
        yield run


def test_a_person_at_the_web_page_moves_the_arm_and_feels_the_table(web_run):
    _requires_chromium()
    wall_start = time.monotonic()
    url, run_dir = web_run["url"], web_run["run_dir"]
    base = url.split("?", 1)[0].rstrip("/")
    without_token = [
        urllib.request.Request(base + "/"),
        urllib.request.Request(base + "/state"),
        urllib.request.Request(url.replace("token=", "token=x")),
        urllib.request.Request(base + "/input", data=b"{}", method="POST"),
    ]
    for request in without_token:
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(request, timeout=PAGE_TIMEOUT_S)
        assert refused.value.code == 403, request.full_url
    shot = run_dir / "web_operator.png"
    with headless_browser() as tools:
        tools.call("Emulation.setFocusEmulationEnabled", enabled=True)
        tools.call("Page.navigate", url=url)
        _drive(Page(tools), shot)
    code = web_run["process"].wait(EXIT_TIMEOUT_S)
    wall_s = time.monotonic() - wall_start
    print(f"screenshot: {shot}")
    print(f"page open to run's end: {wall_s:.1f} s")
    assert code == 1  # ended by the person: the task did not succeed
    summary = json.loads((run_dir / "summary.json").read_text())
    operator = summary["services"]["operator"]
    assert operator["device"] == "web" and operator["task_done"] is True
    assert operator["failure"] == "ended by the person" and summary["success"] is False
    served = operator["web"]
    assert served["forbidden"] >= 4 and served["bad_inputs"] == 0
    assert served["pages"] == 1 and served["inputs"] > 10 and served["frames"] > 0
    assert served["ends"] == 1
    # Where the keys, the drag and the press on the table took the tool (world frame).
    assert operator["tool_end_m"][2] < TABLE_NEAR_M < operator["tool_start_m"][2]
    print(f"page input -> hand input: {operator['input_to_hand_ms']}")
    assert operator["input_to_hand_ms"]["inputs"] > 3
    assert summary["max_device_force_n"] >= MIN_FORCE_N
    assert summary["protective_stop"]["count"] == 0  # pressed on, never hit


def _drive(page: Page, shot: Path) -> None:
    """What the person does on the page (see the module docstring)."""
    page.wait("the page", lambda _: True, PAGE_TIMEOUT_S)
    start = page.wait(
        "the tool and a frame",
        lambda s: s.get("tool_p_m") is not None and page.evaluate("window.teleop.framesShown") > 0,
        PAGE_TIMEOUT_S,
    )
    assert start["phase"] == "reach" and start["holding"] is False
    assert page.evaluate("window.teleop.forbidden") is False

    # Full speed, then a held 'f' straight down to the table until its push-back shows
    # in the bar. First, from the start pose: the way down is clear of the scene's
    # virtual obstacle (at x 0.55), which a tool further forward would meet and be
    # steered around (as it should be), however far a held key took it.
    for _ in range(3):
        page.press("+")
    page.key("f", True)
    pressed = page.wait(
        "the table's push-back at the handle",
        lambda s: (
            s["tool_p_m"][2] < TABLE_NEAR_M
            and s["device_f_n"] is not None
            and s["device_f_n"][2] >= MIN_FORCE_N
        ),
        FORCE_TIMEOUT_S,
    )
    time.sleep(0.3)  # the bar drawn
    width = page.evaluate("document.getElementById('forcefill').style.width")
    # Let go before the screenshot: a held key keeps pushing for as long as a screenshot
    # takes on a busy machine (wall time), and a tool pushed into the table slides along
    # it (a slide of 12 cm, toward the obstacle, was seen), which the rest assumes not.
    page.key("f", False)
    png = base64.b64decode(page.tools.call("Page.captureScreenshot")["data"])
    shot.write_bytes(png)
    assert float(width.rstrip("%")) >= 100 * MIN_FORCE_N / page.evaluate(
        "window.teleop.config.force_full_scale_n"), width  # fmt: skip
    assert pressed["force_n"] >= MIN_FORCE_N
    assert pressed["tool_p_m"][2] < TABLE_NEAR_M, pressed["tool_p_m"]
    page.wait("the stop", lambda s: s["intent"]["v"] == [0, 0, 0], PAGE_TIMEOUT_S)
    for _ in range(2):  # back to a moderate speed for the moves along the table
        page.press("-")
    time.sleep(0.3)

    # A held 's': back along the table (the view frame's -x, the world's -x: the head
    # holds still, facing +x, for a person), away from the obstacle.
    on_table = page.state()["tool_p_m"]
    page.key("s", True)
    page.wait("motion back", lambda s: s["intent"]["v"][0] < 0, PAGE_TIMEOUT_S)
    time.sleep(HOLD_S)
    page.key("s", False)
    page.wait("the stop", lambda s: s["intent"]["v"] == [0, 0, 0], PAGE_TIMEOUT_S)
    time.sleep(0.3)
    after_key = page.state()["tool_p_m"]
    along, share = _moved(on_table, after_key, 0, -1.0)
    assert along > MIN_MOVE_M and share > MIN_AXIS_SHARE, (on_table, after_key)

    # A drag to the right on the view: right (the view frame's -y), toward open table.
    box = page.evaluate(
        "(() => { const r = document.getElementById('viewbox').getBoundingClientRect(); "
        "return [r.x, r.y, r.width, r.height]; })()"
    )
    x0, y0 = box[0] + box[2] / 2, box[1] + box[3] / 2
    page.mouse("mousePressed", x0, y0, held=True)
    for step in range(1, 6):
        page.mouse("mouseMoved", x0 + DRAG_PX * step / 5, y0, held=True)
    page.wait("motion right", lambda s: s["intent"]["v"][1] < 0, PAGE_TIMEOUT_S)
    time.sleep(HOLD_S)
    page.mouse("mouseReleased", x0 + DRAG_PX, y0, held=False)
    page.wait("the drag's end", lambda s: s["intent"]["v"] == [0, 0, 0], PAGE_TIMEOUT_S)
    time.sleep(0.3)
    after_drag = page.state()["tool_p_m"]
    along, share = _moved(after_key, after_drag, 1, -1.0)
    assert along > MIN_MOVE_M and share > MIN_AXIS_SHARE, (after_key, after_drag)

    # 'q' ends the run: the page shows the task done, not a success.
    page.press("q")
    done = page.wait("the task's end", lambda s: s["done"], PAGE_TIMEOUT_S)
    assert done["success"] is False


def _hold_back(page: Page) -> list[float]:
    """Hold 's' until the tool has moved MIN_MOVE_M back (the run goes at the machine's
    pace in lockstep: a time held says nothing of the distance), let go, wait for the
    stop; the tool's position before (world frame)."""
    before = page.state()["tool_p_m"]
    page.key("s", True)
    page.wait(
        "the tool moved back",
        lambda s: before[0] - s["tool_p_m"][0] > MIN_MOVE_M,
        PAGE_TIMEOUT_S,
    )
    page.key("s", False)
    page.wait("the stop", lambda s: s["intent"]["v"] == [0, 0, 0], PAGE_TIMEOUT_S)
    page.wait("the tool at rest", lambda s: s["tool_speed_m_s"] < REST_SPEED_M_S, PAGE_TIMEOUT_S)
    return before


def test_a_person_at_the_web_page_drives_two_robots_in_turn(tmp_path):
    """``--robots 2``: the keys move arm0; tab (the page's robot switch), and they move
    arm1 while arm0 holds still; 'q' ends both tasks."""
    _requires_chromium()
    with _web_run(tmp_path / "two", "--robots", "2") as run, headless_browser() as tools:
        tools.call("Emulation.setFocusEmulationEnabled", enabled=True)
        tools.call("Page.navigate", url=run["url"])
        page = Page(tools)
        page.wait(
            "arm0's run under way and its view",
            lambda s: (
                s.get("tool_p_m") is not None
                and s["robot"] == "arm0"
                and s["sim_s"] > 0.5
                and page.evaluate("window.teleop.framesShown") > 0
            ),
            START_TIMEOUT_S,
        )
        assert page.evaluate("document.getElementById('next').hidden") is False
        arm0_before = _hold_back(page)  # arm0
        arm0_after = page.state()["tool_p_m"]
        page.press("Tab")
        page.wait(
            "arm1 driven, the handle at rest",
            lambda s: s["robot"] == "arm1" and not s["settling"],
            PAGE_TIMEOUT_S,
        )
        assert "arm1 (2 robots)" in page.evaluate("document.getElementById('run').textContent")
        arm1_before = _hold_back(page)  # arm1
        arm1_after = page.state()["tool_p_m"]
        assert page.evaluate("window.teleop.switches") == 1
        page.press("q")
        code = run["process"].wait(EXIT_TIMEOUT_S)
    assert code == 1  # ended by the person: no success
    for before, after in ((arm0_before, arm0_after), (arm1_before, arm1_after)):
        along, share = _moved(before, after, 0, -1.0)
        assert along > MIN_MOVE_M and share > MIN_AXIS_SHARE, (before, after)
    summary = json.loads((run["run_dir"] / "summary.json").read_text())
    operator = summary["services"]["operator"]
    assert [(s["from"], s["to"]) for s in operator["robot_switches"]] == [(0, 1)]
    assert [s["robot"] for s in summary["services"]["haptic"]["robot_switches"]] == [1]
    assert operator["web"]["switches"] == 1
    arm0, arm1 = (operator["robots"][r] for r in ("arm0", "arm1"))
    # arm0 held still once the hand left it; arm1 had held still until the hand came.
    assert max(abs(e - a) for e, a in zip(arm0["tool_end_m"], arm0_after, strict=True)) < 0.003
    assert max(abs(s - b) for s, b in zip(arm1["tool_start_m"], arm1_before, strict=True)) < 0.003
