"""Runs as an ordinary user: a lockstep stack and a short realtime run as ``nobody``.

Root's CI switches to ``nobody`` with ``runuser``: no CAP_SYS_NICE (SCHED_FIFO refused),
no CAP_IPC_LOCK (shared memory bound by the default locked-memory limit), no write access
to the CPU cgroups (idle polling refused). The run must still succeed and say in its
summary's ``machine`` section what it was refused, and the eye view's frames must still
arrive over shared memory (a pool sized within the limit).

``nobody`` must be able to run a Python with the project's packages. The project's own
interpreter may live where ``nobody`` cannot read (a pyenv under /root): then the test
builds a thin venv on a system Python of the same version whose site-packages points
at the project's (compiled extensions are per minor version).
"""

from __future__ import annotations

import json
import os
import pwd
import shutil
import site
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
USER = "nobody"
# Exit codes of `teleop run` that mean the run completed: 0, or 3 when it lost real
# time (a verdict on the machine's load, judged apart below).
EXIT_OK, EXIT_REALTIME_LOST = 0, 3
# A run that neither finishes nor fails within this long is a hang (s): far above the
# runs' own time-outs, only here so that a hung test ends.
HANG_S = 600


def _as_user(argv: list[str], **kwargs: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["runuser", "-u", USER, "--", *argv],
        capture_output=True,
        text=True,
        timeout=HANG_S,
        **kwargs,  # type: ignore[arg-type]
    )


def _user_can_run(python: str) -> bool:
    version = f"{sys.version_info.major}.{sys.version_info.minor}"
    check = "import sys; print('%d.%d' % sys.version_info[:2])"
    try:
        result = _as_user([python, "-c", check], cwd="/")
    except (OSError, subprocess.TimeoutExpired):
        return False
    return result.returncode == 0 and result.stdout.strip() == version


def _python_for_user(tmp: Path) -> Path:
    """A Python ``nobody`` can run with the project importable (see the module doc)."""
    if _user_can_run(sys.executable):
        return Path(sys.executable)
    version = f"{sys.version_info.major}.{sys.version_info.minor}"
    bases = [f"/usr/bin/python{version}", f"/usr/local/bin/python{version}"]
    base = next((b for b in bases if Path(b).exists() and _user_can_run(b)), None)
    if base is None:
        pytest.skip(f"{USER} cannot run {sys.executable} and there is no system python{version}")
    venv = tmp / "venv"
    subprocess.run([base, "-m", "venv", "--without-pip", str(venv)], check=True)
    where = "import sysconfig; print(sysconfig.get_path('purelib'))"
    purelib = Path(
        subprocess.check_output([str(venv / "bin" / "python"), "-c", where], text=True).strip()
    )
    # addsitedir (not a bare path) so the project's own .pth files run: its editable
    # install and cmeel's (Pinocchio's) path set-up.
    lines = [f"import site; site.addsitedir({p!r})" for p in site.getsitepackages()]
    (purelib / "project.pth").write_text("\n".join(lines) + "\n")
    # The stack starts supervisord from the interpreter's own bin directory.
    supervisord = venv / "bin" / "supervisord"
    supervisord.write_text(
        f"#!{venv / 'bin' / 'python'}\nimport sys\nfrom supervisor.supervisord import main\n"
        "sys.exit(main())\n"
    )
    supervisord.chmod(0o755)
    return venv / "bin" / "python"


@pytest.fixture(scope="module")
def user_env() -> Iterator[tuple[Path, Path]]:
    """(the Python to run, a home directory owned by the user)."""
    if os.geteuid() != 0:
        pytest.skip("needs root, to switch to an ordinary user with runuser")
    if shutil.which("runuser") is None:
        pytest.skip("no runuser on this machine")
    try:
        user = pwd.getpwnam(USER)
    except KeyError:
        pytest.skip(f"no user {USER!r} on this machine")
    # Not under pytest's tmp_path: its base directory is private to root.
    tmp = Path(tempfile.mkdtemp(prefix="teleop-unprivileged-"))
    try:
        tmp.chmod(0o755)
        python = _python_for_user(tmp)
        home = tmp / "home"
        home.mkdir()
        os.chown(home, user.pw_uid, user.pw_gid)
        yield python, home
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _run_as_user(user_env: tuple[Path, Path], name: str, args: list[str]) -> tuple[int, dict]:
    python, home = user_env
    run_dir = home / name
    summary = home / f"{name}.json"
    env = {
        "HOME": str(home),
        "PATH": "/usr/bin:/bin",
        "RERUN_ANALYTICS": "0",
        "MUJOCO_GL": "egl",
    }
    command = [python, "-m", "teleop.cli", "run", *args, "--quiet"]
    command += ["--run-dir", str(run_dir), "--summary-json", str(summary)]
    result = _as_user(["env", *(f"{k}={v}" for k, v in env.items()), *map(str, command)], cwd=home)
    assert result.returncode in (EXIT_OK, EXIT_REALTIME_LOST), result.stderr[-3000:]
    return result.returncode, json.loads(summary.read_text())


def _refused_as_an_ordinary_user(machine: dict) -> None:
    assert machine["user"] == USER and machine["uid"] != 0
    # No CAP_SYS_NICE: every loop service that asked for SCHED_FIFO was refused.
    assert machine["sched_fifo"]["granted"] == {}


def test_a_lockstep_stack_runs_as_an_ordinary_user(user_env):
    code, summary = _run_as_user(
        user_env, "lockstep", ["grasp", "--mode", "lockstep", "--seed", "0"]
    )
    assert code == EXIT_OK
    assert summary["success"] is True
    assert summary["machine"]["user"] == USER


def test_a_realtime_run_as_an_ordinary_user_reports_what_it_was_refused(user_env):
    code, summary = _run_as_user(
        user_env, "realtime", ["path-following", "--mode", "realtime", "--duration", "4"]
    )
    assert (code == EXIT_REALTIME_LOST) == (summary["realtime_verdict"] == "lost")
    machine = summary["machine"]
    _refused_as_an_ordinary_user(machine)
    assert set(machine["sched_fifo"]["refused"]) >= {"plant", "controller"}
    # The eye view's pool fits the default locked-memory limit, and its frames arrive
    # through it (before, the pool was refused and the eye view never came alive).
    pool = machine["shm"]
    if pool["memlock_bound"] and pool["memlock_limit_bytes"] is not None:
        assert pool["pool_bytes"] < pool["memlock_limit_bytes"]
    eye = summary["eye_view"]
    assert eye["frames_received"] > 0
    assert eye["frames_received_shm"] == eye["frames_received"]
