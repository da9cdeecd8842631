"""Shared fixtures: the default config and the second (7-DOF) arm's overrides; and an
exit that never waits for a Zenoh session a failed test left open."""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Iterator

import pytest
import zenoh

from teleop.core.config import Config, load_config

# No telemetry from Rerun, no window from MuJoCo, in every test process and its children.
os.environ.setdefault("RERUN_ANALYTICS", "0")
os.environ.setdefault("MUJOCO_GL", "egl")

ARM7_OVERRIDES = (
    'robot.scene_file="scene_arm7.xml"',
    'robot.arm_joints=["j1","j2","j3","j4","j5","j6","j7"]',
    'robot.arm_actuators=["a1","a2","a3","a4","a5","a6","a7"]',
    'robot.tool_site="ee"',
    'robot.gripper_actuator="hand"',
    'robot.gripper_joints=["fl","fr"]',
    "robot.home_q_rad=[0.0,-0.25,0.0,1.75,0.05,-1.5708,-1.5708]",
)


@pytest.fixture
def config() -> Config:
    return load_config()


@pytest.fixture(params=["arm6", "arm7"])
def any_arm_config(request) -> Config:
    return load_config(None, ARM7_OVERRIDES if request.param == "arm7" else ())


# zenoh-python runs each subscriber's callbacks on a thread of this name, not a daemon:
# while a session is open the interpreter's exit waits for them, for ever.
ZENOH_CALLBACK_THREAD = "pyo3-closure"
# A newest-only subscription's thread (teleop.bus.session.NewestSubscriber), ended by its
# undeclare.
NEWEST_THREAD_PREFIX = "newest "
# How long a test's closed sessions may take to end their threads (s).
SESSION_END_GRACE_S = 2.0
EXIT_STATUS = pytest.StashKey[int]()

# Every Zenoh session this test process opens, in order: a test must close the ones it
# opens (zenoh.open is wrapped once, here; the services' own processes are not affected).
_opened_sessions: list[zenoh.Session] = []
_zenoh_open = zenoh.open


def _open_tracked(*args: object, **kwargs: object) -> zenoh.Session:
    session = _zenoh_open(*args, **kwargs)
    _opened_sessions.append(session)
    return session


zenoh.open = _open_tracked


def _newest_threads() -> set[threading.Thread]:
    return {
        thread
        for thread in threading.enumerate()
        if thread.is_alive() and thread.name.startswith(NEWEST_THREAD_PREFIX)
    }


@pytest.fixture(autouse=True)
def no_session_left_open(request: pytest.FixtureRequest) -> Iterator[None]:
    """Fail the test that leaves a Zenoh session it opened, or a newest-only subscription,
    open: its threads would outlive it (and a session's callback threads keep the test
    process alive at exit). Sessions of wider fixtures, opened before the test, are
    theirs to close."""
    first = len(_opened_sessions)
    threads_before = _newest_threads()
    yield
    deadline = time.monotonic() + SESSION_END_GRACE_S
    opened = _opened_sessions[first:]
    del _opened_sessions[first:]
    open_sessions = [session for session in opened if not session.is_closed()]
    threads = _newest_threads() - threads_before
    while threads and time.monotonic() < deadline:
        time.sleep(0.05)
        threads = {thread for thread in threads if thread.is_alive()}
    if open_sessions or threads:
        what = [f"{len(open_sessions)} session(s)"] if open_sessions else []
        if threads:
            what.append(f"subscription thread(s) {', '.join(sorted(t.name for t in threads))}")
        for session in open_sessions:  # the rest of the run must not wait on them
            session.close()
        pytest.fail(
            f"{request.node.nodeid} left {' and '.join(what)} open: close what it opens "
            "(teleop.bus.session.close_session) in a finally or a fixture",
            pytrace=False,
        )


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    session.config.stash[EXIT_STATUS] = int(exitstatus)


def pytest_unconfigure(config: pytest.Config) -> None:
    """A test that fails before it closes its Zenoh session leaves the session's callback
    threads running, and the run would then hang at exit (CI: until its time limit)
    instead of reporting the failure. Name them and exit now, with pytest's status."""
    left = [
        thread.name
        for thread in threading.enumerate()
        if ZENOH_CALLBACK_THREAD in thread.name and thread.is_alive() and not thread.daemon
    ]
    status = config.stash.get(EXIT_STATUS, None)
    if left and status is not None:
        sys.stderr.write(
            f"tests: {len(left)} Zenoh callback threads still running (a session left open "
            "by a test); exiting without waiting for them\n"
        )
        sys.stderr.flush()
        sys.stdout.flush()
        os._exit(status)
