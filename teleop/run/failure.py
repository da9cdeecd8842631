"""A service that fails under the launcher: noticed within seconds, told in one block.

The launcher polls supervisord's view of its programs (``getAllProcessInfo``) while it
waits for the services to come alive and for the run to end. :class:`ProgramWatch`
turns that into a verdict: a program in a failed state, or one whose pid changed (it
died and supervisord restarted it: a crash that a single state poll would miss), has
failed. :class:`ServiceFailed` then carries one block for the user: the service, what
happened, the last lines of its log (the real exception), the log's path and, when the
log shows a known cause, a hint (:func:`hint_for`).

Pure but for :func:`program_log_text`: the process infos and log text come in as
values, so a unit test drives it.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# supervisord states of a program that has stopped for good or is between restarts.
FAILED_STATES = frozenset({"BACKOFF", "FATAL", "EXITED", "STOPPED", "UNKNOWN"})
# Of those, the states a program passes through on its way back after dying: not a
# failure for a program whose restart is expected (ProgramWatch.restarts_expected).
RESTARTING_STATES = frozenset({"BACKOFF", "EXITED"})
# Lines of the service's log the block quotes (its traceback, usually).
TAIL_LINES = 15

# Known causes: (text the log holds, hint). First match wins.
HINTS: tuple[tuple[str, str], ...] = (
    (
        "Unable to create POSIX shm segment",
        "a shared-memory pool exceeds the locked-memory limit (ulimit -l): raise the "
        "limit, lower bus.shm_pool_bytes, or run with --set bus.shm=false",
    ),
    (
        "Address already in use",
        "a port the run listens on is taken (another stack or program): stop it, or "
        "pick another port (bus.endpoint)",
    ),
    (
        "Can not create a new TCP listener",
        "a port the run listens on is taken (another stack or program): stop it, or "
        "pick another port (bus.endpoint)",
    ),
    (
        "Failed to find Rerun Viewer executable",
        "the native Rerun viewer (`rerun`) is not on PATH: install the project's "
        "environment (make venv) or run without --spawn",
    ),
)


class RunError(RuntimeError):
    """A services run did not complete; the message says which service and why."""


def hint_for(log_text: str) -> str:
    """The hint for the first known cause found in ``log_text``; empty when none."""
    for needle, hint in HINTS:
        if needle in log_text:
            return hint
    return ""


def last_lines(text: str, count: int = TAIL_LINES) -> str:
    """The last ``count`` non-empty lines of ``text``."""
    lines = [line for line in text.splitlines() if line.strip()]
    return "\n".join(lines[-count:])


def program_log_text(log_path: Path, supervisord_log: Path) -> str:
    """A program's log; when it is empty (killed before it wrote anything), the lines
    of supervisord's own log about the program instead (how it ended)."""
    try:
        text = log_path.read_text(errors="replace")
    except OSError as exc:
        text = f"(no log: {exc})"
    if text.strip():
        return text
    # supervisord names a program quoted ("spawned: 'plant' with pid 1") or not
    # ("exited: plant (terminated by SIGKILL; not expected)").
    names = (f"'{log_path.stem}'", f": {log_path.stem} (")
    try:
        lines = supervisord_log.read_text(errors="replace").splitlines()
    except OSError:
        return text
    about = [line for line in lines if any(name in line for name in names)]
    return "\n".join(f"supervisord: {line}" for line in about)


class ServiceFailed(RuntimeError):
    """A service of the run died, crash-looped or never came alive; ``str()`` is the
    block shown to the user. ``startup``: it failed before the run began (its stack never
    came up: the run did not start, so it has no outcome)."""

    def __init__(
        self, service: str, what: str, log_path: Path, log_text: str, *, startup: bool = False
    ) -> None:
        self.service = service
        self.what = what
        self.startup = startup
        self.log_path = log_path
        self.tail = last_lines(log_text)
        self.hint = hint_for(log_text)
        self.reported = False  # the block was shown already (the launcher's announce)
        super().__init__(self.block())

    def block(self) -> str:
        rule = "-" * 72
        lines = [f"service {self.service} {self.what}", rule]
        lines += [f"  {line}" for line in (self.tail or "(its log is empty)").splitlines()]
        lines += [rule, f"log:  {self.log_path}"]
        if self.hint:
            lines.append(f"hint: {self.hint}")
        return "\n".join(lines)


@dataclass
class ProgramWatch:
    """Tells from successive supervisord process infos whether a program has failed.

    ``log_of(name)`` gives a program's log path and ``read(path)`` its text (both
    injected: the stack knows where logs are, a test passes strings).
    ``restarts_expected``: programs killed on purpose (a test of their restart), whose
    new pid and passage through EXITED or BACKOFF are no failure (FATAL still is);
    :meth:`expect_restart` announces one such restart at a time (an injected fault).
    """

    log_of: Callable[[str], Path]
    read: Callable[[Path], str]
    restarts_expected: frozenset[str] = frozenset()
    _pids: dict[str, int] = field(default_factory=dict)
    # Restarts announced by expect_restart and not yet seen, by program.
    _expected: dict[str, int] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def expect_restart(self, name: str) -> None:
        """Program ``name`` is about to be killed on purpose (an injected fault): its
        death and one restart are not a failure; a second restart still is. Thread-safe."""
        with self._lock:
            self._expected[name] = self._expected.get(name, 0) + 1

    def check(self, infos: list[Mapping[str, Any]]) -> None:
        """Raise :class:`ServiceFailed` for the first program that failed since the last
        call: a failed state, or a new pid (restarted after dying), unless expected."""
        for info in infos:
            name, state, pid = str(info["name"]), str(info["statename"]), int(info["pid"])
            what = ""
            with self._lock:
                counted = self._expected.get(name, 0)
            expected = name in self.restarts_expected or counted > 0
            if expected and state in RESTARTING_STATES:
                pass
            elif state in FAILED_STATES:
                what = _failed_state(state, info)
            elif pid and self._pids.get(name, pid) != pid and counted:
                with self._lock:
                    self._expected[name] -= 1  # the announced restart came
            elif pid and self._pids.get(name, pid) != pid and not expected:
                code = info.get("exitstatus")
                died = f"exited with code {code}" if code and code > 0 else "died"
                what = f"{died} and was restarted (crash loop)"
            if pid:
                self._pids[name] = pid
            if what:
                path = self.log_of(name)
                raise ServiceFailed(name, what, path, self.read(path))


def _failed_state(state: str, info: Mapping[str, Any]) -> str:
    exit_status = info.get("exitstatus")
    spawn_error = str(info.get("spawnerr") or "")
    if state in ("EXITED", "BACKOFF") and exit_status is not None and not info.get("pid"):
        restart = " (supervisord restarts it: a crash loop)" if state == "BACKOFF" else ""
        return f"exited with code {exit_status}{restart}"
    if spawn_error and not spawn_error.startswith("Bad exit code"):
        return f"could not be started ({state}: {spawn_error})"
    if state == "FATAL":
        return "kept exiting during start-up; supervisord gave up (FATAL)"
    return f"stopped ({state})"
