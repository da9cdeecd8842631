"""Stack under a real supervisord with trivial real programs: start, status, autorestart, stop
leaves nothing, quoting of environment and arguments, attach from elsewhere, clear start
errors, and clean-up when the holder gets SIGINT/SIGTERM or is SIGKILLed."""

import json
import os
import select
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from teleop.run.supervise import STOP_WAIT_S, Program, Stack, StackError

# Waits in these tests poll with a deadline; the deadline only bounds a failure.
WAIT_TIMEOUT_S = 15.0
POLL_S = 0.02

# Sleeps until SIGINT (supervisord's stop signal), then exits 0.
SLEEPER = "import signal, sys; signal.signal(signal.SIGINT, lambda *a: sys.exit(0)); signal.pause()"
# Writes its argv[2:] and T_* environment as JSON to argv[1], then sleeps like SLEEPER. One line:
# supervisord.conf cannot hold a newline in a command.
REPORTER = (
    "import json, os, signal, sys; "
    "env = {k: v for k, v in os.environ.items() if k[:2] == 'T_'}; "
    "report = {'argv': sys.argv[2:], 'env': env}; "
    "open(sys.argv[1] + '.tmp', 'w').write(json.dumps(report)); "
    "os.replace(sys.argv[1] + '.tmp', sys.argv[1]); "
    "signal.signal(signal.SIGINT, lambda *a: sys.exit(0)); signal.pause()"
)
REPO_ROOT = Path(__file__).resolve().parents[2]


def sleeper(name: str, **kwargs) -> Program:
    # startsecs=0: RUNNING as soon as spawned, which keeps the tests fast.
    return Program(name=name, command=[sys.executable, "-c", SLEEPER], startsecs=0, **kwargs)


def wait_for(predicate, what: str, timeout_s: float = WAIT_TIMEOUT_S):
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(POLL_S)


