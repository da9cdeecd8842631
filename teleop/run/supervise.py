"""Start and stop the project's service processes under a real supervisord.

Every service is its own OS process (see DESIGN.md); supervisord starts them in priority
order, restarts one that dies and stops them as whole process groups. This module renders the
supervisord configuration from typed :class:`Program` records, runs supervisord as a child
(or detached, for ``teleop up``) and talks to it over XML-RPC on a unix socket in the run
directory, so a second process (``teleop status`` / ``teleop down``) can :meth:`Stack.attach`.

The guarantee the tests check: after :meth:`Stack.stop` (also on Ctrl-C or SIGTERM of the
process that holds a ``with Stack(...)`` block) no process of the stack is left.
"""

from __future__ import annotations

import contextlib
import http.client
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import threading
import time
import xmlrpc.client
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType, TracebackType
from typing import Any

from supervisor.xmlrpc import SupervisorTransport

from teleop.core.rundir import (
    LOG_DIR,
    SUPERVISOR_CONF_FILE,
    SUPERVISOR_CONSOLE_FILE,
    SUPERVISOR_LOG_FILE,
    SUPERVISOR_PID_FILE,
    SUPERVISOR_SOCKET_FILE,
    program_log_path,
)
from teleop.run.failure import ServiceFailed, program_log_text

# Seconds supervisord waits after the stop signal (SIGINT) before SIGKILLing a program's group.
# A clean stop takes well under a second, but a recorder finishing its .rrd on a starved
# machine can need several seconds, and a killed recorder writes no summary.
STOP_WAIT_S = 15
# Default time for start(): supervisord up plus every program RUNNING (startsecs included), s.
# A program that fails is seen at once (BACKOFF, FATAL, EXITED), so this bounds only a
# supervisord too starved to spawn (a machine loaded many times over its cores).
# The same bound as the services' ready tokens (the launcher's wait after this one).
DEFAULT_START_TIMEOUT_S = 60.0
# Default time for stop(): supervisord's own graceful stop must fit (STOP_WAIT_S per program
# group, run in parallel by priority) before we fall back to signalling it ourselves, s.
DEFAULT_STOP_TIMEOUT_S = STOP_WAIT_S + 5.0
# Programs at or above this supervisord priority (the services that produce: plant,
# controller, devices, operator, eye view) are all told to stop at once; those below it
# (the recorder, the idle pollers) in supervisord's order once the others are gone, so
# the recorder still takes what the producers sent last.
STOP_AT_ONCE_MIN_PRIORITY = 20
# Time after SIGTERM to supervisord's process group before SIGKILL, s.
KILL_GRACE_S = 2.0
# While supervisord shuts down, the stop signal goes again to every program still there
# this often (s): a program spawned a few ms before the stop can lose supervisord's signal
# (it lands between fork and exec, in the child's copy of supervisord's own handler) and
# would otherwise be killed only after STOP_WAIT_S. Long enough that supervisord has
# asked every program in its own order first (a recorder stops after what it records).
RESIGNAL_S = 5.0
# Poll interval while waiting for start-up or shutdown (not a control loop), s.
POLL_INTERVAL_S = 0.02
# supervisord notices that a program exited at its main loop's next turn, and a SIGCHLD
# does not bring that turn on (Python resumes its poll after the signal handler): alone,
# its loop turns once a second, and each step of a shutdown (a priority group stopped,
# the next one signalled, its own exit) waits for a turn. While it shuts down, the stop
# asks it for its state this often: each request is a turn (what exited is reaped).
SHUTDOWN_NUDGE_S = 0.05
# Socket timeout of one such request: a supervisord too busy to answer is left alone, s.
NUDGE_TIMEOUT_S = 0.5
# Socket timeout of one XML-RPC call; stopProcess(wait=True) may take up to STOP_WAIT_S, s.
RPC_TIMEOUT_S = STOP_WAIT_S + 5.0
# How much of a program's log an error message quotes, bytes.
LOG_TAIL_BYTES = 4_000
# Longest unix socket path the kernel accepts (sun_path is 108 bytes with the NUL), bytes.
UNIX_SOCKET_PATH_MAX_BYTES = 107
# Default startsecs: a program must stay up this long to count as started (supervisord's), s.
DEFAULT_STARTSECS = 1


