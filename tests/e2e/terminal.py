"""A real terminal for the end-to-end tests: a program run in a tmux session of its own
(its own server socket), keys sent with ``send-keys`` and the screen read with
``capture-pane``, as a person at a terminal would see it."""

from __future__ import annotations

import shlex
import shutil
import subprocess
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from types import TracebackType
from typing import TypeVar

T = TypeVar("T")


class Terminal:
    """``command`` in a ``columns`` x ``rows`` terminal; after it ends the pane stays
    (its last screen readable) until the terminal is closed."""

    def __init__(self, command: Sequence[str], cwd: Path, columns: int = 110, rows: int = 40):
        if shutil.which("tmux") is None:
            raise FileNotFoundError("tmux is not installed (make test installs it)")
        self.socket = f"teleop-test-{uuid.uuid4().hex[:8]}"
        self.session = "run"
        # The pane outlives the program (remain-on-exit), so its last screen can be read.
        shell = f"cd {shlex.quote(str(cwd))} && {shlex.join(command)}"
        self._tmux("new-session", "-d", "-s", self.session, "-x", str(columns), "-y",
                   str(rows), shell)  # fmt: skip
        self._tmux("set-option", "-t", self.session, "remain-on-exit", "on")

    def _tmux(self, *args: str) -> str:
        result = subprocess.run(
            ["tmux", "-L", self.socket, *args], capture_output=True, text=True, check=True
        )
        return result.stdout

    def screen(self) -> str:
        """The terminal's text now."""
        return self._tmux("capture-pane", "-p", "-t", self.session)

    def press(self, key: str) -> None:
        """One key, as typed (``-l``: a literal character, never a tmux key name)."""
        self._tmux("send-keys", "-t", self.session, "-l", key)

    def exited(self) -> int | None:
        """The program's exit status once it has ended, else None."""
        dead, status, signal = self._tmux(
            "display-message", "-p", "-t", self.session,
            "#{pane_dead}:#{pane_dead_status}:#{pane_dead_signal}",
        ).strip().split(":")  # fmt: skip
        if dead != "1" or not (status or signal):
            return None  # running, or dead a moment ago with its status not yet filled in
        # Killed by a signal: no status; as a shell says it, 128 + the signal's number.
        return int(status) if status else 128 + int(signal)

    def wait_for(self, read: Callable[[str], T | None], timeout_s: float, what: str) -> T:
        """The first non-None ``read(screen)`` within ``timeout_s``; AssertionError with
        the last screen otherwise."""
        deadline = time.monotonic() + timeout_s
        while True:
            screen = self.screen()
            value = read(screen)
            if value is not None:
                return value
            if time.monotonic() > deadline:
                raise AssertionError(f"no {what} within {timeout_s:g} s; the screen:\n{screen}")
            time.sleep(0.1)

    def close(self) -> None:
        subprocess.run(["tmux", "-L", self.socket, "kill-server"], capture_output=True)

    def __enter__(self) -> Terminal:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