def alive(pid: int) -> bool:
    """Running and not a zombie."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat[stat.rindex(")") + 2] != "Z"


def assert_all_gone(pids):
    wait_for(lambda: not any(alive(p) for p in pids), f"pids {pids} to exit", timeout_s=5.0)


def test_start_status_autorestart_stop(tmp_path):
    stack = Stack(tmp_path / "run", [sleeper("alpha", priority=10), sleeper("beta")])
    with stack:
        assert stack.status() == {"alpha": "RUNNING", "beta": "RUNNING"}
        pids = {name: stack.pid(name) for name in ("alpha", "beta")}
        assert all(alive(p) for p in pids.values())
        # Each program leads its own process group (what stopasgroup/killasgroup act on).
        assert all(os.getpgid(p) == p for p in pids.values())

        stack.signal_program("alpha", signal.SIGKILL)
        new_pid = wait_for(
            lambda: (
                stack.status()["alpha"] == "RUNNING"
                and stack.pid("alpha") not in (0, pids["alpha"])
                and stack.pid("alpha")
            ),
            "alpha to be restarted",
        )
        assert stack.pid("beta") == pids["beta"]

        stack.stop_program("beta")
        assert stack.status()["beta"] == "STOPPED"
        stack.start_program("beta")
        assert stack.status()["beta"] == "RUNNING"
        all_pids = [new_pid, stack.pid("beta"), stack.supervisord_pid]
    assert_all_gone(all_pids)
    assert stack.supervisord_pid is None
    stack.stop()  # idempotent
    assert "stopasgroup=true" in stack.conf_path.read_text()


def test_environment_arguments_and_run_dir_survive_quoting(tmp_path):
    run_dir = tmp_path / "run 100%(x)s;dir"
    env = {
        "T_COMMA": "a,b=c,d",
        "T_DQUOTE": 'say "hi" there',
        "T_SQUOTE": "it's",
        "T_PERCENT": "100% %(ENV_HOME)s %%",
        "T_SEMI": "x;y#z",
        "T_EMPTY": "",
        "T_SPACES": "a  b\tc",
        "T_UNICODE": "µ-ü",
    }
    argv = ["plain", "with space", "a ; b", "c #d", "50%", "'q'", '"dq"', "", "$HOME", "\\n"]
    report = tmp_path / "report.json"
    program = Program(
        name="reporter",
        command=[sys.executable, "-c", REPORTER, str(report), *argv],
        environment=env,
        startsecs=0,
    )
    with Stack(run_dir, [program]) as stack:
        wait_for(report.exists, "the reporter's output")
        assert json.loads(report.read_text()) == {"argv": argv, "env": env}
        assert stack.status() == {"reporter": "RUNNING"}
        assert stack.socket_path.parent == run_dir.absolute()
        assert (run_dir / "logs" / "reporter.log").exists()


@pytest.mark.parametrize(
    "value",
    ["both ' and \" quotes", "'leading quote", 'trailing quote"', "a ;comment", "nl\n", "%(here)s"],
)
def test_unrepresentable_environment_values_are_refused(tmp_path, value):
    stack = Stack(tmp_path, [sleeper("x", environment={"T_BAD": value})])
    with pytest.raises(ValueError):
        stack.render()


def test_newline_in_command_is_refused(tmp_path):
    program = Program(name="x", command=[sys.executable, "-c", "import os\nos.getpid()"])
    with pytest.raises(ValueError, match="newline"):
        Stack(tmp_path, [program]).render()


def test_attach_from_another_object_and_detached_start(tmp_path):
    run_dir = tmp_path / "run"
    owner = Stack(run_dir, [sleeper("alpha"), sleeper("beta")])
    owner.start(detach=True)
    try:
        other = Stack.attach(run_dir)
        assert other.status() == {"alpha": "RUNNING", "beta": "RUNNING"}
        pids = [other.pid("alpha"), other.pid("beta"), other.supervisord_pid]
        assert pids[2] == owner.supervisord_pid
        with pytest.raises(StackError):
            other.start()
        other.stop()
        assert_all_gone(pids)
        with pytest.raises(StackError):
            Stack.attach(run_dir)
    finally:
        owner.stop()


def test_start_failure_reports_log_tail_and_cleans_up(tmp_path):
    failing = Program(
        name="broken",
        command=[sys.executable, "-c", "import sys; sys.exit('boom: missing config xyz')"],
        startsecs=1,
    )
    stack = Stack(tmp_path / "run", [sleeper("fine"), failing])
    with pytest.raises(StackError) as excinfo:
        stack.start()
    message = str(excinfo.value)
    assert "broken" in message
    assert "boom: missing config xyz" in message
    assert stack.supervisord_pid is None
    assert not (tmp_path / "run" / "supervisor.sock").exists()


def test_second_start_on_same_run_dir_is_refused(tmp_path):
    with Stack(tmp_path / "run", [sleeper("alpha")]):
        with pytest.raises(StackError, match="already serves"):
            Stack(tmp_path / "run", [sleeper("alpha")]).start()


HOLDER = textwrap.dedent(
    """
    import json, signal, sys
    from pathlib import Path
    from teleop.run.supervise import Program, Stack
    SLEEPER = {sleeper!r}
    programs = [
        Program(name=n, command=[sys.executable, "-c", SLEEPER], startsecs=0) for n in ("a", "b")
    ]
    with Stack(Path(sys.argv[1]), programs) as stack:
        pids = [stack.pid("a"), stack.pid("b"), stack.supervisord_pid]
        print(json.dumps(pids), flush=True)
        while True:
            signal.pause()
    """
)


def start_holder(run_dir: Path) -> tuple[subprocess.Popen, list[int]]:
    """A separate process holding a running stack; returns it and the stack's pids."""
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLDER.format(sleeper=SLEEPER), str(run_dir)],
        stdout=subprocess.PIPE,
        env=env,
    )
    ready, _, _ = select.select([proc.stdout], [], [], WAIT_TIMEOUT_S)
    assert ready, "holder did not report its stack"
    pids = json.loads(proc.stdout.readline())
    assert all(alive(p) for p in pids)
    return proc, pids


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL])
def test_holder_signal_leaves_no_process(tmp_path, signum):
    proc, pids = start_holder(tmp_path / "run")
    try:
        proc.send_signal(signum)
        proc.wait(timeout=WAIT_TIMEOUT_S)
        if signum == signal.SIGKILL:
            # No unwinding: supervisord gets SIGTERM from the kernel (parent death signal).
            wait_for(lambda: not any(alive(p) for p in pids), "the orphaned stack to stop")
        assert_all_gone(pids)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        proc.stdout.close()


# Deaf to the stop signals of the first second after the first one (supervisord's and the
# stack's own at once: they stand for those lost at a program's start, landing between
# supervisord's fork and exec in the child's copy of supervisord's own handler, when the
# stop comes a few ms after the spawn); a later SIGINT ends it with status 0.
DEAF_AT_FIRST = (
    "import signal, sys, time; first = []; "
    "signal.signal(signal.SIGINT, lambda *a: sys.exit(0) if first and time.monotonic() "
    "- first[0] > 1.0 else first.append(first[0] if first else time.monotonic())); "
    "open(sys.argv[1], 'w').close(); "
    "[signal.pause() for _ in iter(int, 1)]"
)


def test_a_program_that_lost_its_stop_signal_is_signalled_again(tmp_path):
    """Stopping, the stack sends SIGINT again to a program still there after RESIGNAL_S:
    it ends by its own handler (exit status 0) well before supervisord's SIGKILL."""
    ready = tmp_path / "ready"
    program = Program(
        name="deaf", command=[sys.executable, "-c", DEAF_AT_FIRST, str(ready)], startsecs=0
    )
    with Stack(tmp_path / "run", [program]):
        wait_for(ready.exists, "the program's handler")
        started = time.monotonic()
    stopped_s = time.monotonic() - started
    log = (tmp_path / "run" / "supervisord.log").read_text()
    assert "stopped: deaf (exit status 0)" in log, log
    assert "SIGKILL" not in log and stopped_s < STOP_WAIT_S
