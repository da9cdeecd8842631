"""Start a restarted service's process below the control path, from its first instruction.

``python -m teleop.run.niced --nice N --run-dir DIR --service NAME -- COMMAND...`` replaces
itself with ``COMMAND`` (``os.execv``: the same pid, which supervisord watches), at
niceness ``N`` when ``NAME`` already ran in this run (its summary, or a running summary
of a process of it, is in ``DIR``), unchanged otherwise.

Why: a restarted recorder or eye view spends seconds importing and loading before its
own code could lower its priority, and at the normal priority that takes the CPU the
operator and the HMD need while the control loop runs. Its first start is left alone:
no loop runs yet (the plant waits for every service), and niced it would only start
late on a busy machine. Once running, the services lower themselves to their ``nice``
anyway (teleop.bus.service.lower_priority_to). Kept to the standard library and
teleop.core.rundir: it runs before every start of those services.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

from teleop.core.rundir import incarnation_paths, summary_path


def ran_before(run_dir: Path, service: str) -> bool:
    """Whether a process of ``service`` already ran in this run (this start is a restart)."""
    return summary_path(run_dir, service).exists() or bool(incarnation_paths(run_dir, service))


def command(nice: int, run_dir: Path, service: str, argv: list[str]) -> list[str]:
    """``argv`` behind this module: how a launcher starts ``service`` so that its restarts
    run at ``nice`` from their first instruction."""
    return [
        sys.executable, "-m", __name__, "--nice", str(nice), "--run-dir", str(run_dir),
        "--service", service, "--", *argv,
    ]  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="teleop-niced", description=__doc__.splitlines()[0])
    parser.add_argument("--nice", type=int, required=True, help="niceness of a restart")
    parser.add_argument("--run-dir", type=Path, required=True)
    parser.add_argument("--service", required=True)
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command")
    args = parser.parse_args(argv)
    target = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not target:
        parser.error("no command after --")
    if args.nice > 0 and ran_before(args.run_dir, args.service):
        os.setpriority(os.PRIO_PROCESS, 0, max(args.nice, os.getpriority(os.PRIO_PROCESS, 0)))
    executable = shutil.which(target[0]) or target[0]
    os.execv(executable, target)
    return 0  # not reached: execv replaced this process


if __name__ == "__main__":
    sys.exit(main())
