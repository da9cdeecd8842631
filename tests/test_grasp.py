"""Bilateral teleoperation end to end: every service under supervisord, a real bus.

The scripted operator acts only through the haptic handle; success means the cube
ends inside the bin. The 20-seed statistics are the benchmark's
(tests/benchmarks/grasp_success.py); these tests check one run of each kind.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from teleop.config import load_config
from teleop.feedback import STANDARD_GRAVITY_M_S2

# Tolerance on the held weight the operator feels, as a fraction of m g.
WEIGHT_TOLERANCE = 0.10
# An obstacle beside the carry path, below it: felt and avoided, never blocking.
OBSTACLE = ("scene.obstacle_p_m=[[0.42, 0.05, 0.12]]", "scene.obstacle_radius_m=[0.04]")


def grasp(tmp_path: Path, name: str, *args: str) -> dict:
    out = tmp_path / f"{name}.json"
    result = subprocess.run(
        [sys.executable, "-m", "teleop.cli", "run", "grasp", "--run-dir", str(tmp_path / name),
         "--summary-json", str(out), "--quiet", *args],
        capture_output=True, text=True, timeout=600, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    assert out.exists(), result.stderr[-3000:]
    summary = json.loads(out.read_text())
    assert result.returncode == (0 if summary["success"] else 1)
    return summary


def assert_physical(summary: dict) -> None:
    config = load_config()
    assert summary["max_device_force_n"] <= config.haptic.peak_force_n + 1e-9
    weight_n = config.teleop.object_mass_kg * STANDARD_GRAVITY_M_S2
    assert summary["held_weight_n"] == pytest.approx(weight_n, rel=WEIGHT_TOLERANCE)
    assert summary["tool_speed_max_m_s"] <= config.teleop.max_tool_speed_m_s * 1.01
    assert summary["dropped_messages"] == 0


def test_realtime_grasp_puts_the_cube_in_the_bin(tmp_path):
    summary = grasp(tmp_path, "rt", "--mode", "realtime", "--seed", "0")
    assert summary["success"] and summary["object_in_box"]
    assert [p["name"] for p in summary["phases"]][-1] == "retreat"
    assert_physical(summary)
    assert Path(summary["rrd"]).stat().st_size > 0


def test_lockstep_grasp_is_deterministic(tmp_path):
    first = grasp(tmp_path, "a", "--mode", "lockstep", "--seed", "4")
    second = grasp(tmp_path, "b", "--mode", "lockstep", "--seed", "4")
    assert first["success"] and second["success"]
    assert first["final_state_sha256"] == second["final_state_sha256"]
    assert first["duration_s"] == second["duration_s"]
    assert_physical(first)


def test_obstacle_is_felt_and_avoided(tmp_path):
    args = [item for override in OBSTACLE for item in ("--set", override)]
    summary = grasp(tmp_path, "obstacle", "--mode", "lockstep", "--seed", "2", *args)
    assert summary["success"]
    assert summary["obstacle_min_clearance_m"] > 0.0
    assert summary["max_obstacle_force_n"] > 0.0
