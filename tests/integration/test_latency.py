"""`teleop latency` and the loop-stage benchmark as processes (no stack): the command line
refuses what it cannot measure, the cold replay runs the real services' callbacks."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from teleop.bench import loop_stats


def test_cli_refuses_a_run_shorter_than_the_warmup():
    result = subprocess.run(
        [sys.executable, "-m", "teleop.cli", "latency", "--duration", "0.5"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and "warm-up" in result.stderr


def test_loop_stage_cost_benchmark_replays_every_stage(tmp_path):
    """The cold-cache replay of the loop's stages (tests/benchmarks/loop_stage_cost.py)
    runs the real services' callbacks end to end: every stage gets a time, warm and cold."""
    out = tmp_path / "loop_stage_cost.json"
    script = Path(__file__).parents[1] / "benchmarks" / "loop_stage_cost.py"
    args = [sys.executable, str(script), "--periods", "20", "--rounds", "1", "--json", str(out)]
    subprocess.run(args, check=True, timeout=120, stdin=subprocess.DEVNULL, capture_output=True)
    stages = json.loads(out.read_text())["stages_us"]
    expected = [hop.name for hop in loop_stats.HOPS if hop.kind in ("compute", "wait")]
    assert sorted(stages) == sorted(expected)
    for figures in stages.values():
        assert figures["warm"] > 0 and figures["cold"] > 0
