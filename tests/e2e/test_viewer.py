"""Viewing a run: `teleop run --web` serves the Rerun web viewer, headless Chromium opens it
and a screenshot shows the 3D scene; `teleop view --web` serves a saved recording; the
path-following recording holds what its blueprint shows, and `teleop report` draws it.

One short lockstep path-following run with --web is shared by every test here. The
screenshot needs Debian's Chromium (`make chromium`); without it that test is skipped,
unless TELEOP_REQUIRE_CHROMIUM=1 (`make test-web`) makes it fail instead.
"""

from __future__ import annotations

import base64
import contextlib
import io
import itertools
import json
import os
import queue
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
from websockets.sync.client import ClientConnection, connect

from teleop.core.config import load_config
from teleop.viz import entities as ent
from teleop.viz import stream_writers
from teleop.viz.blueprint import view_specs
from teleop.viz.report import write_reports
from teleop.viz.rrd import Recording

RUN_TIMEOUT_S = 300.0  # the whole --web run, start-up included (a loaded 2-core machine)
EXIT_TIMEOUT_S = 30.0
HTTP_TIMEOUT_S = 10.0
SETTINGS = ["--duration", "3", "--seed", "0", "--set", "run.settle_s=1"]
URL_LINE = re.compile(r"web viewer: (http://\S+) \(Ctrl-C to stop\)")
EXIT_INTERRUPTED = 130  # the CLI's exit code after Ctrl-C

CHROMIUM = shutil.which("chromium")
REQUIRE_CHROMIUM = os.environ.get("TELEOP_REQUIRE_CHROMIUM") == "1"
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    # WebGL on the CPU (SwiftShader): without a GPU, Chromium needs this to offer WebGL.
    "--enable-unsafe-swiftshader",
    "--window-size=1600,1000",
    "--remote-debugging-port=0",
)
# Wait for the page to draw the scene: poll a screenshot this often, up to the timeout
# (the viewer's wasm, then the recording, load on a CPU renderer; slow on a busy machine).
SCREENSHOT_POLL_S = 3.0
SCREENSHOT_TIMEOUT_S = 240.0
# The scene is on screen when this share of the pixels has the table's brown (the model's
# table rgba 0.55 0.45 0.35, shaded): red well above blue, green above blue.
TABLE_PIXEL_SHARE = 0.01
DEVTOOLS_LINE = re.compile(r"DevTools listening on (ws://\S+)")  # Chromium's stderr


def _reader(stream: io.TextIOBase, lines: queue.Queue[str]) -> None:
    for line in stream:
        lines.put(line)


def _wait_line(lines: queue.Queue[str], pattern: re.Pattern[str], timeout_s: float) -> str:
    """The first match of ``pattern`` in the process's output lines (event driven)."""
    deadline = time.monotonic() + timeout_s
    seen = []
    while time.monotonic() < deadline:
        try:
            line = lines.get(timeout=max(deadline - time.monotonic(), 0.0))
        except queue.Empty:
            break
        seen.append(line)
        match = pattern.search(line)
        if match:
            return match.group(1)
    tail = "".join(seen)[-3000:]
    raise AssertionError(f"no match for {pattern.pattern!r} in:\n{tail}")


def _http_get(url: str) -> tuple[int, bytes]:
    with urllib.request.urlopen(url, timeout=HTTP_TIMEOUT_S) as response:
        return response.status, response.read()


def _grpc_port(url: str) -> int:
    return int(re.search(r"%3A(\d+)%2Fproxy", url).group(1))


def _port_open(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=1.0):
            return True
    except OSError:
        return False


def _interrupt(process: subprocess.Popen[str]) -> int:
    process.send_signal(signal.SIGINT)
    return process.wait(EXIT_TIMEOUT_S)


@pytest.fixture(scope="module")
def web_run(tmp_path_factory) -> Iterator[dict]:
    """`teleop run path-following --web`, after the run (it keeps serving until Ctrl-C)."""
    tmp = tmp_path_factory.mktemp("web_run")
    process = subprocess.Popen(
        [sys.executable, "-m", "teleop.cli", "run", "path-following", "--mode", "lockstep",
         *SETTINGS, "--web", "--run-dir", str(tmp / "run"), "--rrd", str(tmp / "run.rrd"),
         "--summary-json", str(tmp / "summary.json"), "--quiet"],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=_reader, args=(process.stderr, lines), daemon=True).start()
    try:
        url = _wait_line(lines, URL_LINE, RUN_TIMEOUT_S)
        yield {"process": process, "url": url, "tmp": tmp, "rrd": tmp / "run.rrd"}
    finally:
        if process.poll() is None:
            _interrupt(process)


def test_run_web_serves_the_viewer_page_until_ctrl_c(web_run):
    summary = json.loads((web_run["tmp"] / "summary.json").read_text())
    assert summary["rrd"] == str(web_run["rrd"])  # the file is written as well
    status, body = _http_get(web_run["url"])
    assert status == 200 and b"Rerun" in body
    assert _port_open(_grpc_port(web_run["url"]))  # where the recorder streamed the run


def test_headless_chromium_shows_the_scene(web_run):
    if CHROMIUM is None:
        if REQUIRE_CHROMIUM:
            pytest.fail("TELEOP_REQUIRE_CHROMIUM=1 but no chromium: run `make chromium`")
        pytest.skip("no chromium (install it with `make chromium`)")
    shot_path = web_run["tmp"] / "web_viewer.png"
    share = screenshot_until_scene(web_run["url"], shot_path)
    assert share >= TABLE_PIXEL_SHARE, f"no scene in {shot_path} ({share:.4f} table pixels)"


