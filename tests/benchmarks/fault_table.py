"""Benchmark: every service killed, and frozen, mid-grasp in realtime; one table.

One `teleop run grasp --mode realtime` per (service, fault), the fault injected by the
run itself (`--kill SERVICE@T`, `--freeze SERVICE@T:SECONDS`, teleop.run.faults) while
the cube is held, plus one run without a fault for reference. Each row: what the
summary's ``faults`` measured (brake ms, restart s, resumed s, all from the instant of
injection) and the task's outcome; a run that failed gives its one-line reason.
Writes JSON and a markdown table (docs/faults.md quotes it).

    .venv/bin/python tests/benchmarks/fault_table.py --json runs/faults.json \
        --markdown runs/faults.md
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from teleop.core import markdown

SERVICES = ("plant", "controller", "haptic", "hmd", "operator", "recorder", "eyeview")
KINDS = ("kill", "freeze")
# Sim time of the fault (s): the realtime grasp with seed 0 closes the gripper at about
# 9 s, lifts the cube until about 13 s, carries it and releases it at about 18.5 s, so
# 12 s is mid-grasp, the cube in the air.
DEFAULT_AT_S = 12.0
DEFAULT_FREEZE_S = 1.0
# One run's bound (s): start-up, the task (about 31 s) and the stop, on a loaded machine.
RUN_TIMEOUT_S = 600


def fault_run(args: list[str], run_dir: Path) -> dict:
    """One `teleop run grasp` with ``args``; what the table needs from it."""
    out = run_dir / "summary.json"
    started = time.monotonic()
    result = subprocess.run(
        [sys.executable, "-m", "teleop.cli", "run", "grasp", "--mode", "realtime",
         "--run-dir", str(run_dir), "--summary-json", str(out), "--quiet", *args],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL,
        timeout=RUN_TIMEOUT_S,
    )  # fmt: skip
    row: dict = {"exit_code": result.returncode, "wall_s": round(time.monotonic() - started, 1)}
    if not out.exists():
        reason = [line for line in result.stderr.splitlines() if line.startswith("teleop:")]
        row.update(success=False, error=(reason or result.stderr.splitlines()[-1:] or ["?"])[0])
        return row
    summary = json.loads(out.read_text())
    row.update(
        success=summary.get("success"),
        task_s=summary.get("duration_s"),
        realtime_verdict=summary.get("realtime_verdict"),
        realtime_problems=summary.get("realtime_problems"),
        faults=summary.get("faults"),
    )
    return row


def _cell(value: object, fmt: str) -> str:
    return "–" if value is None else f"{value:{fmt}}"


def rows_markdown(rows: list[dict]) -> str:
    cells = []
    for row in rows:
        fault = (row.get("faults") or [{}])[0]
        if row.get("error"):
            outcome = f"failed: {row['error'].removeprefix('teleop: ')}"
        elif row.get("success"):
            outcome = f"success ({row['task_s']:.1f} s)"
        else:
            outcome = "failed (task not done)"
        cells.append((row["service"], row["kind"], _cell(fault.get("t_s"), ".2f"),
                      _cell(fault.get("brake_ms"), ".1f"), _cell(fault.get("restart_s"), ".2f"),
                      _cell(fault.get("resumed_s"), ".2f"), outcome))  # fmt: skip
    header = ("service", "fault", "at (sim s)", "brake ms", "restart s", "resumed s", "task")
    return "\n".join(markdown.table(header, cells, "llrrrrl")) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--services", default=",".join(SERVICES))
    parser.add_argument("--kinds", default=",".join(KINDS))
    parser.add_argument("--at", type=float, default=DEFAULT_AT_S, help="sim s of the fault")
    parser.add_argument("--freeze-s", type=float, default=DEFAULT_FREEZE_S)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-reference", action="store_true", help="skip the fault-free run")
    parser.add_argument("--json", type=Path, required=True)
    parser.add_argument("--markdown", type=Path)
    parser.add_argument("--run-root", type=Path, help="run directories (default: a temp dir)")
    args = parser.parse_args()
    root = args.run_root or Path(tempfile.mkdtemp(prefix="faults-"))
    plan = [] if args.no_reference else [("none", "none", [])]
    for service in args.services.split(","):
        for kind in args.kinds.split(","):
            spec = f"{service}@{args.at:g}" + (f":{args.freeze_s:g}" if kind == "freeze" else "")
            plan.append((service, kind, [f"--{kind}", spec]))
    rows = []
    for service, kind, extra in plan:
        run_dir = root / f"{service}-{kind}"
        row = {"service": service, "kind": kind, **fault_run(
            ["--seed", str(args.seed), *extra], run_dir)}  # fmt: skip
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
        report = {"at_s": args.at, "freeze_s": args.freeze_s, "seed": args.seed, "rows": rows}
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")
        if args.markdown is not None:
            args.markdown.write_text(rows_markdown(rows))
    print(rows_markdown(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
