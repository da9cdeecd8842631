"""The web operator without a bus: the token check, what the page may send, the intent's
expiry, the page's settings, the launcher's port and token file; and the page's server on
a loopback port, driven by HTTP requests, with the service's bus side stubbed out."""

from __future__ import annotations

import http.client
import json
import math
import os
import stat
import threading
import time
from collections.abc import Iterator
from types import SimpleNamespace

import numpy as np
import pytest

from services import web
from teleop.bus.messages import Button
from teleop.bus.topics import Topics
from teleop.core.clock import NS_PER_S
from teleop.core.config import ConfigError, load_config
from teleop.core.net import LoopbackPorts
from teleop.devices.person import web_page
from teleop.devices.person.intent import DEFAULT_KEYS, SWITCH, HandIntent
from teleop.devices.person.loop import WorldView
from teleop.run import web_operator

TOKEN = "a-token-of-enough-characters-0123456789"


# -- the token -------------------------------------------------------------------------
def test_only_the_exact_token_passes():
    assert web_page.token_matches(TOKEN, TOKEN)
    for given in (None, "", TOKEN[:-1], TOKEN + "x", TOKEN.upper(), "é" + TOKEN[1:], "\udcff"):
        assert not web_page.token_matches(TOKEN, given), given


def test_the_token_file_must_be_private_and_long_enough(tmp_path):
    path = tmp_path / "token"
    path.write_text(TOKEN + "\n")
    os.chmod(path, 0o600)
    assert web_page.read_token(path) == TOKEN
    os.chmod(path, 0o640)
    with pytest.raises(ConfigError, match="readable by other users"):
        web_page.read_token(path)
    os.chmod(path, 0o600)
    path.write_text("short")
    with pytest.raises(ConfigError, match="16\\+ characters"):
        web_page.read_token(path)
    with pytest.raises(ConfigError, match="No such file"):
        web_page.read_token(tmp_path / "none")


# -- what the page may send ------------------------------------------------------------
def _body(**message: object) -> bytes:
    return json.dumps(message).encode()


def test_a_well_formed_input_is_the_intent_it_says_and_may_name_its_robot():
    intent, robot = web_page.parse_input(_body(v=[0.5, -1, 0], gripper=True, clutch=False))
    assert intent == HandIntent((0.5, -1.0, 0.0), True, False) and robot is None
    _, robot = web_page.parse_input(_body(v=[0, 0, 0], gripper=False, clutch=False, robot="arm1"))
    assert robot == "arm1"


@pytest.mark.parametrize(
    ("body", "reason"),
    [
        (b"{", "not JSON"),
        (b"\xff\xfe", "not JSON"),
        (b"[0, 0, 0]", "expected the keys"),
        (_body(v=[0, 0, 0], gripper=False), "expected the keys"),
        (_body(v=[0, 0, 0], gripper=False, clutch=False, extra=1), "expected the keys"),
        (_body(v=[0, 0], gripper=False, clutch=False), "a list of 3"),
        (_body(v=[0, 0, 0, 0], gripper=False, clutch=False), "a list of 3"),
        (_body(v="000", gripper=False, clutch=False), "a list of 3"),
        (_body(v=[0, "1", 0], gripper=False, clutch=False), "numbers"),
        (_body(v=[0, True, 0], gripper=False, clutch=False), "numbers"),
        (b'{"v": [NaN, 0, 0], "gripper": false, "clutch": false}', "finite"),
        (b'{"v": [Infinity, 0, 0], "gripper": false, "clutch": false}', "finite"),
        (_body(v=[1.5, 0, 0], gripper=False, clutch=False), "in \\[-1, 1\\]"),
        (_body(v=[0, 0, -1.01], gripper=False, clutch=False), "in \\[-1, 1\\]"),
        (_body(v=[0, 0, 0], gripper=1, clutch=False), "true or false"),
        (_body(v=[0, 0, 0], gripper=False, clutch=False, robot=7), "a robot id"),
        (_body(v=[0, 0, 0], gripper=False, clutch=False, robot=""), "a robot id"),
        (b" " * (web_page.MAX_INPUT_BYTES + 1), "bytes"),
    ],
)
def test_a_malformed_input_is_refused_with_its_reason(body, reason):
    with pytest.raises(web_page.BadInput, match=reason):
        web_page.parse_input(body)


