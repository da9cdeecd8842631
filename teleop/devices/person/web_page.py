"""The web page a person drives the arm from (``teleop run grasp --operator web``): the
page, its HTTP server and what it parses and sends. The bus side is services/web.py (the
operator's place in the stack, :class:`PageOperator` here).

The page (teleop/devices/person/web_page.html, one self-contained file read at start) is served on
127.0.0.1 only, at ``web.port``, by the standard library's HTTP server. Every request
carries the run's token (``web.token_file``, written by the launcher: see
teleop/run/web_operator.py): the page's URL has it in its query, and the page sends it in
the ``X-Teleop-Token`` header of every later request. No cookie: a browser sends a
cookie of 127.0.0.1 to every port of that host, another user's server included. A request
without the token gets 403 and is counted.

Endpoints:

- ``GET /?token=...``: the page, with the key map, speed steps and rates filled in.
- ``GET /state``: Server-Sent Events, ``web.state_rate_hz``: what the terminal's screen
  shows (services/keyboard.py's ``screen_lines``) as JSON: the robot driven, tick, phase,
  tool position and speed, objects, holding, the force the handle renders (N), done and
  success, the intent applied, the newest eye-view frame's number.
- ``GET /frame``: the newest eye-view frame (EYE_VIEW, services/eyeview.py), as JPEG
  (``web.jpeg_quality``), encoded once per frame when first asked for. JPEG rather than
  raw pixels to a canvas: a small fraction of a raw frame's 230 kB, so the view keeps up
  through an ``ssh -L`` tunnel too, and the browser decodes it natively.
- ``POST /input``: the page's intent, ``{"v": [x, y, z], "gripper": bool, "clutch":
  bool}`` (velocity fractions in the view frame, as :class:`HandIntent`), and
  optionally the ``"robot"`` it was meant for (one meant for a robot the hand has left
  is dropped and counted). Anything else
  (a body too large, not JSON, another key, a NaN, a value outside [-1, 1]) gets 400,
  is counted and logged once; the intent stays as it was.
- ``POST /end``: the person ends the run (TASK_DONE, not a success).
- ``POST /switch``: a run of several robots: the hand drives the next robot whose task is
  not done; the answer, ``{"switched": bool, "robot": id, "gripper": bool, "clutch":
  bool}``, gives the page the gripper and clutch as the hand last left that robot. The
  state and the eye view are the driven robot's.

The page sends its intent at once on a change and, while it asks for motion,
``web.input_rate_hz`` times a second; ``web.input_expiry_s`` after its newest input the
motion falls back to none (:class:`PageIntent`), so a closed tab or a lost link stops the
arm. The keys are those of the terminal (:data:`teleop.devices.person.intent.DEFAULT_KEYS`);
the page holds a motion key's motion while the key is down (a browser reports releases).

Threads: the HTTP server and its request threads run under normal scheduling, even where
the operator runs under SCHED_FIFO (realtime runs): the page is for a person's eyes and
must never take CPU from the control loops. Its state is read under the operator's lock,
held only to copy a few numbers.
"""

from __future__ import annotations

import hmac
import io
import json
import logging
import math
import os
import stat
import sys
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, Protocol
from urllib.parse import parse_qs, urlsplit

import numpy as np
import PIL.Image

from teleop.bus.messages import Button
from teleop.core.clock import NS_PER_S
from teleop.core.config import Config, ConfigError
from teleop.core.net import LOOPBACK
from teleop.devices.person.intent import (
    DOWN,
    KEY_HELP,
    LEFT,
    PAGE_DOWN,
    PAGE_UP,
    RIGHT,
    SWITCH_HELP,
    TAB,
    UP,
    HandIntent,
    KeyAction,
)
from teleop.devices.person.loop import PHASES, WorldView

logger = logging.getLogger(__name__)

