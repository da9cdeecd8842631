"""Start a restarted service's process at a priority of its own, from its first instruction.

``python -m teleop.run.restart_priority --run-dir DIR --service NAME [--nice N | --fifo P]
-- COMMAND...`` replaces itself with ``COMMAND`` (``os.execv``: the same pid, which
supervisord watches). When ``NAME`` already ran in this run (its summary, or a running
summary of a process of it, is in ``DIR``: this start is a restart), it first lowers
itself to niceness ``N``, or takes ``SCHED_FIFO`` priority ``P``; a first start is left
as the launcher made it.

Why: a restart spends seconds importing and loading (numpy, Zenoh, MuJoCo, Pinocchio)
before its own code could choose its scheduling, beside a control loop that runs on.

- The recorder and the eye view (``--nice``): at the normal priority that would take
  the CPU the operator and the HMD need. Once running they lower themselves to their
  ``nice`` anyway (teleop.bus.service.lower_priority_to).
- The control path's services (``--fifo``, below the loops' own priority): on 2 cores the
  realtime loops leave a small share of the CPUs to everything else, and a normally
  scheduled restart shares it with whatever else runs on the host; the new operator or
  controller then takes tens of seconds to come back (in lockstep, past the plant's
  ``lockstep_timeout_s``). Once running they take their own scheduling (service_main).

A first start is left alone: no loop runs yet (the plant waits for every service), and
niced it would only start late on a busy machine. Kept to the standard library and
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


def command(
    run_dir: Path, service: str, argv: list[str], *, nice: int = 0, fifo: int = 0
) -> list[str]:
    """``argv`` behind this module: how a launcher starts ``service`` so that its restarts
    run at niceness ``nice``, or under SCHED_FIFO priority ``fifo``, from their first
    instruction."""
    priority = ["--fifo", str(fifo)] if fifo > 0 else ["--nice", str(nice)]
    return [
        sys.executable, "-m", __name__, *priority, "--run-dir", str(run_dir),
        "--service", service, "--", *argv,
    ]  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="teleop-restart-priority", description=__doc__.splitlines()[0]
    )
    how = parser.add_mutually_exclusive_group(required=True)
    how.add_argument("--nice", type=int, help="niceness of a restart")
    how.add_argument("--fifo", type=int, help="SCHED_FIFO priority of a restart")
    parser.add_argument("--run-dir", type=Path, required=True)
    parser.add_argument("--service", required=True)
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command")
    args = parser.parse_args(argv)
    target = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not target:
        parser.error("no command after --")
    if ran_before(args.run_dir, args.service):
        if args.fifo:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.fifo))
            except OSError as exc:  # no CAP_SYS_NICE: the restart runs normally scheduled
                print(f"restart priority: SCHED_FIFO {args.fifo} refused ({exc})", file=sys.stderr)
        elif args.nice:
            current = os.getpriority(os.PRIO_PROCESS, 0)
            os.setpriority(os.PRIO_PROCESS, 0, max(args.nice, current))
    os.execv(shutil.which(target[0]) or target[0], target)
    return 0  # not reached: execv replaced this process


if __name__ == "__main__":
    sys.exit(main())
