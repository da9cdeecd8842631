"""The sweep's task generator (seeded, reachable) and its judging of run summaries."""

from __future__ import annotations

import numpy as np
import pytest

from teleop.core.config import Config, PathConfig, SceneConfig, load_config
from teleop.devices.scripted.routing import SceneKnowledge
from teleop.run import sweep, tasks
from teleop.run.failure import ServiceFailed
from teleop.run.supervise import StartTimeout
from teleop.run.tasks import GraspTask, ReachabilityChecker, Unreachable


@pytest.fixture(scope="module")
def checker() -> ReachabilityChecker:
    return ReachabilityChecker(load_config())


def test_path_tasks_are_the_same_for_the_same_seed(config: Config) -> None:
    first = tasks.random_path_tasks(config, 3, seed=5)
    again = tasks.random_path_tasks(config, 3, seed=5)
    other = tasks.random_path_tasks(config, 3, seed=6)
    assert first.tasks == again.tasks
    assert first.candidates == again.candidates
    assert first.tasks != other.tasks


def test_grasp_tasks_are_the_same_for_the_same_seed(config: Config) -> None:
    first = tasks.random_grasp_tasks(config, 4, seed=2)
    assert first.tasks == tasks.random_grasp_tasks(config, 4, seed=2).tasks
    assert first.tasks != tasks.random_grasp_tasks(config, 4, seed=3).tasks


def test_a_task_is_its_overrides(config: Config) -> None:
    """What a sweep runs is what the printed command runs: the task's --set values load
    into the config with the task's numbers."""
    path = tasks.random_path_tasks(config, 1, seed=1).tasks[0]
    loaded = load_config(None, path.overrides())
    assert loaded.path.center_m == pytest.approx(path.center_m)
    assert loaded.path.radius_m == pytest.approx(path.radius_m)
    assert loaded.control.path_speed_m_s == pytest.approx(path.path_speed_m_s)
    assert loaded.run.duration_s == pytest.approx(path.duration_s)
    assert "--inprocess" in path.command() and "path.center_m" in path.command()
    scene = tasks.random_grasp_tasks(config, 1, seed=1).tasks[0]
    loaded = load_config(None, scene.overrides())
    assert loaded.scene.cube_p_m == pytest.approx(scene.cube_p_m)
    assert loaded.scene.bin_p_m == pytest.approx(scene.bin_p_m)
    assert loaded.scene.obstacle_p_m[0] == pytest.approx(scene.obstacle_p_m)
    assert "--mode lockstep" in scene.command()


def test_generated_paths_are_reachable_and_follow_the_ranges(
    config: Config, checker: ReachabilityChecker
) -> None:
    generated = tasks.random_path_tasks(config, 4, seed=11)
    for task in generated.tasks:
        assert tasks.PATH_RADIUS_M[0] <= task.radius_m <= tasks.PATH_RADIUS_M[1]
        assert tasks.PATH_SPEED_M_S[0] <= task.path_speed_m_s <= tasks.PATH_SPEED_M_S[1]
        assert task.duration_s >= config.run.settle_s + tasks.MIN_MEASURED_S
        path = PathConfig(
            center_m=task.center_m, radius_m=task.radius_m, z_amplitude_m=task.z_amplitude_m
        )
        tasks.check_path(checker, path)  # raises if not reachable
    # The generator does reject: some draws of these ranges are out of reach.
    assert generated.candidates > len(generated.tasks)
    assert sum(generated.rejected.values()) == generated.candidates - len(generated.tasks)


def test_the_default_path_is_reachable(config: Config, checker: ReachabilityChecker) -> None:
    tasks.check_path(checker, config.path)


@pytest.mark.parametrize(
    ("path", "kind"),
    [
        (PathConfig(center_m=(1.2, 0.0, 0.3), radius_m=0.1), "out of reach"),
        (
            PathConfig(center_m=(0.45, 0.0, 0.0), radius_m=0.1, z_amplitude_m=0.0),
            "too close to the scene",
        ),  # fmt: skip
    ],
)
def test_unreachable_paths_are_rejected(
    checker: ReachabilityChecker, path: PathConfig, kind: str
) -> None:
    with pytest.raises(Unreachable) as caught:
        tasks.check_path(checker, path)
    assert caught.value.kind == kind


def _scene(cube=(0.45, -0.25, 0.025), bin_=(0.35, 0.35, 0.0), obstacle=(0.55, 0.1, 0.15)):
    return GraspTask(0, 0, cube, bin_, obstacle, 0.05, False)


def test_the_default_scene_is_reachable(checker: ReachabilityChecker) -> None:
    tasks.check_grasp(checker, _scene())


@pytest.mark.parametrize(
    ("scene", "kind"),
    [
        (_scene(cube=(1.1, 0.0, 0.025)), "out of reach"),
        (_scene(obstacle=(0.45, -0.25, 0.15)), "target within the obstacle's influence"),
    ],
)
def test_unreachable_scenes_are_rejected(
    checker: ReachabilityChecker, scene: GraspTask, kind: str
) -> None:
    with pytest.raises(Unreachable) as caught:
        tasks.check_grasp(checker, scene)
    assert caught.value.kind == kind