PAGE_FILE = Path(__file__).with_name("web_page.html")
# Where the page's settings go in its HTML (a JSON object).
PAGE_CONFIG_MARK = "/*TELEOP_PAGE_CONFIG*/{}"
TOKEN_HEADER = "X-Teleop-Token"
TOKEN_QUERY = "token"
# A token shorter than this is refused at start (the launcher's has 43 characters).
MIN_TOKEN_CHARS = 16
# The largest input body taken (bytes): an intent is about 60.
MAX_INPUT_BYTES = 1024
INPUT_KEYS = frozenset({"v", "gripper", "clutch"})
# An input may name the robot it was meant for: one for another robot than the one driven
# (sent before the page saw a switch) is dropped, so its buttons never reach the next.
ROBOT_KEY = "robot"
MAX_ROBOT_ID_CHARS = 64
# State streams served at once (one per open page; more is a page left open twice over).
MAX_STATE_STREAMS = 8
# A connection that sends nothing for this long is closed (s): keep-alive and dead peers.
CONNECTION_TIMEOUT_S = 30.0
# Digits of the state's numbers (0.1 mm, 0.1 mN: far below what a screen shows).
STATE_DIGITS = 4
# The browser's names (KeyboardEvent.key) of the key map's special keys.
BROWSER_KEYS: Mapping[str, str] = {
    UP: "ArrowUp",
    DOWN: "ArrowDown",
    LEFT: "ArrowLeft",
    RIGHT: "ArrowRight",
    PAGE_UP: "PageUp",
    PAGE_DOWN: "PageDown",
    TAB: "Tab",
}
# The page's own controls, after the terminal's keys.
PAGE_HELP = (
    "mouse: drag on the view (up: forward, right: right); shift- or right-drag: up/down",
    "gamepad: left stick forward/back and left/right, right stick up/down, "
    "A: gripper, LB/RB held: clutch",
)


class BadInput(ValueError):
    """An input body the page should not have sent (the reason, for the log)."""


def token_matches(expected: str, given: str | None) -> bool:
    """Whether ``given`` is the run's token, in constant time (no timing tells how much
    of a guess was right). Any string is safe to pass, non-ASCII included."""
    if given is None:
        return False
    return hmac.compare_digest(expected.encode(), given.encode("utf-8", "surrogateescape"))


def read_token(path: Path) -> str:
    """The run's token from ``path`` (written by the launcher, 0600). ConfigError if it
    is missing, too short, or readable by other users (then it is no secret)."""
    if not str(path):
        raise ConfigError("web.token_file: the run's token file is needed (teleop run writes it)")
    try:
        mode = os.stat(path).st_mode
        token = Path(path).read_text().strip()
    except OSError as exc:
        raise ConfigError(f"web.token_file {path}: {exc.strerror}") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ConfigError(f"web.token_file {path}: readable by other users (mode "
                          f"{stat.S_IMODE(mode):o}); it must be 0600")  # fmt: skip
    if len(token) < MIN_TOKEN_CHARS:
        raise ConfigError(f"web.token_file {path}: a token of {MIN_TOKEN_CHARS}+ characters")
    return token


def parse_input(body: bytes) -> tuple[HandIntent, str | None]:
    """The page's intent from a POST body, and the robot it was meant for (None: not
    said); :class:`BadInput` says what is wrong with it."""
    if len(body) > MAX_INPUT_BYTES:
        raise BadInput(f"body of {len(body)} bytes (at most {MAX_INPUT_BYTES})")
    try:
        message = json.loads(body)
    except (ValueError, UnicodeDecodeError) as exc:
        raise BadInput(f"not JSON ({exc})") from None
    if not isinstance(message, dict) or not INPUT_KEYS <= set(message) <= INPUT_KEYS | {ROBOT_KEY}:
        keys = sorted(message) if isinstance(message, dict) else type(message).__name__
        raise BadInput(f"expected the keys {sorted(INPUT_KEYS)} (and {ROBOT_KEY!r}), got {keys}")
    robot = message.get(ROBOT_KEY)
    if robot is not None and not (isinstance(robot, str) and 0 < len(robot) <= MAX_ROBOT_ID_CHARS):
        raise BadInput(f"{ROBOT_KEY}: a robot id, got {robot!r}")
    v, gripper, clutch = message["v"], message["gripper"], message["clutch"]
    if not isinstance(v, list) or len(v) != 3:
        raise BadInput(f"v: a list of 3 numbers, got {v!r}")
    if not all(isinstance(x, int | float) and not isinstance(x, bool) for x in v):
        raise BadInput(f"v: numbers, got {v!r}")
    if not all(math.isfinite(x) and -1.0 <= x <= 1.0 for x in v):
        raise BadInput(f"v: finite values in [-1, 1], got {v!r}")
    if not isinstance(gripper, bool) or not isinstance(clutch, bool):
        raise BadInput(f"gripper, clutch: true or false, got {gripper!r}, {clutch!r}")
    return HandIntent((float(v[0]), float(v[1]), float(v[2])), gripper, clutch), robot


