"""Clearance of the arm (teleop/control/clearance.py) and how path following keeps it.

The distances are checked against MuJoCo's own narrow phase called directly, the
approach rows against finite differences of those distances. The two in-process runs
reproduce the failure that motivated the avoidance (a reachable path on which the
unguarded law folds the arm into the table and into itself) and an unreachable path
that must be reported as a stall, not as a good run.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from teleop.control.clearance import (
    ClearanceModel,
    PairKind,
    allowed_approach_m_s,
    approach_row,
    push_depth_m,
)
from teleop.control.kinematics import build_arm_model, tool_position_and_jacobian
from teleop.control.path import ControlOutput, PathMetrics, hold_clearance
from teleop.core.config import load_config
from teleop.run.experiments import run_path_following_inprocess

# A reachable path that passes close to the shoulder singularity (tool near the base
# axis): the unguarded law swings the arm through it, into the table and through itself.
SWING_PATH = ["path.center_m=[0.35, 0.0, 0.3]", "path.radius_m=0.4"]
# The unguarded law's first contact on SWING_PATH comes at about 18.8 s.
SWING_RUN = ["run.duration_s=21", "run.settle_s=5", *SWING_PATH]
# A path behind and left of the base, 0.6 m from the home pose's tool: on the way in the
# tool is commanded past the plant's tool speed limit and the gripper swings at the
# shoulder (the velocity loops lag the held command); 3 s covers the way in.
FAST_WAY_IN_RUN = [
    "path.center_m=[-0.067, -0.439, 0.206]",
    "path.radius_m=0.143",
    "path.z_amplitude_m=0.047",
    "control.path_speed_m_s=0.105",
    "run.duration_s=3",
    "run.settle_s=2",
]
# A path mostly beyond the arm's reach (about 0.85 m): the tool must stall, and say so.
UNREACHABLE_PATH = ["path.center_m=[0.95, 0.0, 0.3]", "path.radius_m=0.3"]
# Distances agree with MuJoCo's to rounding (m); rows with finite differences (m/s).
DISTANCE_TOLERANCE_M = 1e-12
ROW_TOLERANCE_M_S = 1e-5
# Margins are held to within this (m): the cap acts on the next step's approach.
MARGIN_TOLERANCE_M = 1e-3
# From the home pose: the shoulder and elbow bent down, the gripper at the table.
LOWERED_RAD = np.array([0.0, 0.8, 0.3, 0.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def model() -> ClearanceModel:
    config = load_config()
    return ClearanceModel(config, build_arm_model(config.robot))


def _home(model: ClearanceModel) -> np.ndarray:
    return np.array(load_config().robot.home_q_rad)


def test_pairs_are_mujocos_distances_and_adjacent_links_are_left_out(model):
    q = _home(model) + LOWERED_RAD
    clearance = model.measure(q, model.open_m)
    assert clearance.pairs, "a lowered arm has something within the influence distance"
    for pair in clearance.pairs:
        direct = mujoco.mj_geomDistance(
            model.model, model.data, pair.arm_geom, pair.other_geom, 1.0, None
        )
        assert abs(direct - pair.distance_m) < DISTANCE_TOLERANCE_M
        assert abs(np.linalg.norm(pair.world_n_away) - 1.0) < 1e-9
    names = {(model.geom_name(a), model.geom_name(b)) for a, b in model.self_pairs}
    assert ("upper_arm_geom", "forearm_geom") not in names  # adjacent: touch by design
    assert ("wrist_1_geom", "palm_geom") in names  # the wrist can fold onto itself
    scene = {model.geom_name(g) for g in model.scene_geoms}
    assert {"table", "bin_wall_px", "base_geom"} <= scene
    assert "cube_geom" not in scene and "obstacle_0" not in scene


def test_approach_rows_are_the_rate_of_change_of_the_distance(model):
    config = load_config()
    arm = build_arm_model(config.robot)
    q = _home(model) + LOWERED_RAD
    qd = np.random.default_rng(0).normal(0.0, 0.2, size=6)
    before = model.measure(q, model.open_m)
    tool_position_and_jacobian(arm, q)  # the joint Jacobians the rows read
    rows = {(p.arm_geom, p.other_geom): approach_row(arm, p) for p in before.pairs}
    dt = 1e-6
    after = {(p.arm_geom, p.other_geom): p for p in model.measure(q + qd * dt, model.open_m).pairs}
    kinds = set()
    for pair in before.pairs:
        key = (pair.arm_geom, pair.other_geom)
        if pair.distance_m <= 0:  # overlapping: the witness points are not unique
            continue
        rate = (after[key].distance_m - pair.distance_m) / dt
        assert abs(rows[key] @ qd - rate) < ROW_TOLERANCE_M_S
        kinds.add(pair.kind)
    assert PairKind.SCENE in kinds or PairKind.FINGER in kinds


def test_the_allowed_approach_speed_falls_to_zero_at_the_stop_distance():
    config = load_config().clearance
    stop, slow = config.stop_m, config.slowdown_m
    assert allowed_approach_m_s(config, PairKind.SCENE, slow) == config.approach_speed_m_s
    assert allowed_approach_m_s(config, PairKind.SCENE, stop) == 0.0
    # Inside the stop distance the pair must open, as fast as it may close at the
    # slowdown distance at most.
    inside = allowed_approach_m_s(config, PairKind.SCENE, stop - 0.1 * (slow - stop))
    assert inside == pytest.approx(-0.1 * config.approach_speed_m_s)
    assert allowed_approach_m_s(config, PairKind.SCENE, -0.5) == -config.approach_speed_m_s
    half = allowed_approach_m_s(config, PairKind.SCENE, 0.5 * (stop + slow))
    assert half == pytest.approx(0.5 * config.approach_speed_m_s)


def test_a_pair_closing_fast_is_capped_on_the_distance_it_will_have_a_lag_ahead():
    config = load_config().clearance
    stop, slow = config.self_stop_m, config.self_slowdown_m
    lookahead_s = config.approach_lookahead_s
    assert lookahead_s > 0
    closing_m_s = 0.2
    ahead_m = 0.5 * (stop + slow)
    now_m = ahead_m + lookahead_s * closing_m_s
    assert allowed_approach_m_s(config, PairKind.SELF, now_m, closing_m_s) == pytest.approx(
        allowed_approach_m_s(config, PairKind.SELF, ahead_m)
    )
    # Opening, or still: the distance now.
    assert allowed_approach_m_s(config, PairKind.SELF, now_m, -closing_m_s) == pytest.approx(
        allowed_approach_m_s(config, PairKind.SELF, now_m)
    )
    # Closing at the approach speed itself from one lag's travel beyond the stop: stop now.
    at_m = stop + lookahead_s * config.approach_speed_m_s
    stop_now = allowed_approach_m_s(config, PairKind.SELF, at_m, config.approach_speed_m_s)
    assert stop_now == pytest.approx(0.0, abs=1e-12)


def test_a_still_command_opens_a_pair_that_drifted_inside_its_stop_distance():
    config = load_config().clearance
    stop, slow = config.self_stop_m, config.self_slowdown_m
    cap = allowed_approach_m_s(config, PairKind.SELF, stop - 0.2 * (slow - stop))
    assert cap < 0
    row = np.array([0.0, 0.3, -0.2, 0.1, 0.0, 0.05])  # m/rad: d' = row . q'
    held, count = hold_clearance(np.zeros(6), [(cap, row)])
    assert count == 1
    opening_m_s = float(row @ held)  # the row's own damping leaves a few percent out
    assert -cap * 0.9 < opening_m_s <= -cap


def test_the_null_space_push_enters_without_a_step_and_is_linear_from_the_stop_distance():
    config = load_config().clearance
    stop, slow = config.stop_m, config.slowdown_m
    assert push_depth_m(config, PairKind.SCENE, slow + 0.01) == 0.0
    assert push_depth_m(config, PairKind.SCENE, slow) == 0.0
    # Zero slope at the slowdown distance: 1 um inside, the depth is ~1e-12 m, not 1e-6.
    assert push_depth_m(config, PairKind.SCENE, slow - 1e-6) < 1e-10
    assert push_depth_m(config, PairKind.SCENE, stop) == pytest.approx(slow - stop)
    assert push_depth_m(config, PairKind.SCENE, stop - 0.004) == pytest.approx(slow - stop + 0.004)


def test_a_fast_way_in_keeps_the_margins_and_is_not_a_stall():
    """The tool is 0.6 m from the path: the command is cut to the plant's tool speed
    limit, and the velocity reference keeps the caps (the compensation would otherwise
    carry the gripper on into the shoulder); the tool closing in is progress."""
    config = load_config(None, FAST_WAY_IN_RUN)
    summary = run_path_following_inprocess(config, progress=None)
    assert summary["arm_contacts"] == 0, summary["events"]
    assert summary["min_clearance_self_m"] >= config.clearance.self_stop_m - MARGIN_TOLERANCE_M
    assert summary["stalls"] == 0, summary["events"]


def test_unguarded_law_collides_where_the_guarded_one_keeps_its_margins():
    config = load_config(None, [*SWING_RUN, "clearance.avoid=false"])
    unguarded = run_path_following_inprocess(config, progress=None)
    assert unguarded["arm_contacts"] > 0
    assert unguarded["success"] is False
    assert "CONTACT" in {e["event"] for e in unguarded["events"]}

    config = load_config(None, SWING_RUN)
    guarded = run_path_following_inprocess(config, progress=None)
    margins = config.clearance
    assert guarded["arm_contacts"] == 0
    assert "CONTACT" not in {e["event"] for e in guarded["events"]}
    assert guarded["min_clearance_scene_m"] >= margins.stop_m - MARGIN_TOLERANCE_M
    assert guarded["min_clearance_self_m"] >= margins.self_stop_m - MARGIN_TOLERANCE_M


def test_a_path_out_of_reach_is_a_stall_and_not_a_good_run():
    config = load_config(None, ["run.duration_s=15", "run.settle_s=5", *UNREACHABLE_PATH])
    summary = run_path_following_inprocess(config, progress=None)
    assert summary["stalled_s"] > 0
    assert summary["path_progress"] < 0.95
    assert "STALL" in {e["event"] for e in summary["events"]}
    assert summary["success"] is False
    assert any("stalled" in problem for problem in summary["motion_problems"])


def _cycle(arc_m: float, speed_m_s: float = 0.1) -> ControlOutput:
    zero = np.zeros(3)
    return ControlOutput(
        qd_ref_rad_s=np.zeros(6), qd_c_rad_s=np.zeros(6), tool_p_m=zero, desired_p_m=zero,
        path_error_m=0.0, manipulability=0.05, path_s=0.0, path_arc_m=arc_m,
        path_speed_m_s=speed_m_s,
    )  # fmt: skip


def test_a_braked_stretch_is_not_a_stall_but_a_still_commanded_tool_is():
    """A controller frozen for 0.5 s (the plant's watchdog braked: its states held, not
    commanded) is not a stall once the tool moves again; the same half second of cycles
    that command 0.1 m/s while the tool stands still is one."""
    period_s = 0.001
    metrics = PathMetrics(settle_s=0.0, path_speed_m_s=0.1)
    arc_m = 0.0
    for k in range(2500):  # 1 s moving, 0.5 s braked where it was, 1 s moving again
        t_s = k * period_s
        braked = 1000 <= k < 1500
        arc_m += 0.0 if braked else 0.1 * period_s
        metrics.add(t_s, _cycle(arc_m), commanded=not braked)
    assert metrics.stalled_s == 0 and metrics.stalls == 0 and not metrics.problems()

    still = PathMetrics(settle_s=0.0, path_speed_m_s=0.1)
    for k in range(1600):  # commanded every cycle, never moving after 0.5 s
        t_s = k * period_s
        still.add(t_s, _cycle(min(t_s, 0.5) * 0.1))
    assert still.stalls == 1 and still.stalled_s >= 0.99