def test_the_operators_route_is_what_is_checked(checker: ReachabilityChecker) -> None:
    """An obstacle right on the carry: the operator routes the tool over it, and that
    route is what the generator walks. Here the straight carry passes below the arm,
    but on the route over, the forearm sweeps through the obstacle, where the
    controller would push the arm back (the operator, who steers the tool, would be
    held off without knowing why): not a reachable task."""
    scene = GraspTask(0, 0, (-0.116, 0.506, 0.025), (0.508, -0.446, 0.0), (0.219, 0.03, 0.178),
                      0.056, True)  # fmt: skip
    checker.set_scene(
        SceneConfig(
            cube_p_m=scene.cube_p_m,
            bin_p_m=scene.bin_p_m,
            obstacle_p_m=(scene.obstacle_p_m,),
            obstacle_radius_m=(scene.obstacle_radius_m,),
        )
    )
    knowledge = SceneKnowledge.from_model(checker.mj_model, checker.config)
    home_p, _ = checker.tool_pose(checker.home_q_rad)
    objects = {"cube": np.array(scene.cube_p_m), "bin": np.array(scene.bin_p_m)}
    moves = {m.phase: m for m in tasks.operator_moves(checker.scenario, knowledge, home_p, objects)}
    assert list(moves) == ["approach", "descend", "lift", "carry", "retreat"]
    carry = moves["carry"].points_m
    assert len(carry) == 4 and carry[1][2] > scene.obstacle_p_m[2] + 0.1  # up, over, down
    with pytest.raises(Unreachable) as caught:
        tasks.check_grasp(checker, scene)
    assert caught.value.kind == "arm within the obstacle's influence"
    assert "carry leg 1" in str(caught.value)


def test_a_far_cube_under_an_obstacle_holds_the_arm_back(checker: ReachabilityChecker) -> None:
    """The tool's way to a cube near the edge of the reach stays clear of the obstacle,
    the arm's links pass through its influence: rejected (the operator, steering the tool,
    stopped 194 mm short of it, and said "out of reach")."""
    scene = GraspTask(0, 0, (0.7, -0.053, 0.025), (0.158, 0.343, 0.0), (0.511, -0.112, 0.422),
                      0.038, False)  # fmt: skip
    with pytest.raises(Unreachable) as caught:
        tasks.check_grasp(checker, scene)
    assert caught.value.kind == "arm within the obstacle's influence"


def test_every_other_scene_has_its_obstacle_in_the_way(config: Config) -> None:
    generated = tasks.random_grasp_tasks(config, 6, seed=0)
    assert [t.obstacle_in_the_way for t in generated.tasks] == [False, True] * 3


def test_inverse_kinematics_reaches_the_pose_it_returns(checker: ReachabilityChecker) -> None:
    _, home_r = checker.tool_pose(checker.home_q_rad)
    target = np.array([0.5, -0.1, 0.1])
    q = checker.solve(checker.home_q_rad, target, home_r)
    assert q is not None
    p, r = checker.tool_pose(q)
    assert np.linalg.norm(p - target) <= tasks.IK_POSITION_TOLERANCE_M
    assert np.allclose(r, home_r, atol=1e-3)


def test_failures_are_counted_by_kind_without_their_numbers() -> None:
    assert sweep.reason_kind("event STALL at 0.5 s") == "event STALL"
    assert sweep.reason_kind("path error RMS: 2.71 mm > 1 mm") == "path error RMS"
    assert (
        sweep.reason_kind("operator: the target out of reach in descend (stopped 120 mm short)")
        == "operator: the target out of reach in descend"
    )


@pytest.mark.parametrize(
    ("failure", "runs", "success"),
    [("not ready", 2, True), ("not running", 2, True), ("died", 1, False)],
)
def test_a_stack_that_did_not_come_up_is_started_again(
    tmp_path, monkeypatch: pytest.MonkeyPatch, failure: str, runs: int, success: bool
) -> None:
    """A grasp run whose programs were not RUNNING or whose services were not ready in
    time never ran: the task is started again (and the retry counted); a service that
    failed once the run was under way is the task's result."""
    calls = []
    done = {
        "scenario": "grasp",
        "object_in_box": True,
        "arm_contacts": 0,
        "max_device_force_n": 1.0,
        "commands_applied": 6000,
    }

    def run(job: sweep.Job) -> dict:
        calls.append(job)
        if len(calls) == 1:
            if failure == "not running":
                raise StartTimeout("stack not RUNNING after 15 s")
            raise ServiceFailed("controller", "failed", tmp_path / "controller.log", "",
                                startup=failure == "not ready")  # fmt: skip
        return done

    monkeypatch.setattr(sweep, "_run", run)
    task = GraspTask(0, 0, (0.45, -0.25, 0.025), (0.35, 0.35, 0.0), (0.55, 0.1, 0.15), 0.05, False)
    record = sweep.run_job(sweep.Job("grasp", task, None, (), str(tmp_path)))
    assert len(calls) == runs and record.success is success
    assert record.startup_retries == runs - 1
    assert record.to_json().get("startup_retries", 0) == runs - 1