class PageIntent:
    """The page's newest intent as the pacer reads it (clock-injected): its motion lasts
    ``expiry_s`` after its arrival, then falls back to none; the buttons stay as the
    page last set them (an object held is not dropped when the page goes silent)."""

    def __init__(self, expiry_s: float) -> None:
        self.expiry_ns = round(expiry_s * NS_PER_S)
        self.newest = HandIntent()
        self.received_ns: int | None = None
        self.inputs = 0
        self.expiries = 0  # motions the page stopped renewing (a closed tab, a lost link)
        self._expired = True

    def update(self, intent: HandIntent, now_ns: int) -> bool:
        """The page's input at ``now_ns``; whether it changes what the hand is asked."""
        changed = intent != self.intent(now_ns)
        self.newest, self.received_ns = intent, now_ns
        self.inputs += 1
        self._expired = False
        return changed

    def take_robot(self, buttons: Button) -> None:
        """The hand moved to another robot: no motion until the page's next input, the
        gripper and clutch as the hand last left that robot (``buttons``)."""
        self.newest = HandIntent.at_rest(buttons)
        self.received_ns, self._expired = None, True

    def live(self, now_ns: int) -> bool:
        """Whether the newest input still holds at ``now_ns``."""
        return self.received_ns is not None and now_ns - self.received_ns <= self.expiry_ns

    def intent(self, now_ns: int) -> HandIntent:
        """What the page asks of the hand at ``now_ns``."""
        if self.live(now_ns):
            return self.newest
        if not self._expired:
            self._expired = True
            self.expiries += int(self.newest.moving)
        return HandIntent((0.0, 0.0, 0.0), self.newest.gripper_closed, self.newest.clutch)


def browser_key_map(keys: Mapping[str, KeyAction]) -> dict[str, list[Any]]:
    """The key map for the page: by the browser's key name, ``[kind, axis, sign]``."""
    return {BROWSER_KEYS.get(k, k): [a.kind, a.axis, a.sign] for k, a in keys.items()}


def page_settings(config: Config, keys: Mapping[str, KeyAction]) -> dict[str, Any]:
    """What the page needs of the config: the keys, speed steps, rates, the force's full
    scale and the gamepad's dead zone."""
    return {
        "keys": browser_key_map(keys),
        "help": [*KEY_HELP, *PAGE_HELP, *([SWITCH_HELP] if config.run.robots > 1 else [])],
        "speed_steps": list(config.keyboard.speed_steps),
        "start_speed_step": config.keyboard.start_speed_step,
        "input_rate_hz": config.web.input_rate_hz,
        "force_full_scale_n": config.haptic.peak_force_n,
        "max_tool_speed_m_s": config.teleop.max_tool_speed_m_s,
        "dead_zone_fraction": config.gamepad.dead_zone_fraction,
        "token_header": TOKEN_HEADER,
        "robot_id": config.robot.robot_id,
        "robots": list(config.robot_ids()),
        "mode": config.run.mode,
        "phases": list(PHASES),
    }


def render_page(template: str, settings: Mapping[str, Any]) -> bytes:
    """The page with ``settings`` in place of its mark (as JSON, safe inside a script)."""
    if template.count(PAGE_CONFIG_MARK) != 1:
        raise ConfigError(f"{PAGE_FILE}: expected one {PAGE_CONFIG_MARK!r}")
    blob = json.dumps(settings).replace("<", "\\u003c")
    return template.replace(PAGE_CONFIG_MARK, blob).encode()


def _rounded(values: Any) -> list[float] | None:
    if values is None:
        return None
    return [round(float(v), STATE_DIGITS) for v in values]