# -- the intent's expiry ---------------------------------------------------------------
def test_the_motion_stops_when_the_page_goes_silent_and_the_buttons_stay():
    page = web_page.PageIntent(expiry_s=0.5)
    assert page.intent(0) == HandIntent()  # nothing from the page yet
    moving = HandIntent((0.4, 0.0, -0.2), gripper_closed=True)
    t0 = 10 * NS_PER_S
    assert page.update(moving, t0)  # a change
    assert not page.update(moving, t0 + 1)  # a repeat
    assert page.intent(t0 + NS_PER_S // 2) == moving
    silent = page.intent(t0 + NS_PER_S // 2 + 2)
    assert silent == HandIntent((0.0, 0.0, 0.0), gripper_closed=True)
    assert page.intent(t0 + 2 * NS_PER_S) == silent
    assert (page.expiries, page.inputs) == (1, 2)  # counted once per lapse
    assert page.update(moving, t0 + 3 * NS_PER_S)  # the page is back: a change again
    assert page.intent(t0 + 3 * NS_PER_S) == moving


def test_a_still_page_going_silent_is_no_expiry():
    page = web_page.PageIntent(expiry_s=0.5)
    page.update(HandIntent(clutch=True), 0)
    assert page.intent(NS_PER_S) == HandIntent(clutch=True)
    assert page.expiries == 0


# -- the page --------------------------------------------------------------------------
def test_the_page_gets_the_terminals_keys_by_the_browsers_names():
    keys = web_page.browser_key_map(DEFAULT_KEYS)
    assert keys["w"] == ["move", 0, 1.0] and keys["ArrowUp"] == ["move", 0, 1.0]
    assert keys["PageDown"] == ["move", 2, -1.0] and keys["f"] == ["move", 2, -1.0]
    assert keys[" "][0] == "stop" and keys["q"][0] == "quit" and keys["g"][0] == "gripper"
    assert keys["Tab"][0] == SWITCH
    assert len(keys) == len(DEFAULT_KEYS)


def test_the_page_file_takes_its_settings_safely():
    config = load_config()
    settings = web_page.page_settings(config, DEFAULT_KEYS)
    template = web_page.PAGE_FILE.read_text()
    page = web_page.render_page(template, {**settings, "robot_id": "</script>"})
    assert web_page.PAGE_CONFIG_MARK.encode() not in page
    assert b'</script>"' not in page and b"\\u003c/script>" in page
    assert b"http://" not in page and b"https://" not in page  # nothing from elsewhere
    with pytest.raises(ConfigError, match="expected one"):
        web_page.render_page("<html></html>", settings)


def test_the_state_names_what_the_screen_shows():
    config = load_config()
    view = WorldView(tick=250, tool_p_m=np.array([0.4, 0.0, 0.2]), phase=1, holding=True,
                     device_f_n=np.array([0.0, 3.0, 4.0]),
                     objects_p_m={"cube": np.zeros(3)})  # fmt: skip
    state = web_page.state_message(view, config, HandIntent((0.1, 0, 0)), intent_live=True,
                              run_over=False, frame_seq=7, robot_id="arm1")  # fmt: skip
    assert state["robot"] == "arm1"
    assert state["phase"] == "carry" and state["holding"] is True
    assert math.isclose(state["force_n"], 5.0) and state["tool_p_m"] == [0.4, 0.0, 0.2]
    assert state["sim_s"] == round(250 * config.tick_s, 3)  # tick 250 of loop.rate_hz ticks
    assert state["intent"] == {"v": [0.1, 0, 0], "gripper": False, "clutch": False, "live": True}
    assert state["frame_seq"] == 7 and state["objects_p_m"] == {"cube": [0.0, 0.0, 0.0]}
    json.dumps(state)  # plain data


# -- the launcher's side ---------------------------------------------------------------
def test_the_launcher_writes_a_private_token_and_keeps_it_off_the_command_line(tmp_path):
    config = load_config(None, ['run.scenario="grasp"', 'run.operator="web"'])
    with LoopbackPorts() as ports:
        access = web_operator.prepare_web_operator(config, tmp_path / "run", ports)
        assert access is not None
        assert access.url == f"http://127.0.0.1:{access.port}/?token={access.token}"
        assert len(access.token) >= web_page.MIN_TOKEN_CHARS
        assert access.token_file == tmp_path / "run" / "auth" / web_operator.TOKEN_FILE
        assert stat.S_IMODE(access.token_file.stat().st_mode) == 0o600
        assert stat.S_IMODE(access.token_file.parent.stat().st_mode) == 0o700
        assert web_page.read_token(access.token_file) == access.token
        overrides = web_operator.web_overrides(access)
        assert not any(access.token in o for o in overrides)
        assert access.token not in repr(access)
        taken = load_config(None, overrides).web
        assert taken.port == access.port and taken.token_file == str(access.token_file)
        assert access.url in access.announcement()
        again = web_operator.prepare_web_operator(config, tmp_path / "run", ports)
        assert again is not None and again.token != access.token  # fresh per run
    scripted = load_config(None, ['run.scenario="grasp"'])
    with LoopbackPorts() as ports:
        assert web_operator.prepare_web_operator(scripted, tmp_path / "other", ports) is None
    assert web_operator.web_overrides(None) == []


def test_the_web_config_checks_its_rates():
    assert load_config(None, ['run.operator="web"']).run.operator == "web"
    with pytest.raises(ConfigError, match="web.input_expiry_s"):
        load_config(None, ["web.input_rate_hz=2", "web.input_expiry_s=0.5"])
    with pytest.raises(ConfigError, match="web.port"):
        load_config(None, ["web.port=70000"])


# -- the page's server, its bus side stubbed -------------------------------------------
class _Station:
    """A two-robot PersonStation stand-in: its loop's view is fixed, ending is counted,
    the switch goes to the other robot, whose gripper the hand left closed."""

    def __init__(self) -> None:
        self.view = WorldView(tick=10, tool_p_m=np.array([0.3, 0.1, 0.2]))
        self.loop = self
        self.active = 0
        self.ended = 0
        self.last_buttons = Button.GRIPPER_CLOSE
        self.settling = False

    def end_task(self) -> None:
        self.ended += 1

    def switch(self) -> bool:
        self.active = 1 - self.active
        return True


@pytest.fixture
def served(tmp_path) -> Iterator[SimpleNamespace]:
    """A WebOperatorService's page server on a free port, the bus side stubbed: the
    state comes from a fixed WorldView, end_task is counted."""
    config = load_config(None, ['run.scenario="grasp"', 'run.operator="web"'])
    service = web.WebOperatorService.__new__(web.WebOperatorService)
    service.config = config
    service.page_intent = web_page.PageIntent(config.web.input_expiry_s)
    service.frames = web_page.EyeFrames(config.web.jpeg_quality)
    service.lock = threading.Lock()
    service.station = _Station()
    service.robot_topics = (Topics("arm0"), Topics("arm1"))
    service.run_over = threading.Event()
    service._pending_input_ns = None
    service._wake = threading.Event()
    page = web_page.render_page(
        web_page.PAGE_FILE.read_text(), web_page.page_settings(config, DEFAULT_KEYS)
    )
    service.site = web_page.PageServer(0, service, token=TOKEN, page=page, frames=service.frames,
                                       state_rate_hz=config.web.state_rate_hz)  # fmt: skip
    stop = threading.Event()
    thread = threading.Thread(target=service.site.serve, args=(stop,))
    thread.start()
    try:
        yield SimpleNamespace(service=service, port=service.site.port)
    finally:
        stop.set()
        thread.join()
        service.site.close()


def _request(port: int, method: str, path: str, body: bytes | None = None,
             token: str | None = TOKEN) -> tuple[int, bytes, http.client.HTTPResponse]:  # fmt: skip
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    headers = {web_page.TOKEN_HEADER: token} if token is not None else {}
    connection.request(method, path, body=body, headers=headers)
    response = connection.getresponse()
    data = response.read() if response.headers.get("Content-Type") != "text/event-stream" else b""
    return response.status, data, response


def test_every_request_without_the_token_is_forbidden_and_counted(served):
    port = served.port
    assert _request(port, "GET", f"/?token={TOKEN}", token=None)[0] == 200
    for method, path, token in [
        ("GET", "/", None), ("GET", "/?token=wrong", None), ("GET", "/state", None),
        ("GET", "/frame", "wrong"), ("POST", "/input", None), ("POST", "/end", ""),
        ("GET", "/nothing-here", None),
    ]:  # fmt: skip
        status, body, response = _request(port, method, path, b"{}", token=token)
        assert status == 403, (method, path)
        assert TOKEN.encode() not in body
        assert response.headers["Cache-Control"] == "no-store"
    assert served.service.site.counts.forbidden == 7
    assert served.service.loop.ended == 0


def test_the_robot_switch_drives_the_next_robot_with_its_gripper_as_left(served):
    port, service = served.port, served.service
    assert (
        _request(port, "POST", "/input", _body(v=[0.5, 0.0, 0.0], gripper=False, clutch=False))[0]
        == 204
    )
    service._wake.clear()
    status, body, _ = _request(port, "POST", "/switch")
    assert status == 200
    assert json.loads(body) == {"switched": True, "robot": "arm1", "gripper": True, "clutch": False}
    # the page's motion stops; the hand holds the new robot's gripper as it left it
    assert service.page_intent.intent(time.monotonic_ns()) == HandIntent(gripper_closed=True)
    assert service._wake.is_set() and service.site.counts.switches == 1
    assert service.state()["robot"] == "arm1"
    assert _request(port, "POST", "/switch", token="wrong")[0] == 403
    # An input the page sent for arm0 before it saw the switch: dropped, counted.
    stale = _body(v=[0.5, 0.0, 0.0], gripper=False, clutch=False, robot="arm0")
    assert _request(port, "POST", "/input", stale)[0] == 204
    assert service.page_intent.newest == HandIntent(gripper_closed=True)
    assert service.site.counts.other_robot_inputs == 1
    fresh = _body(v=[0.5, 0.0, 0.0], gripper=True, clutch=False, robot="arm1")
    assert _request(port, "POST", "/input", fresh)[0] == 204
    assert service.page_intent.newest == HandIntent((0.5, 0.0, 0.0), True, False)


def test_inputs_are_taken_or_refused_and_end_ends(served):
    port, service = served.port, served.service
    good = _body(v=[0.2, 0.0, -0.3], gripper=True, clutch=False)
    assert _request(port, "POST", "/input", good)[0] == 204
    assert service.page_intent.newest == HandIntent((0.2, 0.0, -0.3), True, False)
    assert service._wake.is_set()  # the pacer is told
    assert _request(port, "POST", "/input", b'{"v": [NaN, 0, 0]}')[0] == 400
    assert _request(port, "POST", "/input", b"x" * (web_page.MAX_INPUT_BYTES + 1))[0] == 400
    counts = service.site.counts
    assert counts.bad_inputs == 2 and "expected the keys" in counts.first_bad_input
    assert service.page_intent.newest == HandIntent((0.2, 0.0, -0.3), True, False)  # kept
    assert _request(port, "POST", "/end")[0] == 204 and service.loop.ended == 1
    assert _request(port, "GET", "/frame")[0] == 204  # no frame yet
    pixels = np.zeros((24, 32, 3), dtype=np.uint8)
    service.frames(None, pixels, 0, True)
    status, jpeg, response = _request(port, "GET", "/frame")
    assert status == 200 and jpeg[:2] == b"\xff\xd8" and response.headers["X-Frame-Seq"] == "1"


def test_the_state_stream_sends_the_view(served):
    connection = http.client.HTTPConnection("127.0.0.1", served.port, timeout=5)
    connection.request("GET", "/state", headers={web_page.TOKEN_HEADER: TOKEN})
    response = connection.getresponse()
    assert response.status == 200
    assert response.headers["Content-Type"] == "text/event-stream"
    start = time.monotonic()
    line = response.fp.readline()
    assert line.startswith(b"data: ")
    state = json.loads(line[len(b"data: ") :])
    assert state["tick"] == 10 and state["tool_p_m"] == [0.3, 0.1, 0.2]
    assert state["intent"]["live"] is False
    assert response.fp.readline() == b"\n"
    assert response.fp.readline().startswith(b"data: ")  # the next one, a period later
    assert time.monotonic() - start < 2.0
    connection.close()
