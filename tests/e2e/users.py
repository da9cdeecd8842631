"""Runs as an ordinary user (``nobody``) from root's test run.

Root's CI switches to ``nobody`` with ``runuser``: no CAP_SYS_NICE (SCHED_FIFO refused),
no CAP_IPC_LOCK (shared memory bound by the default locked-memory limit), no write access
to the CPU cgroups (idle polling refused).

``nobody`` must be able to run a Python with the project's packages. The project's own
interpreter may live where ``nobody`` cannot read (a pyenv under /root): then a thin venv
is built on a system Python of the same version whose site-packages points at the
project's (compiled extensions are per minor version).
"""

from __future__ import annotations

import os
import pwd
import shutil
import site
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

USER = "nobody"
# A run that neither finishes nor fails within this long is a hang (s): far above the
# runs' own time-outs, only here so that a hung test ends.
HANG_S = 600


class UserUnavailable(Exception):
    """Why this machine cannot run a test as ``nobody`` (the message is the reason)."""


@dataclass(frozen=True)
class UserEnv:
    """A Python ``nobody`` can run with the project importable, and a home it owns."""

    python: Path
    home: Path

    def argv(self, args: Sequence[str]) -> list[str]:
        """``python ARGS`` as ``nobody``, with a plain user's environment."""
        env = {
            "HOME": str(self.home),
            "PATH": "/usr/bin:/bin",
            "RERUN_ANALYTICS": "0",
            "MUJOCO_GL": "egl",
        }
        return ["runuser", "-u", USER, "--", "env", *(f"{k}={v}" for k, v in env.items()),
                str(self.python), *args]  # fmt: skip

    def run(self, args: Sequence[str]) -> subprocess.CompletedProcess[str]:
        """``python ARGS`` as ``nobody`` in its home, to the end; its output captured."""
        return subprocess.run(
            self.argv(args), capture_output=True, text=True, timeout=HANG_S, cwd=self.home
        )


def _user_can_run(python: str) -> bool:
    version = f"{sys.version_info.major}.{sys.version_info.minor}"
    check = "import sys; print('%d.%d' % sys.version_info[:2])"
    try:
        result = subprocess.run(
            ["runuser", "-u", USER, "--", python, "-c", check],
            capture_output=True, text=True, timeout=HANG_S, cwd="/",
        )  # fmt: skip
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
        raise UserUnavailable(
            f"{USER} cannot run {sys.executable} and there is no system python{version}"
        )
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


@contextmanager
def ordinary_user() -> Iterator[UserEnv]:
    """A :class:`UserEnv` for ``nobody``, removed afterwards; raises
    :class:`UserUnavailable` where this process cannot switch to it."""
    if os.geteuid() != 0:
        raise UserUnavailable("needs root, to switch to an ordinary user with runuser")
    if shutil.which("runuser") is None:
        raise UserUnavailable("no runuser on this machine")
    try:
        user = pwd.getpwnam(USER)
    except KeyError:
        raise UserUnavailable(f"no user {USER!r} on this machine") from None
    # Not under pytest's tmp_path: its base directory is private to root.
    tmp = Path(tempfile.mkdtemp(prefix="teleop-unprivileged-"))
    try:
        tmp.chmod(0o755)
        python = _python_for_user(tmp)
        home = tmp / "home"
        home.mkdir()
        os.chown(home, user.pw_uid, user.pw_gid)
        yield UserEnv(python, home)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