def state_message(
    view: WorldView,
    config: Config,
    intent: HandIntent,
    *,
    intent_live: bool,
    run_over: bool,
    frame_seq: int,
    robot_id: str,
    settling: bool = False,
) -> dict[str, Any]:
    """What the page shows, as the state stream sends it (units in the names; positions
    in the world frame, the force in the device frame): the world of ``robot_id``, the
    robot the hand drives."""
    force_n = view.force_n
    phase = view.phase_name
    return {
        "robot": robot_id,
        "settling": settling,  # after a switch: no motion until the handle rests
        "tick": view.tick,
        "sim_s": round(max(view.tick, 0) * config.tick_s, 3),
        "started": view.tick >= 0,
        "phase": phase,
        "phase_index": view.phase,
        "tool_p_m": _rounded(view.tool_p_m),
        "tool_speed_m_s": round(view.tool_speed_m_s, STATE_DIGITS),
        "objects_p_m": {name: _rounded(p) for name, p in (view.objects_p_m or {}).items()},
        "holding": view.holding,
        "force_n": round(force_n, STATE_DIGITS),
        "device_f_n": _rounded(view.device_f_n),
        "done": view.done,
        "success": view.success,
        "run_over": run_over,
        "intent": {
            "v": list(intent.velocity_fraction),
            "gripper": intent.gripper_closed,
            "clutch": intent.clutch,
            "live": intent_live,
        },
        "frame_seq": frame_seq,
    }


class EyeFrames:
    """The newest eye-view frame, from Zenoh's thread, and its JPEG, encoded once when
    first asked for (on a request thread, at normal scheduling)."""

    def __init__(self, jpeg_quality: int) -> None:
        self.jpeg_quality = jpeg_quality
        self._lock = threading.Lock()
        self._pixels: np.ndarray | None = None
        self._jpeg: tuple[int, bytes] | None = None  # (frame number, JPEG)
        self.received = 0
        self.encoded = 0

    def __call__(self, rec: np.ndarray, pixels: np.ndarray, rx_ns: int, via_shm: bool) -> None:
        copy = pixels.copy()  # a view of the received buffer, not ours to keep
        with self._lock:
            self._pixels = copy
            self.received += 1

    @property
    def newest(self) -> int:
        """The newest frame's number (1 the first; 0: none yet)."""
        with self._lock:
            return self.received

    def jpeg(self) -> tuple[int, bytes] | None:
        """The newest frame's number and JPEG; None before the first frame."""
        with self._lock:
            pixels, number, cached = self._pixels, self.received, self._jpeg
        if pixels is None:
            return None
        if cached is not None and cached[0] == number:
            return cached
        out = io.BytesIO()
        PIL.Image.fromarray(pixels).save(out, format="JPEG", quality=self.jpeg_quality)
        encoded = (number, out.getvalue())
        with self._lock:
            self._jpeg = encoded
            self.encoded += 1
        return encoded


@dataclass
class RequestCounts:
    """What the page's server saw, for the summary."""

    pages: int = 0
    forbidden: int = 0  # requests without the run's token (403)
    bad_inputs: int = 0  # input bodies refused (400)
    first_bad_input: str = ""
    not_found: int = 0
    state_streams: int = 0
    state_streams_refused: int = 0  # over MAX_STATE_STREAMS
    frames: int = 0
    ends: int = 0
    switches: int = 0  # robot switches asked for (a run of several robots)
    other_robot_inputs: int = 0  # inputs meant for a robot the hand had left: dropped
    by_status: dict[int, int] = field(default_factory=dict)


class PageOperator(Protocol):
    """What the page asks of the operator behind it (services/web.py)."""

    def take_input(self, intent: HandIntent, robot: str | None) -> None:
        """The page's input, meant for ``robot`` (None: whichever is driven)."""

    def switch_from_page(self) -> dict[str, Any]:
        """The robot switch; what the page is to take up (``switched``, ``robot``, ...)."""

    def end_task(self) -> None:
        """The person ends the run."""

    def state(self) -> dict[str, Any]:
        """The state message (:func:`state_message`)."""


