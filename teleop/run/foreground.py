"""A service the launcher runs in the user's terminal, not under supervisord: a person's
operator that reads the keyboard and draws its screen there (``--operator keyboard``).

It is started like a supervised program (the same command line: its place in the mesh,
its credentials) once the stack is up, with the launcher's standard input and output (the
terminal) and its log in ``<run_dir>/logs/<name>.log``; it is not restarted (a person who
leaves has left); the launcher stops it (SIGTERM, then SIGKILL) when the run ends.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
from pathlib import Path
from types import TracebackType

from teleop.core.rundir import FOREGROUND_DIR, LOG_DIR
from teleop.run.supervise import Program

# Seconds a foreground service has to write its summary and restore the terminal.
STOP_WAIT_S = 10.0


class ForegroundExited(RuntimeError):
    """The foreground service ended before the run did."""


class Foreground:
    """One :class:`Program` run in the launcher's terminal (a context manager)."""

    def __init__(self, program: Program, run_dir: Path) -> None:
        self.program = program
        self.run_dir = run_dir
        self.log_path = run_dir / LOG_DIR / f"{program.name}.log"  # beside the others' logs
        self.process: subprocess.Popen[bytes] | None = None

    def __enter__(self) -> Foreground:
        # Its command line where a by-hand observer finds the run's processes
        # (teleop.run.outside.stack_endpoints), as supervisord's file holds the others'.
        commands = self.run_dir / FOREGROUND_DIR
        commands.mkdir(exist_ok=True)
        self.log_path.parent.mkdir(exist_ok=True)
        (commands / f"{self.program.name}.json").write_text(json.dumps(self.program.command))
        with open(self.log_path, "ab") as log:
            self.process = subprocess.Popen(
                self.program.command,
                stderr=log,
                env={**os.environ, **self.program.environment},
            )
        return self

    def check(self) -> None:
        """ForegroundExited if it has ended (the run cannot go on without it)."""
        if self.process is not None and (code := self.process.poll()) is not None:
            raise ForegroundExited(
                f"{self.program.name} ended (exit code {code}) before the run did; "
                f"its log: {self.log_path}"
            )

    def stop(self) -> int | None:
        """SIGTERM, then SIGKILL after STOP_WAIT_S; its exit code (None: never started)."""
        process = self.process
        if process is None:
            return None
        if process.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                process.send_signal(signal.SIGTERM)
            try:
                process.wait(STOP_WAIT_S)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        return process.returncode

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()
