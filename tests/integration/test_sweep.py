"""A tiny ``teleop sweep`` (two paths, two worker processes) through the command line:
the report files, one record per task, their command lines and the totals."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from teleop.core.config import REPO_ROOT
from teleop.run import sweep

# Short runs: settle 2 s, then the generator's minimum measured time.
OVERRIDES = ("--set", "run.settle_s=2.0")


def test_a_two_path_sweep_writes_its_table_and_json(tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    result = subprocess.run(
        [sys.executable, "-m", "teleop.cli", "sweep", "path-following", "--paths", "2",
         "--seed", "3", "--workers", "2", "--out", str(out), *OVERRIDES],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    report = json.loads((out / sweep.REPORT_JSON).read_text())
    assert report["kind"] == "path-following"
    assert report["tasks"] == 2 and report["workers"] == 2
    assert [r["index"] for r in report["results"]] == [0, 1]
    for record in report["results"]:
        assert record["command"].startswith("teleop run path-following --inprocess")
        assert "path.center_m" in record["command"]
        assert "run.settle_s=2.0" in record["command"]  # the sweep's own --set too
        assert record["figures"]["path_error_rms_m"] is not None
        names = {c["name"] for c in record["criteria"]}
        assert names == {"path error RMS", "path error max", "path progress",
                         "no unintended contact", "commands applied"}  # fmt: skip
        # Never a silent failure: a task that did not succeed says why.
        assert record["success"] or record["reasons"]
    assert report["silent_failures"] == 0
    assert report["successes"] == sum(r["success"] for r in report["results"])
    # Exit code: 0 only when every task succeeded.
    assert result.returncode == (0 if report["successes"] == 2 else 1), result.stderr
    # Progress on stderr: one line per finished task.
    assert result.stderr.count("/2] task") == 2
    table = (out / sweep.REPORT_MARKDOWN).read_text()
    assert "| task |" in table
    assert table.count("teleop run path-following --inprocess") == 2
    # The same seed lists the same tasks.
    listed = subprocess.run(
        [sys.executable, "-m", "teleop.cli", "sweep", "path-following", "--paths", "2",
         "--seed", "3", "--list", *OVERRIDES],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=120, check=True,
    )  # fmt: skip
    assert listed.stdout.splitlines() == [r["command"] for r in report["results"]]