class PageServer:
    """The page's server on 127.0.0.1 (``port`` 0: any free one, :attr:`port` says
    which): the token checked on every request, the requests counted (:attr:`counts`),
    at most MAX_STATE_STREAMS state streams at once. Bound at construction, so a taken
    port fails the caller's start-up (OSError)."""

    def __init__(self, port: int, operator: PageOperator, *, token: str, page: bytes,
                 frames: EyeFrames, state_rate_hz: float) -> None:  # fmt: skip
        self.operator, self.token, self.page, self.frames = operator, token, page, frames
        self.state_period_s = 1.0 / state_rate_hz
        self.counts = RequestCounts()
        self.stopping = threading.Event()  # set by serve()'s stop: state streams end
        self._lock = threading.Lock()
        self._streams = 0
        self._http = _HttpServer((LOOPBACK, port), self)
        self.port = int(self._http.server_address[1])

    def serve(self, stop: threading.Event) -> None:
        """Serve until ``stop`` (under normal scheduling, on threads of its own)."""
        self.stopping = stop
        _normal_scheduling()  # the server's threads are started from this one
        thread = threading.Thread(target=self._http.serve_forever, name="web-page",
                                  kwargs={"poll_interval": 0.25})  # fmt: skip
        thread.start()
        try:
            stop.wait()
        finally:
            self._http.shutdown()
            thread.join()

    def close(self) -> None:
        self._http.server_close()

    def count(self, name: str) -> None:
        with self._lock:
            setattr(self.counts, name, getattr(self.counts, name) + 1)

    def count_status(self, status: int) -> None:
        with self._lock:
            self.counts.by_status[status] = self.counts.by_status.get(status, 0) + 1

    def refuse(self) -> None:
        """A request without the token: counted, the first one logged."""
        with self._lock:
            self.counts.forbidden += 1
            first = self.counts.forbidden == 1
        if first:
            logger.warning("a request without the run's token was refused (403); "
                           "further ones are counted in the summary")  # fmt: skip

    def bad_input(self, reason: str) -> None:
        with self._lock:
            self.counts.bad_inputs += 1
            first = self.counts.bad_inputs == 1
            if first:
                self.counts.first_bad_input = reason
        if first:
            logger.warning("an input from the page was refused (400): %s; further ones "
                           "are counted in the summary", reason)  # fmt: skip

    def open_stream(self) -> bool:
        """A state stream may start (at most MAX_STATE_STREAMS at once)."""
        with self._lock:
            if self._streams >= MAX_STATE_STREAMS:
                self.counts.state_streams_refused += 1
                return False
            self._streams += 1
            self.counts.state_streams += 1
            return True

    def close_stream(self) -> None:
        with self._lock:
            self._streams -= 1

    def summary(self) -> dict[str, Any]:
        """The request counts, for the service's summary."""
        with self._lock:
            counts = dict(vars(self.counts))
            counts["by_status"] = {str(k): v for k, v in sorted(self.counts.by_status.items())}
        return {**counts, "port": self.port}


def _normal_scheduling() -> None:
    """Put the calling thread (and the threads it starts) under normal scheduling, where
    it runs under a realtime policy (the operator's SCHED_FIFO in realtime runs)."""
    if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


class _HttpServer(ThreadingHTTPServer):
    """The standard library's server: request threads are daemons (a page left open never
    holds the service's exit), and a connection's failure is logged, never raised."""

    daemon_threads = True

    def __init__(self, address: tuple[str, int], site: PageServer) -> None:
        self.site = site
        super().__init__(address, _PageHandler)

    def handle_error(self, request: Any, client_address: Any) -> None:
        logger.debug("web page: a connection failed", exc_info=sys.exc_info())


