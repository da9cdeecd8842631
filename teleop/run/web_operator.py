"""The launcher's side of a person at a web page (``teleop run grasp --operator web``).

The page (services/web.py) is served on 127.0.0.1 only, on a port the launcher takes
from the run's :class:`~teleop.core.net.LoopbackPorts` (held until the run ends, so no
other program binds it meanwhile), and every request must carry the run's token: a
fresh ``secrets.token_urlsafe`` written to a 0600 file in ``<run_dir>/auth`` (a 0700
directory). Loopback alone is not enough: any user of the machine can connect to a
loopback port; the token is what keeps them out.

The token never goes on a command line (``/proc/<pid>/cmdline`` is readable by every
user): the service is given the file's path (``web.token_file``) and the port
(``web.port``) as ``--set`` overrides, and the person is given the URL with the token,
printed by the launcher on its own terminal once the stack is up.
"""

from __future__ import annotations

import os
import secrets
from dataclasses import dataclass, field
from pathlib import Path

from teleop.bus.access import write_private
from teleop.core.config import Config
from teleop.core.net import LOOPBACK, LoopbackPorts
from teleop.core.rundir import AUTH_DIR

# The run.operator value of the web page.
WEB = "web"
# The token's file in <run_dir>/auth.
TOKEN_FILE = "web-operator.token"
# Random bytes of the token (secrets.token_urlsafe: 43 URL-safe characters for 32).
TOKEN_BYTES = 32


@dataclass(frozen=True)
class WebAccess:
    """Where the run's page is served and how it is opened: the port, the token's file,
    and the token itself (kept out of ``repr``, so no log or traceback shows it)."""

    port: int
    token_file: Path
    token: str = field(repr=False)

    @property
    def url(self) -> str:
        """The page's address with the token, for the person (never for a command line)."""
        return f"http://{LOOPBACK}:{self.port}/?token={self.token}"

    def overrides(self) -> list[str]:
        """The service's ``--set`` overrides: the port and the token's file, not the token."""
        return [f"web.port={self.port}", f'web.token_file="{self.token_file}"']

    def announcement(self) -> str:
        """What the launcher prints once the stack is up (see docs/operators.md)."""
        return (
            f"web operator: open {self.url} in a browser on this machine (over SSH: "
            f"ssh -L {self.port}:{LOOPBACK}:{self.port} HOST, then the same URL); the token "
            "in it is this run's, keep it to yourself"
        )


def write_token(run_dir: Path) -> tuple[Path, str]:
    """A fresh token in ``<run_dir>/auth/web-operator.token`` (the directory 0700, the
    file 0600 from its creation on); the file's path and the token."""
    directory = Path(run_dir).absolute() / AUTH_DIR
    directory.mkdir(parents=True, exist_ok=True)
    os.chmod(directory, 0o700)
    token = secrets.token_urlsafe(TOKEN_BYTES)
    path = directory / TOKEN_FILE
    write_private(path, token + "\n")
    return path, token


def prepare_web_operator(config: Config, run_dir: Path, ports: LoopbackPorts) -> WebAccess | None:
    """For a run driven from the web page (``run.operator == "web"``): a port taken from
    ``ports`` and a fresh token on file; None for any other operator."""
    if config.run.operator != WEB:
        return None
    port = ports.take()
    path, token = write_token(run_dir)
    return WebAccess(port, path, token)


def web_overrides(access: WebAccess | None) -> list[str]:
    """The overrides a run adds for its web page (none without one)."""
    return [] if access is None else access.overrides()