_PROGRAM_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
_ENV_KEY_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
# Process states of supervisord that mean a program failed to start.
_FAILED_STATES = frozenset({"BACKOFF", "FATAL", "EXITED", "UNKNOWN"})
_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
# Runs before supervisord (then exec's it, same pid) to ask the kernel for SIGTERM if the
# starting process dies, even by SIGKILL: supervisord then stops its programs by itself.
# A wrapper rather than preexec_fn, which is unsafe once the parent has threads (Zenoh's).
_EXEC_WITH_PDEATHSIG = (
    "import ctypes, os, signal, sys\n"
    "PR_SET_PDEATHSIG = 1\n"
    "ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)\n"
    "if os.getppid() != int(sys.argv[1]):\n"
    "    sys.exit('parent exited before supervisord started')\n"
    "os.execv(sys.argv[2], sys.argv[2:])\n"
)


class StackError(RuntimeError):
    """The stack could not be started, reached or stopped; the message says why."""


class StartTimeout(StackError):
    """Not every program of the stack was RUNNING within the start's time-out (none
    failed: a machine too loaded to start them in time)."""


class ProgramFailed(StackError, ServiceFailed):
    """A program of the stack failed to start: the failure block of teleop.run.failure."""


@dataclass(frozen=True)
class Program:
    """One service process as supervisord should run it.

    ``command`` is an argv list (no shell). ``priority``: lower starts first and stops last;
    supervisord does not wait for RUNNING between priorities, so services still wait for
    their peers on the bus. ``startsecs``: seconds the process must stay up to count as
    started (0 makes a process that exits at once look RUNNING for a moment).
    """

    name: str
    command: list[str]
    priority: int = 999
    environment: dict[str, str] = field(default_factory=dict)
    autorestart: bool = True
    startsecs: int = DEFAULT_STARTSECS

    def __post_init__(self) -> None:
        if not _PROGRAM_NAME_RE.fullmatch(self.name):
            raise ValueError(f"program name {self.name!r} must match {_PROGRAM_NAME_RE.pattern}")
        if not self.command:
            raise ValueError(f"program {self.name!r} has an empty command")
        if self.startsecs < 0:
            raise ValueError(f"program {self.name!r}: startsecs must be >= 0")
        for key in self.environment:
            if not _ENV_KEY_RE.fullmatch(key):
                raise ValueError(f"program {self.name!r}: bad environment variable name {key!r}")


# ---------------------------------------------------------------------------------------------
# Rendering: supervisord reads the file with configparser (';' and '#' after whitespace start an
# inline comment, values are stripped, no multi-line values here), then %-expands most values
# (so '%' must be doubled), then splits `command` with shlex (POSIX) and `environment` with a
# non-POSIX shlex that strips every quote character at both ends of a value.


def _ini_value(text: str, what: str, expansions: int = 1) -> str:
    """Make ``text`` survive configparser and ``expansions`` rounds of %-expansion unchanged."""
    if "\n" in text or "\r" in text:
        raise ValueError(f"{what}: newlines cannot be written to supervisord.conf: {text!r}")
    if text != text.strip():
        raise ValueError(f"{what}: leading/trailing whitespace would be stripped: {text!r}")
    if re.search(r"\s[;#]", text):
        raise ValueError(f"{what}: whitespace before ';' or '#' starts a comment: {text!r}")
    if "%(here)s" in text:
        # supervisord substitutes this literally in every value before %-expansion.
        raise ValueError(f"{what}: '%(here)s' cannot be escaped for supervisord: {text!r}")
    return text.replace("%", "%" * 2**expansions)


def _command_value(argv: list[str], what: str) -> str:
    """Quote an argv for supervisord's shlex.split so that every argument survives.

    An argument whose quoted form would put ';' or '#' after whitespace (a configparser
    comment) gets those characters backslash-escaped outside the quotes instead.
    """
    parts = []
    for arg in argv:
        rendered = shlex.quote(arg)
        if re.search(r"\s[;#]", rendered):
            chunks = re.split(r"([;#])", arg)
            rendered = "".join(
                "\\" + chunk if chunk in (";", "#") else shlex.quote(chunk)
                for chunk in chunks
                if chunk
            )
        parts.append(rendered)
    return _ini_value(" ".join(parts), what)