class _PageHandler(BaseHTTPRequestHandler):
    """One request of the page: the token first, then the route."""

    server: _HttpServer
    protocol_version = "HTTP/1.1"  # keep-alive: the page's inputs reuse one connection
    timeout = CONNECTION_TIMEOUT_S
    server_version = "zenoh-teleop"
    sys_version = ""

    @property
    def site(self) -> PageServer:
        return self.server.site

    def log_message(self, format: str, *args: Any) -> None:
        """Nothing: a request line may hold the token (the page's query)."""

    # -- routes ----------------------------------------------------------------------------
    def do_GET(self) -> None:
        url = urlsplit(self.path)
        if url.path in ("/", "/index.html"):
            given = parse_qs(url.query).get(TOKEN_QUERY, [None])[0]
            if not self._authorised(given):
                return
            self.site.count("pages")
            self._send(HTTPStatus.OK, self.site.page, "text/html; charset=utf-8")
            return
        if not self._authorised(self.headers.get(TOKEN_HEADER)):
            return
        if url.path == "/state":
            self._stream_state()
        elif url.path == "/frame":
            self._frame()
        else:
            self.site.count("not_found")
            self._send(HTTPStatus.NOT_FOUND, b"not found\n", "text/plain")

    def do_POST(self) -> None:
        if not self._authorised(self.headers.get(TOKEN_HEADER)):
            return
        path = urlsplit(self.path).path
        if path == "/input":
            self._input()
        elif path == "/end":
            self.site.count("ends")
            self.site.operator.end_task()
            self._send(HTTPStatus.NO_CONTENT)
        elif path == "/switch":
            body = json.dumps(self.site.operator.switch_from_page()).encode()
            self._send(HTTPStatus.OK, body, "application/json")
        else:
            self.close_connection = True  # its body, if any, is not read
            self.site.count("not_found")
            self._send(HTTPStatus.NOT_FOUND, b"not found\n", "text/plain")

    def _authorised(self, given: str | None) -> bool:
        if token_matches(self.site.token, given):
            return True
        self.site.refuse()
        self.close_connection = True  # a body it may have sent is not read
        self._send(HTTPStatus.FORBIDDEN, b"forbidden: this needs the run's token (open the "
                   b"URL teleop printed)\n", "text/plain")  # fmt: skip
        return False

    def _input(self) -> None:
        try:
            length = int(self.headers.get("Content-Length", ""))
        except ValueError:
            length = -1
        if not 0 <= length <= MAX_INPUT_BYTES:
            self.close_connection = True  # the body is not read
            self.site.bad_input(f"Content-Length {self.headers.get('Content-Length')!r}")
            self._send(HTTPStatus.BAD_REQUEST, b"bad input: body size\n", "text/plain")
            return
        body = self.rfile.read(length)
        try:
            intent, robot = parse_input(body)
        except BadInput as exc:
            self.site.bad_input(str(exc))
            self._send(HTTPStatus.BAD_REQUEST, f"bad input: {exc}\n".encode(), "text/plain")
            return
        self.site.operator.take_input(intent, robot)
        self._send(HTTPStatus.NO_CONTENT)

    def _frame(self) -> None:
        frame = self.site.frames.jpeg()
        if frame is None:
            self._send(HTTPStatus.NO_CONTENT)
            return
        number, jpeg = frame
        self.site.count("frames")
        self._send(HTTPStatus.OK, jpeg, "image/jpeg", {"X-Frame-Seq": str(number)})

    def _stream_state(self) -> None:
        site = self.site
        if not site.open_stream():
            self._send(HTTPStatus.SERVICE_UNAVAILABLE, b"too many state streams\n", "text/plain")
            return
        try:
            self.close_connection = True  # the stream ends with the connection
            site.count_status(HTTPStatus.OK)
            self.send_response(HTTPStatus.OK)
            self._common_headers()
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Connection", "close")
            self.end_headers()
            stop = site.stopping
            while not stop.is_set():
                data = json.dumps(site.operator.state(), separators=(",", ":"))
                self.wfile.write(f"data: {data}\n\n".encode())
                self.wfile.flush()
                stop.wait(site.state_period_s)
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            pass  # the page went away
        finally:
            site.close_stream()

    # -- responses -------------------------------------------------------------------------
    def _common_headers(self) -> None:
        self.send_header("Cache-Control", "no-store")
        self.send_header("Referrer-Policy", "no-referrer")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("X-Frame-Options", "DENY")
        self.send_header(
            "Content-Security-Policy",
            "default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; "
            "img-src blob:; connect-src 'self'; frame-ancestors 'none'",
        )

    def _send(
        self,
        status: HTTPStatus,
        body: bytes = b"",
        content_type: str = "",
        headers: Mapping[str, str] | None = None,
    ) -> None:
        self.site.count_status(int(status))
        self.send_response(status)
        self._common_headers()
        if content_type:
            self.send_header("Content-Type", content_type)
        for name, value in (headers or {}).items():
            self.send_header(name, value)
        self.send_header("Content-Length", str(len(body)))
        if self.close_connection:
            self.send_header("Connection", "close")
        self.end_headers()
        if body:
            self.wfile.write(body)
