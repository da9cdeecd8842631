"""A real terminal for the end-to-end tests: a program run in a tmux session of its own
(its own server socket), keys sent with ``send-keys`` and the screen read with
``capture-pane``, as a person at a terminal would see it."""

from __future__ import annotations

import shlex
import shutil
import subprocess
import tempfile
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
        # The program's exit status goes to a file of its own (tmux's pane_dead_status was
        # seen left empty for a program that had exited); the pane outlives the program
        # (remain-on-exit), so its last screen can be read.
        self._status = Path(tempfile.mkdtemp(prefix="teleop-terminal-")) / "status"
        shell = (
            f"cd {shlex.quote(str(cwd))} && {shlex.join(command)}; "
            f"echo $? > {shlex.quote(str(self._status))}"
        )
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
        try:
            text = self._status.read_text().strip()
        except FileNotFoundError:
            return None
        return int(text) if text else None  # an empty file: being written

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
        shutil.rmtree(self._status.parent, ignore_errors=True)

    def __enter__(self) -> Terminal:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
