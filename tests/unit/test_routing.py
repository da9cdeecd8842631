"""The operator's route planning: over or around what it sees, from the scene file."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from teleop.core.config import load_config
from teleop.devices.scripted import routing
from teleop.devices.scripted.routing import KeepOut, SceneKnowledge, plan_route


def _clear(start, waypoints, target, volumes) -> bool:
    points = [np.asarray(start), *waypoints, np.asarray(target)]
    return not any(v.meets(a, b) for a, b in itertools.pairwise(points) for v in volumes)


def test_a_clear_move_needs_no_waypoint():
    ball = KeepOut.sphere("ball", np.array([0.4, 0.3, 0.2]), 0.1)
    assert plan_route(np.array([0.4, -0.2, 0.2]), np.array([0.4, -0.2, 0.4]), [ball]) == []


def test_over_a_sphere_in_the_way():
    ball = KeepOut.sphere("ball", np.array([0.4, 0.0, 0.2]), 0.15)
    start, target = np.array([0.4, -0.3, 0.2]), np.array([0.4, 0.3, 0.2])
    route = plan_route(start, target, [ball])
    assert len(route) == 2
    assert all(w[2] >= ball.top_m for w in route)
    assert _clear(start, route, target, [ball])
    assert routing.route_length_m(start, route, target) > np.linalg.norm(target - start)


def test_around_a_sphere_too_high_to_pass_over():
    centre = np.array([0.5, 0.0, routing.MAX_ROUTE_HEIGHT_M - 0.05])
    ball = KeepOut.sphere("ball", centre, 0.1)
    start = np.array([0.5, -0.3, centre[2]])
    target = np.array([0.5, 0.3, centre[2]])
    route = plan_route(start, target, [ball])
    assert len(route) == 1
    assert _clear(start, route, target, [ball])
    assert abs(route[0][0]) < centre[0]  # on the side of the base axis


def test_over_the_bin_walls_and_into_the_bin():
    knowledge = SceneKnowledge.from_config(load_config())
    bin_p = np.array([0.35, 0.35, 0.0])
    walls = knowledge.keep_outs(bin_p, holding=False)
    (bin_box,) = [v for v in walls if v.name == "bin"]
    # Low across the bin: over its walls.
    start, target = np.array([0.35, 0.15, 0.06]), np.array([0.35, 0.56, 0.06])
    route = plan_route(start, target, [bin_box])
    assert route and all(w[2] >= bin_box.top_m for w in route)
    # Into the bin (the task puts the tool there): straight.
    assert plan_route(np.array([0.35, 0.0, 0.2]), bin_p + [0, 0, 0.05], [bin_box]) == []
    # A held cube hangs below the tool: the box grows upward by its height.
    (held,) = [v for v in knowledge.keep_outs(bin_p, holding=True) if v.name == "bin"]
    assert held.top_m == pytest.approx(bin_box.top_m + 2 * routing.HELD_HALF_HEIGHT_M)


def test_scene_knowledge_reads_the_placed_obstacles():
    config = load_config(
        None, ["scene.obstacle_p_m=[[0.4, 0.05, 0.19]]", "scene.obstacle_radius_m=[0.05]"]
    )
    knowledge = SceneKnowledge.from_config(config)
    assert knowledge.obstacles == ((pytest.approx((0.4, 0.05, 0.19)), pytest.approx(0.05)),)
    assert knowledge.influence_m == config.teleop.obstacle_influence_m
    (ball,) = [v for v in knowledge.keep_outs(None, holding=False)]
    assert ball.radius_m == pytest.approx(0.05 + knowledge.influence_m + routing.TOOL_CLEARANCE_M)
