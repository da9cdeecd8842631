"""Opening a recording: the native Rerun viewer, or the web viewer on a loopback port.

Both use the ``rerun`` executable that comes with ``rerun-sdk`` (next to the Python
interpreter), so the viewer always matches the SDK that wrote the recording.

The web viewer is ``rerun --serve-web``: an HTTP server for the viewer's page and a gRPC
server that the page reads from. It serves a saved ``.rrd``, or, with no file, whatever
a recorder streams to its gRPC address (``recorder.grpc_url``; ``teleop run --web``).
The gRPC server keeps what it received for viewers that connect later.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

from teleop.core.net import LOOPBACK, LoopbackPorts
from teleop.core.rundir import segment_paths

# How long to wait for the web viewer's HTTP port to accept connections (s) ...
SERVE_TIMEOUT_S = 30.0
# ... polling it this often (s).
SERVE_POLL_S = 0.05
# Memory the gRPC server may keep for late viewers (Rerun's size syntax).
SERVER_MEMORY_LIMIT = "2GiB"
# How long a stopped viewer process gets to exit after SIGINT before it is killed (s).
STOP_TIMEOUT_S = 5.0


class ViewerError(RuntimeError):
    """The viewer could not be started."""


def rerun_executable() -> str:
    """The ``rerun`` executable of this environment (beside the interpreter, else PATH)."""
    beside = Path(sys.executable).with_name("rerun")
    if beside.exists():
        return str(beside)
    found = shutil.which("rerun")
    if found is None:
        raise ViewerError("no `rerun` executable: install rerun-sdk in this environment")
    return found


def grpc_url(port: int) -> str:
    """The Rerun gRPC proxy address of a server on ``port`` (what SDK sinks connect to)."""
    return f"rerun+http://{LOOPBACK}:{port}/proxy"


@dataclass
class WebViewer:
    """A running ``rerun --serve-web``: its process, page address and gRPC address."""

    process: subprocess.Popen[bytes]
    web_port: int
    grpc_port: int

    @property
    def url(self) -> str:
        """The page to open in a browser; it connects itself to the gRPC server."""
        return f"http://{LOOPBACK}:{self.web_port}/?url={quote(self.grpc_url, safe='')}"

    @property
    def grpc_url(self) -> str:
        return grpc_url(self.grpc_port)

    def wait(self) -> int:
        """Block until the server exits (Ctrl-C stops it); its exit code."""
        return self.process.wait()

    def stop(self) -> None:
        """Stop the server (SIGINT, then SIGKILL after STOP_TIMEOUT_S). Safe to call twice.

        The signals go to the server's whole process group: ``rerun`` is a Python wrapper
        around the native server, and a signal to the wrapper alone can leave the native
        server running (and spinning) after the wrapper is gone.
        """
        if self.process.poll() is None:
            _signal_group(self.process.pid, signal.SIGINT)
            try:
                self.process.wait(STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                _signal_group(self.process.pid, signal.SIGKILL)
                self.process.wait()
        _signal_group(self.process.pid, signal.SIGKILL)  # whatever the wrapper left behind

    def __enter__(self) -> WebViewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _signal_group(pid: int, signum: signal.Signals) -> None:
    """Send ``signum`` to the process group led by ``pid`` (gone already: nothing to do)."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pid, signum)


def listening(port: int, timeout_s: float) -> bool:
    """Whether something accepts TCP connections on loopback ``port`` (one attempt,
    ``timeout_s`` at most)."""
    try:
        with socket.create_connection((LOOPBACK, port), timeout=timeout_s):
            return True
    except OSError:
        return False


def _wait_listening(process: subprocess.Popen[bytes], port: int, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise ViewerError(f"the web viewer exited with code {process.returncode}")
        if listening(port, SERVE_POLL_S):
            return
        time.sleep(SERVE_POLL_S)
    raise ViewerError(f"the web viewer did not listen on port {port} within {timeout_s:g} s")


def serve_web(
    rrd_path: Path | None = None,
    *,
    web_port: int | None = None,
    grpc_port: int | None = None,
    log_path: Path | None = None,
) -> WebViewer:
    """Start the web viewer on loopback ports (free ones unless given) and wait until its
    page is served. With ``rrd_path`` it shows that file; without, what SDKs stream to
    its gRPC address. The server's own log goes to ``log_path`` (default: discarded).
    """
    if rrd_path is not None and not rrd_path.is_file():
        raise ViewerError(f"no recording {rrd_path}")
    with LoopbackPorts() as ports:  # held until the server listens on them
        web_port = web_port or ports.take()
        grpc_port = grpc_port or ports.take()
        return _serve_web(rrd_path, web_port, grpc_port, log_path)


def _serve_web(
    rrd_path: Path | None, web_port: int, grpc_port: int, log_path: Path | None
) -> WebViewer:
    args = [
        rerun_executable(),
        "--serve-web",
        "--bind",
        LOOPBACK,
        "--port",
        str(grpc_port),
        "--web-viewer-port",
        str(web_port),
        "--server-memory-limit",
        SERVER_MEMORY_LIMIT,
    ]
    if rrd_path is not None:  # with the segments of restarted recorders: one timeline
        args += [str(path) for path in segment_paths(rrd_path)]
    log = open(log_path, "ab") if log_path is not None else subprocess.DEVNULL
    try:
        # A process group of its own, so that stop() reaches the native server too.
        process = subprocess.Popen(
            args, stdin=subprocess.DEVNULL, stdout=log, stderr=log, start_new_session=True
        )
    finally:
        if log_path is not None:
            log.close()
    viewer = WebViewer(process, web_port, grpc_port)
    try:
        _wait_listening(process, web_port, SERVE_TIMEOUT_S)
        _wait_listening(process, grpc_port, SERVE_TIMEOUT_S)
    except BaseException:
        viewer.stop()
        raise
    return viewer


def open_native(rrd_path: Path) -> int:
    """Open ``rrd_path`` in the native viewer (needs a display); its exit code."""
    if not rrd_path.is_file():
        raise ViewerError(f"no recording {rrd_path}")
    paths = [str(path) for path in segment_paths(rrd_path)]  # every segment, one timeline
    return subprocess.call([rerun_executable(), *paths], stdin=subprocess.DEVNULL)
