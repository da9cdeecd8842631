"""The teleop command as a user runs it: a real subprocess, a real summary file."""

from __future__ import annotations

import json
import subprocess
import sys

SUMMARY_KEYS = {
    "scenario",
    "duration_s",
    "path_error_rms_m",
    "path_error_max_m",
    "settle_s",
    "min_manipulability",
    "compensation",
    "steps",
    "wall_s",
    "final_state_sha256",
}


def teleop(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "teleop.cli", *args],
        capture_output=True,
        text=True,
        timeout=120,
        stdin=subprocess.DEVNULL,
    )


def test_inprocess_run_writes_the_summary(tmp_path):
    out = tmp_path / "out.json"
    result = teleop(
        "run", "path-following", "--inprocess", "--duration", "3", "--seed", "1",
        "--set", "run.settle_s=1", "--summary-json", str(out),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    summary = json.loads(out.read_text())
    assert SUMMARY_KEYS <= summary.keys()
    assert summary["steps"] == 3000 and summary["compensation"] is True
    assert json.loads(result.stdout) == summary
    assert "100%" in result.stderr  # progress is shown


def test_bad_override_exits_2_with_the_key_named():
    result = teleop("run", "path-following", "--inprocess", "--set", "control.gain=1")
    assert result.returncode == 2
    assert "control: unknown key(s) gain" in result.stderr