def _environment_value(environment: Mapping[str, str], what: str) -> str:
    """Render KEY="value",... so that commas, quotes and '%' in values survive.

    supervisord's parser has no escapes: a value is wrapped in whichever quote it does not
    contain, and values holding both quote kinds or starting/ending with one are refused.
    """
    items = []
    for key, value in environment.items():
        if '"' in value and "'" in value:
            raise ValueError(f"{what}: {key} holds both quote kinds, supervisord cannot parse it")
        if value[:1] in ("'", '"') or value[-1:] in ("'", '"'):
            raise ValueError(f"{what}: {key} starts or ends with a quote, supervisord strips it")
        quote = "'" if '"' in value else '"'
        items.append(f"{key}={quote}{value}{quote}")
    return _ini_value(",".join(items), what)


def _path_value(path: Path, what: str, expansions: int = 1) -> str:
    return _ini_value(str(path), what, expansions)


@dataclass
class _StopSnapshot:
    """What stop() must make sure is gone: supervisord and the program process groups."""

    supervisord_pid: int | None
    program_pgids: list[int]
    stop_at_once_pgids: list[int]  # see STOP_AT_ONCE_MIN_PRIORITY


class Stack:
    """A set of programs run by one supervisord whose files all live in ``run_dir``.

    ``run_dir`` holds supervisord.conf, the control socket (mode 0700), supervisord's pid and
    log files and ``logs/<program>.log``. As a context manager the stack is started on entry
    and stopped on exit, and SIGINT/SIGTERM raise KeyboardInterrupt in the main thread
    meanwhile, so Ctrl-C or a ``kill`` of the holder unwinds through the stop.
    """

    def __init__(self, run_dir: Path, programs: list[Program]) -> None:
        self.run_dir = Path(run_dir).absolute()
        names = [p.name for p in programs]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate program names in {names}")
        self.programs = list(programs)
        socket_bytes = len(os.fsencode(self.socket_path))
        if socket_bytes > UNIX_SOCKET_PATH_MAX_BYTES:
            raise ValueError(
                f"socket path {self.socket_path} is {socket_bytes} bytes, more than the "
                f"{UNIX_SOCKET_PATH_MAX_BYTES} a unix socket allows: use a shorter run_dir"
            )
        self._proc: subprocess.Popen[bytes] | None = None
        self._attached = False
        self._signals: contextlib.ExitStack | None = None

    # -- files ---------------------------------------------------------------------------------

    @property
    def conf_path(self) -> Path:
        """The rendered supervisord configuration."""
        return self.run_dir / SUPERVISOR_CONF_FILE

    @property
    def socket_path(self) -> Path:
        """supervisord's XML-RPC unix socket."""
        return self.run_dir / SUPERVISOR_SOCKET_FILE

    @property
    def log_dir(self) -> Path:
        """Directory of the per-program logs (stdout and stderr merged)."""
        return self.run_dir / LOG_DIR

    def log_path(self, name: str) -> Path:
        """Log file of program ``name``."""
        return program_log_path(self.run_dir, name)

    def render(self) -> str:
        """The supervisord.conf text for this stack (raises ValueError if a value can't fit)."""
        run = self.run_dir
        lines = [
            "; Generated by teleop.run.supervise: edit the Program records, not this file.",
            "[supervisord]",
            "nodaemon=true",
            "silent=true",
            f"logfile={_path_value(run / SUPERVISOR_LOG_FILE, 'logfile')}",
            f"pidfile={_path_value(run / SUPERVISOR_PID_FILE, 'pidfile')}",
            f"childlogdir={_path_value(self.log_dir, 'childlogdir')}",
            "",
            "[unix_http_server]",
            f"file={_path_value(self.socket_path, 'socket')}",
            "chmod=0700",
            "",
            "[rpcinterface:supervisor]",
            "supervisor.rpcinterface_factory=supervisor.rpcinterface:make_main_rpcinterface",
            "",
            "[supervisorctl]",
            f"serverurl=unix://{_path_value(self.socket_path, 'serverurl')}",
        ]
        for program in self.programs:
            what = f"program {program.name}"
            lines += [
                "",
                f"[program:{program.name}]",
                f"command={_command_value(program.command, what + ' command')}",
                f"priority={program.priority}",
                "autostart=true",
                f"autorestart={'true' if program.autorestart else 'false'}",
                f"startsecs={program.startsecs}",
                "stopsignal=INT",
                "stopasgroup=true",
                "killasgroup=true",
                f"stopwaitsecs={STOP_WAIT_S}",
                "redirect_stderr=true",
                # supervisord 4.3 %-expands stdout_logfile twice (get(), then expand() again).
                f"stdout_logfile={_path_value(self.log_path(program.name), what + ' log', 2)}",
            ]
            if program.environment:
                env = _environment_value(program.environment, what + " environment")
                lines.append(f"environment={env}")
        return "\n".join(lines) + "\n"

    # -- start ---------------------------------------------------------------------------------

    def start(self, timeout_s: float = DEFAULT_START_TIMEOUT_S, detach: bool = False) -> None:
        """Run supervisord and return once it answers and every program is RUNNING.

        supervisord gets its own session, so a Ctrl-C in the terminal reaches only this
        process, which then stops the stack in order (see :meth:`__enter__`); if this process
        dies without unwinding (SIGKILL), the kernel sends supervisord SIGTERM and it stops
        the programs itself (when started from the main thread). With ``detach=True``
        supervisord outlives this process (``teleop up``); stop it later with
        ``Stack.attach(run_dir).stop()``. On any failure, including an interrupt,
        the stack is stopped and StackError says which program failed, with its log tail.
        """
        if self._attached:
            raise StackError("an attached stack can be inspected and stopped, not started")
        if self._proc is not None and self._proc.poll() is None:
            raise StackError(f"stack in {self.run_dir} is already started")
        if self._answers():
            raise StackError(f"a supervisord already serves {self.socket_path}")
        conf_text = self.render()
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.conf_path.write_text(conf_text)
        argv = [str(Path(sys.executable).parent / "supervisord"), "-c", str(self.conf_path)]
        if not detach and _in_main_thread():
            # The kernel's parent-death signal fires when the creating *thread* ends, so it
            # is only tied to the process lifetime when set from the main thread.
            argv = [sys.executable, "-c", _EXEC_WITH_PDEATHSIG, str(os.getpid()), *argv]
        with open(self.run_dir / SUPERVISOR_CONSOLE_FILE, "ab") as console:
            self._proc = subprocess.Popen(
                argv,
                stdin=subprocess.DEVNULL,
                stdout=console,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        try:
            self._wait_started(timeout_s)
        except BaseException:
            self.stop()
            raise

    def _wait_started(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        expected = {p.name for p in self.programs}
        states: dict[str, str] = {}
        while True:
            assert self._proc is not None
            if self._proc.poll() is not None:
                raise StackError(
                    f"supervisord exited with code {self._proc.returncode}:\n"
                    + _tail(self.run_dir / SUPERVISOR_CONSOLE_FILE)
                )
            with contextlib.suppress(OSError, xmlrpc.client.Error, http.client.HTTPException):
                states = self.status()
            for name, state in states.items():
                if state in _FAILED_STATES:
                    path = self.log_path(name)
                    supervisord_log = self.run_dir / SUPERVISOR_LOG_FILE
                    text = program_log_text(path, supervisord_log)
                    raise ProgramFailed(name, f"failed to start ({state})", path, text)
            if set(states) == expected and all(s == "RUNNING" for s in states.values()):
                return
            if time.monotonic() >= deadline:
                pending = {n: states.get(n, "not started") for n in sorted(expected)}
                tails = "\n".join(
                    f"--- {n}:\n{self.log_tail(n)}" for n, s in pending.items() if s != "RUNNING"
                )
                raise StartTimeout(
                    f"stack not RUNNING after {timeout_s} s: {pending}\n{tails}\n"
                    f"--- supervisord:\n{_tail(self.run_dir / SUPERVISOR_CONSOLE_FILE)}"
                )
            time.sleep(POLL_INTERVAL_S)

    # -- attach and inspect --------------------------------------------------------------------

    @classmethod
    def attach(cls, run_dir: Path) -> Stack:
        """A handle on a stack started by another process (or object) in ``run_dir``.

        It can report status, start/stop programs and stop the whole stack; it cannot start
        it. Raises StackError if no supervisord answers there.
        """
        stack = cls(Path(run_dir), [])
        stack._attached = True
        if not stack.conf_path.exists() or not stack._answers():
            raise StackError(f"no running stack in {stack.run_dir}")
        return stack

    def _rpc(self, timeout_s: float = RPC_TIMEOUT_S) -> xmlrpc.client.ServerProxy:
        """A fresh XML-RPC proxy (a new connection each time: no state left by an interrupt)."""
        transport = _UnixTransport(self.socket_path, timeout_s)
        # The host part is ignored by the unix transport; it only has to parse as a URL.
        return xmlrpc.client.ServerProxy("http://localhost", transport=transport)

    def _answers(self, timeout_s: float = RPC_TIMEOUT_S) -> bool:
        if not self.socket_path.exists():
            return False
        try:
            with self._rpc(timeout_s) as rpc:
                rpc.supervisor.getState()
        except (OSError, xmlrpc.client.Error, http.client.HTTPException):
            return False
        return True

    def status(self) -> dict[str, str]:
        """State name of every program (RUNNING, STARTING, BACKOFF, STOPPED, EXITED, FATAL...)."""
        with self._rpc() as rpc:
            infos = rpc.supervisor.getAllProcessInfo()
        return {info["name"]: info["statename"] for info in infos}

    def process_infos(self) -> list[dict[str, Any]]:
        """supervisord's record of every program (name, statename, pid, exitstatus,
        spawnerr...): what :class:`teleop.run.failure.ProgramWatch` judges."""
        with self._rpc() as rpc:
            return list(rpc.supervisor.getAllProcessInfo())

    def pid(self, name: str) -> int:
        """Pid of program ``name`` (0 when it is not running)."""
        with self._rpc() as rpc:
            return int(rpc.supervisor.getProcessInfo(name)["pid"])

    def signal_program(self, name: str, signum: int, *, group: bool = False) -> None:
        """Send ``signum`` to the main process of program ``name``, or with ``group`` to
        its whole process group (supervisord makes each program a group leader): a
        crash, a freeze (SIGSTOP) or a thaw (SIGCONT) of everything the program runs."""
        pid = self.pid(name)
        if pid == 0:
            raise StackError(f"program {name!r} is not running")
        if group and os.getpgid(pid) == pid:
            os.killpg(pid, signum)
        else:
            os.kill(pid, signum)

    def stop_program(self, name: str) -> None:
        """Stop one program and wait until it is down; autorestart does not bring it back."""
        with self._rpc() as rpc:
            rpc.supervisor.stopProcess(name, True)

    def start_program(self, name: str) -> None:
        """Start one stopped program and wait until it is RUNNING (startsecs elapsed)."""
        with self._rpc() as rpc:
            rpc.supervisor.startProcess(name, True)

    def log_tail(self, name: str, max_bytes: int = LOG_TAIL_BYTES) -> str:
        """The last ``max_bytes`` of program ``name``'s log, for error messages."""
        return _tail(self.log_path(name), max_bytes)

    @property
    def supervisord_pid(self) -> int | None:
        """Pid of this stack's supervisord, or None if it is not running."""
        if self._proc is not None:
            return self._proc.pid if self._proc.poll() is None else None
        pid = _read_pid(self.run_dir / SUPERVISOR_PID_FILE)
        if pid is not None and _is_supervisord_of(pid, self.conf_path):
            return pid
        return None

    # -- stop ----------------------------------------------------------------------------------

    def stop(self, timeout_s: float = DEFAULT_STOP_TIMEOUT_S) -> None:
        """Stop every program and supervisord; afterwards no process of the stack is left.

        First the orderly way (XML-RPC shutdown: SIGINT to each program group, SIGKILL after
        STOP_WAIT_S); if supervisord is still there after ``timeout_s``, SIGTERM then SIGKILL
        to its process group; finally SIGKILL to any program process group that survived
        (a grandchild that ignored SIGINT). Safe to call twice, and from another process via
        :meth:`attach`. SIGINT/SIGTERM arriving meanwhile are held and re-raised afterwards, so
        a second Ctrl-C cannot cut the stop short.
        """
        with _deferred_stop_signals():
            self._stop(timeout_s)

    def _stop(self, timeout_s: float) -> None:
        snapshot = self._snapshot()
        if snapshot.supervisord_pid is not None:
            with contextlib.suppress(OSError, xmlrpc.client.Error, http.client.HTTPException):
                with self._rpc() as rpc:
                    rpc.supervisor.shutdown()
            # supervisord stops the programs one at a time, and a process takes a second
            # or more to exit on a starved machine: in series that outlasts the timeout.
            # Shutting down, it restarts nothing, so the producers are told at once.
            for pgid in snapshot.stop_at_once_pgids:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(pgid, signal.SIGINT)
            pid = snapshot.supervisord_pid
            if not self._wait_gone_resignalling(pid, snapshot.program_pgids, timeout_s):
                self._signal_own_group(pid, signal.SIGTERM)
                if not self._wait_gone(pid, KILL_GRACE_S):
                    self._signal_own_group(pid, signal.SIGKILL)
                    self._wait_gone(pid, KILL_GRACE_S)
        for pgid in snapshot.program_pgids:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(pgid, signal.SIGKILL)
        if self._proc is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                self._proc.wait(timeout=KILL_GRACE_S)

    def _snapshot(self) -> _StopSnapshot:
        pid = self.supervisord_pid
        pgids: list[int] = []
        at_once: list[int] = []
        if pid is not None:
            with contextlib.suppress(OSError, xmlrpc.client.Error, http.client.HTTPException):
                with self._rpc() as rpc:
                    infos = rpc.supervisor.getAllProcessInfo()
                    configs = rpc.supervisor.getAllConfigInfo()
                priority = {str(c["name"]): int(c["process_prio"]) for c in configs}
                for info in infos:
                    program_pid = int(info["pid"])
                    # supervisord makes each program the leader of its own process group;
                    # only such groups are ours to kill (never the caller's own group).
                    with contextlib.suppress(ProcessLookupError):
                        if program_pid and os.getpgid(program_pid) == program_pid:
                            pgids.append(program_pid)
                            if priority.get(str(info["name"]), 0) >= STOP_AT_ONCE_MIN_PRIORITY:
                                at_once.append(program_pid)
        return _StopSnapshot(supervisord_pid=pid, program_pgids=pgids, stop_at_once_pgids=at_once)

    def _wait_gone_resignalling(self, pid: int, pgids: list[int], timeout_s: float) -> bool:
        """:meth:`_wait_gone` for supervisord, sending SIGINT again to the program groups
        still there every :data:`RESIGNAL_S` (a signal lost at a program's start)."""
        deadline = time.monotonic() + timeout_s
        while True:
            left_s = deadline - time.monotonic()
            if self._wait_gone(pid, min(RESIGNAL_S, max(left_s, 0.0)), nudge=True):
                return True
            if left_s <= RESIGNAL_S:
                return False
            for pgid in pgids:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(pgid, signal.SIGINT)

    def _wait_gone(self, pid: int, timeout_s: float, *, nudge: bool = False) -> bool:
        """Wait until ``pid`` has exited (reaped or zombie); True if it did within the time.
        ``nudge``: ``pid`` is supervisord shutting down; ask it for its state every
        :data:`SHUTDOWN_NUDGE_S` meanwhile, so that its loop turns."""
        deadline = time.monotonic() + timeout_s
        nudged = 0.0
        while True:
            if self._proc is not None and self._proc.pid == pid:
                if self._proc.poll() is not None:
                    return True
            elif not _pid_alive(pid):
                return True
            now = time.monotonic()
            if now >= deadline:
                return False
            if nudge and now - nudged >= SHUTDOWN_NUDGE_S:
                nudged = now
                self._answers(NUDGE_TIMEOUT_S)
            time.sleep(POLL_INTERVAL_S)

    def _signal_own_group(self, pid: int, signum: int) -> None:
        """Signal supervisord's process group, which start() made its own session."""
        with contextlib.suppress(ProcessLookupError):
            if os.getpgid(pid) == pid:
                os.killpg(pid, signum)
            else:
                os.kill(pid, signum)

    # -- context manager -----------------------------------------------------------------------

    def __enter__(self) -> Stack:
        """Start the stack with SIGINT/SIGTERM turned into KeyboardInterrupt (main thread)."""
        signals = contextlib.ExitStack()
        signals.enter_context(interrupt_on_signals())
        try:
            self.start()
        except BaseException:
            signals.close()
            raise
        self._signals = signals
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            self.stop()
        finally:
            if self._signals is not None:
                self._signals.close()
                self._signals = None


class _UnixHTTPConnection(http.client.HTTPConnection):
    """HTTP over a unix socket, with a timeout (supervisor's own connection has none)."""

    def __init__(self, socket_path: Path, timeout_s: float) -> None:
        super().__init__("localhost", timeout=timeout_s)
        self._socket_path = str(socket_path)

    def connect(self) -> None:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.settimeout(self.timeout)
        try:
            sock.connect(self._socket_path)
        except BaseException:
            sock.close()
            raise
        self.sock = sock


class _UnixTransport(SupervisorTransport):
    """supervisor's XML-RPC transport, on our connection class so a hung server times out."""

    def __init__(self, socket_path: Path, timeout_s: float) -> None:
        super().__init__(serverurl=f"unix://{socket_path}")
        self._get_connection = lambda: _UnixHTTPConnection(socket_path, timeout_s)


# -- signals -----------------------------------------------------------------------------------


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _raise_interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt(f"received {signal.Signals(signum).name}")


@contextlib.contextmanager
def interrupt_on_signals() -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM raise KeyboardInterrupt in the main thread.

    SIGTERM would otherwise end the process without unwinding, so ``finally`` blocks and
    ``__exit__`` methods (which stop child processes) would never run. Outside the main
    thread Python cannot install handlers and this does nothing.
    """
    if not _in_main_thread():
        yield
        return
    previous = {signum: signal.signal(signum, _raise_interrupt) for signum in _STOP_SIGNALS}
    try:
        yield
    finally:
        _restore_handlers(previous)


def _restore_handlers(previous: Mapping[int, Any]) -> None:
    for signum, handler in previous.items():
        if handler is not None:  # None: a handler set outside Python, cannot be reinstalled
            signal.signal(signum, handler)


@contextlib.contextmanager
def _deferred_stop_signals() -> Iterator[None]:
    """Hold SIGINT/SIGTERM during a stop and deliver the first one afterwards."""
    if not _in_main_thread():
        yield
        return
    received: list[int] = []

    def hold(signum: int, frame: FrameType | None) -> None:
        received.append(signum)

    previous: dict[int, Any] = {signum: signal.signal(signum, hold) for signum in _STOP_SIGNALS}
    try:
        yield
    finally:
        _restore_handlers(previous)
        if received:
            signal.raise_signal(received[0])


# -- process helpers ---------------------------------------------------------------------------


def _tail(path: Path, max_bytes: int = LOG_TAIL_BYTES) -> str:
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - max_bytes))
            return f.read().decode(errors="replace")
    except FileNotFoundError:
        return f"(no log at {path})"


def _read_pid(path: Path) -> int | None:
    try:
        return int(path.read_text().strip())
    except (FileNotFoundError, ValueError):
        return None


def _pid_alive(pid: int) -> bool:
    """True if ``pid`` runs; a zombie (exited, not yet reaped by its parent) counts as gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return False
    # The state follows the parenthesised command name, which may itself contain ')'.
    return stat[stat.rindex(")") + 2] != "Z"


def _is_supervisord_of(pid: int, conf_path: Path) -> bool:
    """Guard against a stale pidfile whose pid now belongs to an unrelated process."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except (FileNotFoundError, ProcessLookupError):
        return False
    return _pid_alive(pid) and os.fsencode(conf_path) in argv