def table_pixel_share(png: bytes) -> float:
    """Share of the screenshot's pixels that have the table's brown."""
    rgb = matplotlib.image.imread(io.BytesIO(png), format="png")[..., :3] * 255.0
    red, green, blue = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    brown = (red - blue > 40) & (green - blue > 15) & (red > 90) & (red < 200)
    return float(np.mean(brown))


class DevTools:
    """A minimal Chrome DevTools Protocol client: one page, calls answered in order."""

    def __init__(self, ws: ClientConnection) -> None:
        self._ws = ws
        self._ids = itertools.count(1)
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        attached = self.call("Target.attachToTarget", targetId=target, flatten=True)
        self._session = attached["sessionId"]

    def call(self, method: str, **params: object) -> dict:
        call_id = next(self._ids)
        message: dict[str, object] = {"id": call_id, "method": method, "params": params}
        if getattr(self, "_session", None):
            message["sessionId"] = self._session
        self._ws.send(json.dumps(message))
        while True:
            reply = json.loads(self._ws.recv())
            if reply.get("id") == call_id:
                assert "error" not in reply, reply["error"]
                return reply["result"]


@contextlib.contextmanager
def headless_browser() -> Iterator[DevTools]:
    """Headless Chromium on a fresh profile, its DevTools session open, the page domain
    enabled; the browser ends with the context."""
    # Chromium's helper processes may still write into the profile for a moment after
    # the browser exits: a leftover file must not fail the test.
    with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as profile:
        browser = subprocess.Popen(
            [CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=_reader, args=(browser.stderr, lines), daemon=True).start()
        try:
            ws_url = _wait_line(lines, DEVTOOLS_LINE, EXIT_TIMEOUT_S)
            with connect(ws_url, max_size=None) as ws:
                tools = DevTools(ws)
                tools.call("Page.enable")
                yield tools
        finally:
            browser.terminate()
            browser.wait(EXIT_TIMEOUT_S)


def screenshot_until_scene(url: str, shot_path: Path) -> float:
    """Open ``url`` in headless Chromium and screenshot it until the scene shows (or the
    timeout); the last screenshot is written to ``shot_path``. The table-pixel share."""
    with headless_browser() as tools:
        tools.call("Page.navigate", url=url)
        share = 0.0
        deadline = time.monotonic() + SCREENSHOT_TIMEOUT_S
        while share < TABLE_PIXEL_SHARE and time.monotonic() < deadline:
            time.sleep(SCREENSHOT_POLL_S)
            png = base64.b64decode(tools.call("Page.captureScreenshot")["data"])
            shot_path.write_bytes(png)
            share = table_pixel_share(png)
        return share


def test_path_following_recording_holds_what_its_blueprint_shows(web_run):
    config = load_config(None, ['run.scenario="path-following"'])
    rec = Recording(web_run["rrd"])
    assert rec.has_blueprint
    data = rec.lists()
    n_status = len(data[ent.ENTITY_PATH_ERROR]["Scalars:scalars"])
    assert n_status > 0
    for spec in view_specs(config):
        for entity in spec.entities:
            assert len(data[entity]["Scalars:scalars"]) == n_status, entity
        for root in spec.subtrees:
            if root != ent.ENTITY_EYE_VIEW:  # the eye view is grasp only
                assert any(e == root or e.startswith(root + "/") for e in data), root
    strips = data[ent.ENTITY_DESIRED_PATH]["LineStrips3D:strips"]
    assert len(strips[0][0]) == stream_writers.DESIRED_PATH_POINTS


def test_report_draws_the_path_following_figures(web_run, tmp_path):
    (report,) = write_reports(web_run["rrd"], tmp_path, settle_s=1.0)
    assert {p.name for p in report.figures} == {
        "fig7_stroboscopic.png",
        "fig8_desired_vs_actual_path.png",
        "fig9_path_error.png",
        "fig_timing.png",
    }
    summary = json.loads((web_run["tmp"] / "summary.json").read_text())
    # The report sees the run's path error at the status rate, the run at every step:
    # the same error, sampled more sparsely (so never above it, and of its size).
    run_max_mm = summary["path_error_max_m"] * 1e3
    assert 0.5 * run_max_mm <= report.metrics["path_error_max_mm"] <= run_max_mm * (1 + 1e-9)


def test_view_web_serves_a_saved_recording_and_ctrl_c_stops_it(web_run):
    process = subprocess.Popen(
        [sys.executable, "-m", "teleop.cli", "view", str(web_run["rrd"]), "--web"],
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=_reader, args=(process.stdout, lines), daemon=True).start()
    try:
        url = _wait_line(lines, URL_LINE, EXIT_TIMEOUT_S)
        status, body = _http_get(url)
        assert status == 200 and b"Rerun" in body
    finally:
        assert _interrupt(process) == EXIT_INTERRUPTED
    assert not _port_open(_grpc_port(url))  # the server went with it


def test_view_and_report_refuse_a_missing_file(tmp_path):
    for command in ("view", "report"):
        result = subprocess.run(
            [sys.executable, "-m", "teleop.cli", command, str(tmp_path / "none.rrd")],
            capture_output=True, text=True, timeout=EXIT_TIMEOUT_S,
        )  # fmt: skip
        assert result.returncode == 2, result.stderr
        assert "none.rrd" in result.stderr
