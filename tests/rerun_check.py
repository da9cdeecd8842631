"""Rerun's own check of a recording's files, for the tests that write one."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from teleop.core.rundir import segment_paths


def rerun_verify_problems(recording: Path) -> list[str]:
    """What `rerun rrd verify` (footers included) says against each segment of the
    recording whose first segment is ``recording``; empty: every one passes."""
    rerun = Path(sys.executable).with_name("rerun")
    problems = []
    paths = segment_paths(Path(recording))
    if not paths:
        return [f"no recording at {recording}"]
    for path in paths:
        done = subprocess.run(
            [str(rerun), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120
        )
        if done.returncode != 0:
            problems.append(f"{path}: {(done.stdout + done.stderr).strip()}")
    return problems
