"""Grasp scenes the scripted operator must read before it moves, on the whole stack.

- An obstacle right on the straight carry from the cube to the bin: an operator going
  straight would push against its repulsion (the device force at its peak, the fingers
  squeezing the cube); the operator goes over and never enters the influence zone.
- A cube out of the arm's reach: the operator says so at once, with an OUT_OF_REACH
  event and a failure reason, instead of pushing until the phase times out.
"""

from __future__ import annotations

import pytest

from teleop.core.config import load_config
from teleop.viz import entities as ent
from teleop.viz.rrd import read_rrd
from tests.e2e.test_grasp import grasps

# On the straight move from over the default cube (0.45, -0.25) to over the default bin
# (0.35, 0.35) at carry height.
IN_THE_WAY = ("--set", "scene.obstacle_p_m=[[0.40, 0.05, 0.19]]",
              "--set", "scene.obstacle_radius_m=[0.05]")  # fmt: skip
IN_THE_WAY_RADIUS_M = 0.05
# A device force the operator never needs to hold against on a clear route (N): the
# cube's weight through the force scale is about 1 N.
CLEAR_ROUTE_FORCE_N = 3.0
# Beyond the arm's reach (about 0.9 m with the tool pointing down).
OUT_OF_REACH = ("--set", "scene.cube_p_m=[1.0, 0.0, 0.025]")


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict]:
    """Both scenes' lockstep grasps, run at once (the summaries by name)."""
    lockstep = ("--mode", "lockstep", "--seed", "0")
    scenes = {"way": (*lockstep, *IN_THE_WAY), "far": (*lockstep, *OUT_OF_REACH)}
    return grasps(tmp_path_factory.mktemp("routing"), scenes)


def test_the_operator_carries_over_an_obstacle_in_the_way(runs: dict[str, dict]) -> None:
    summary = runs["way"]
    assert summary["success"], summary.get("operator_failure")
    influence_m = load_config().teleop.obstacle_influence_m
    assert summary["obstacle_min_clearance_m"] > influence_m  # never felt its repulsion
    assert summary["max_device_force_n"] < CLEAR_ROUTE_FORCE_N
    assert summary["max_obstacle_force_n"] == 0.0
    routes = summary["services"]["operator"]["routes"]
    assert "carry" in [r["phase"] for r in routes]


def test_a_cube_out_of_reach_is_reported_not_timed_out(runs: dict[str, dict]) -> None:
    summary = runs["far"]
    assert not summary["success"]
    assert "out of reach in approach" in summary["operator_failure"]
    approach_timeout_s = 15.0  # deploy/scenarios/grasp.toml
    assert summary["duration_s"] < approach_timeout_s
    events = read_rrd(summary["rrd"])[ent.ENTITY_EVENTS]["TextLog:text"]
    assert any("OUT_OF_REACH" in text[0] for text in events)
