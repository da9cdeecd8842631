"""Random reachable tasks for ``teleop sweep``: paths to follow and grasp scenes.

A task is a handful of config values (``--set`` overrides) drawn from a seeded generator,
so any one of them can be run again by hand with the command line it prints
(:meth:`PathTask.command`, :meth:`GraspTask.command`).

A drawn candidate is kept only if it is *reachable*, checked on the models the run uses
(:class:`ReachabilityChecker`): every point the tool must pass through has an inverse
kinematics solution (Pinocchio, damped least squares, warm-started from the previous
point so the arm stays on one branch) that is

- within the joint limits (less a margin),
- away from singularities (path following: manipulability; teleoperation: the position
  Jacobian's condition number, where the controller's slow-down begins),
- clear of the table, the bin and the floor by ``CLEARANCE_MARGIN_M``
  (MuJoCo's ``mj_geomDistance`` between the arm's and the scene's collision geoms),
- and continuous with the previous point (no joint jumps by more than
  ``MAX_JOINT_STEP_RAD``: a jump means the arm would have to swap configurations).

Path following checks the way from the start pose to the path and one whole period of
the path. A grasp scene checks the moves the scripted operator makes, with the tool
pointing down: each phase of its scenario (``operator.scenario_file``) from the target
before to the phase's target, along the route the operator plans around what it sees
(:func:`teleop.devices.scripted.routing.plan_route`: over or beside a virtual obstacle, over
the bin's walls). The virtual obstacle (non-colliding) is kept away from every target,
and the arm's links (the gripper's are the route's business) stay out of its influence
along the whole way: there the controller pushes the arm away, and the operator, who
steers the tool, would find it held back without knowing why.

Frames and units: world frame (z up, origin at the arm base on the table top), metres,
radians, seconds.
"""

from __future__ import annotations

import itertools
import math
import shlex
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import mujoco
import numpy as np
import pinocchio as pin

from teleop.control.desired_path import DesiredPath
from teleop.control.kinematics import (
    ArmModel,
    build_arm_model,
    manipulability,
    tool_pose_and_jacobian,
)
from teleop.control.teleop import (
    CONTINUOUS_LIMIT_RAD,
    approach_down_orientation,
    position_condition_number,
)
from teleop.core.config import Config, PathConfig, SceneConfig
from teleop.devices.scripted.routing import SceneKnowledge, plan_route
from teleop.devices.scripted.scenario import TOOL_ANCHOR, Scenario
from teleop.sim.proximity import apply_scene_overrides, arm_collision_geoms, obstacle_geoms

# --- Reachability -------------------------------------------------------------------------

# Inverse kinematics: iterations per point, damping of the least squares, largest joint
# step per iteration (rad) and the errors at which a point counts as reached.
IK_ITERATIONS = 200
IK_DAMPING = 1e-3
IK_MAX_STEP_RAD = 0.2
IK_POSITION_TOLERANCE_M = 1e-4
IK_ORIENTATION_TOLERANCE_RAD = 1e-3
# Between consecutive points of a move no joint turns more than this (rad): a larger step
# is a change of arm configuration (elbow or wrist flip), not a continuous motion.
MAX_JOINT_STEP_RAD = 0.3
# Every arm and gripper geom keeps this far from the table, the bin and the floor (m).
CLEARANCE_MARGIN_M = 0.02
# Joints stay this far inside their limits (rad) in path following; teleoperation uses
# its own ``teleop.joint_limit_margin_rad``.
PATH_JOINT_LIMIT_MARGIN_RAD = 0.05
# Path following: smallest manipulability sqrt(det(Jv Jv^T)) (m^3) on the path; half the
# smallest value seen on the default path (about 0.04).
MIN_PATH_MANIPULABILITY = 0.02
# Spacing of the checked points along a path or a move (m).
CHECK_SPACING_M = 0.01

# --- Path tasks -----------------------------------------------------------------------------

# Ranges of the random paths: centre in cylindrical coordinates around the base axis
# (distance m, azimuth rad, height m), radius, vertical amplitude, path speed.
PATH_CENTRE_DISTANCE_M = (0.0, 0.5)
PATH_CENTRE_AZIMUTH_RAD = (-math.pi, math.pi)
PATH_CENTRE_HEIGHT_M = (0.15, 0.6)
PATH_RADIUS_M = (0.08, 0.30)
PATH_Z_AMPLITUDE_M = (0.0, 0.08)
PATH_SPEED_M_S = (0.05, 0.15)
# A path task runs the settling time plus one lap of its circle, and is measured for at
# least this long after settling (s).
MIN_MEASURED_S = 10.0

# --- Grasp tasks ----------------------------------------------------------------------------

# Where a cube or a bin centre may be drawn: a disc sector around the base axis (m, rad)
# intersected with the table less an edge margin.
OBJECT_DISTANCE_M = (0.25, 0.80)
OBJECT_AZIMUTH_RAD = (-0.6 * math.pi, 0.6 * math.pi)
TABLE_EDGE_MARGIN_M = 0.05
# Height of the cube's centre on the table (half its 5 cm side) and of the bin's origin.
CUBE_Z_M = 0.025
BIN_Z_M = 0.0
# Half the bin's outer side (m): its walls reach 0.1 m from its centre.
BIN_HALF_M = 0.1
# Free space between the cube and the bin's outer wall (m): room for the fingers.
CUBE_BIN_GAP_M = 0.06
# The gripper may come closer to the table than CLEARANCE_MARGIN_M on moves that start or
# end within this distance (m) of the cube's centre: a top grasp puts the fingertips 5 mm
# above the table.
GRASP_ZONE_M = 0.05
# Obstacle sphere radius (m) and where a free one may be: distance, azimuth, centre height.
OBSTACLE_RADIUS_M = (0.03, 0.06)
OBSTACLE_DISTANCE_M = (0.2, 0.8)
OBSTACLE_HEIGHT_M = (0.05, 0.45)
# Every this many scenes, one has its obstacle placed in the way of the carry (on the
# straight move from the lift point to the point over the bin), the hard case for the
# operator; its draws are repeated until one is reachable (they are rejected more often
# than the others, so a share per draw would leave fewer of them among the tasks).
OBSTACLE_IN_THE_WAY_EVERY = 2
# Sideways and vertical scatter of an in-the-way obstacle around that move's midpoint (m).
OBSTACLE_IN_THE_WAY_SCATTER_M = 0.03
# The obstacle's surface stays this far beyond the controller's influence distance from
# every operator target and from the arm's start pose (m).
OBSTACLE_TARGET_GAP_M = 0.02
# Candidates drawn per task kept, at most (a generator that finds nothing stops).
MAX_CANDIDATES_PER_TASK = 200


class Unreachable(Exception):
    """A candidate failed the reachability check: ``kind`` says why in a few words (for
    counting), the message also where."""

    def __init__(self, kind: str, where: str = "", detail: str = "") -> None:
        super().__init__(f"{where}: {kind}{detail}" if where else f"{kind}{detail}")
        self.kind = kind


@dataclass
class ReachabilityChecker:
    """Inverse kinematics and clearance on the run's own models (one per process).

    ``arm``: the controller's Pinocchio model; ``mj_model``/``mj_data``: the plant's
    MuJoCo scene, whose cube, bin and obstacles :meth:`set_scene` moves.
    """

    config: Config
    arm: ArmModel = field(init=False)
    mj_model: mujoco.MjModel = field(init=False)
    mj_data: mujoco.MjData = field(init=False)

    def __post_init__(self) -> None:
        robot = self.config.robot
        self.arm = build_arm_model(robot)
        self.mj_model = mujoco.MjModel.from_xml_path(str(robot.scene_path))
        self.mj_data = mujoco.MjData(self.mj_model)
        model = self.mj_model
        # Joints whose limits allow a full turn each way are continuous (the shoulder pan
        # of the default arm): never clipped, never near a limit.
        lower, upper = self.arm.model.lowerPositionLimit, self.arm.model.upperPositionLimit
        self.limited = (lower > -CONTINUOUS_LIMIT_RAD) | (upper < CONTINUOUS_LIMIT_RAD)
        self.lower_rad = np.where(self.limited, lower, -np.inf)
        self.upper_rad = np.where(self.limited, upper, np.inf)
        self.qpos_index = np.array(
            [
                model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)]
                for name in robot.arm_joints
            ]
        )
        self.arm_geoms = arm_collision_geoms(model, robot)
        tool_body = int(model.site_bodyid[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE,
                                                             robot.tool_site)])  # fmt: skip
        self.gripper_geoms = frozenset(
            g for g in self.arm_geoms if self._in_subtree(int(model.geom_bodyid[g]), tool_body)
        )
        # The scene's collision geoms outside the arm, but the cube (the object the
        # gripper is meant to touch) and the fixed base the shoulder stands on.
        cube = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, robot.object_bodies[0])
        first_joint_body = int(
            model.jnt_bodyid[
                mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, robot.arm_joints[0])
            ]  # fmt: skip
        )
        base = int(model.body_parentid[first_joint_body])
        arm = set(self.arm_geoms)
        self.scene_geoms = [
            g
            for g in range(model.ngeom)
            if g not in arm
            and (model.geom_contype[g] or model.geom_conaffinity[g])
            and int(model.geom_bodyid[g]) not in (cube, base)
            and g not in obstacle_geoms(model, robot.obstacle_prefix)
        ]
        self.obstacle_geoms = obstacle_geoms(model, robot.obstacle_prefix)
        self._fromto = np.zeros(6)
        self.home_q_rad = np.array(robot.home_q_rad, dtype=float)
        # The task the scripted operator plays (grasp scenes walk its moves).
        self.scenario = Scenario.load(self.config.operator.scenario_path, robot.object_bodies)

    def _in_subtree(self, body: int, root: int) -> bool:
        while body > 0:
            if body == root:
                return True
            body = int(self.mj_model.body_parentid[body])
        return False

    def set_scene(self, scene: SceneConfig) -> None:
        """Move the cube, the bin and the obstacles as a run with ``scene`` would."""
        apply_scene_overrides(self.mj_model, scene, self.config.robot)

    def tool_pose(self, q_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """world_p_tool (3,) m and world_R_tool (3, 3) at ``q_rad``."""
        p, r, _ = tool_pose_and_jacobian(self.arm, q_rad)
        return p, r

    def solve(
        self, q0_rad: np.ndarray, world_p_m: np.ndarray, world_r: np.ndarray | None = None
    ) -> np.ndarray | None:
        """Joint angles that put the tool at ``world_p_m`` (and, given, its orientation at
        ``world_r``), from ``q0_rad``; None when damped least squares does not get there."""
        q = np.array(q0_rad, dtype=float)
        rows = 3 if world_r is None else 6
        damping = IK_DAMPING**2 * np.eye(rows)
        for _ in range(IK_ITERATIONS):
            p, r, jacobian = tool_pose_and_jacobian(self.arm, q)
            error = np.asarray(world_p_m, dtype=float) - p
            reached = float(np.linalg.norm(error)) <= IK_POSITION_TOLERANCE_M
            if world_r is not None:
                turn = pin.log3(world_r @ r.T)  # world-axes rotation from r to world_r
                error = np.concatenate((error, turn))
                reached = reached and float(np.linalg.norm(turn)) <= IK_ORIENTATION_TOLERANCE_RAD
            if reached:
                return q
            j = jacobian[:rows]
            step = j.T @ np.linalg.solve(j @ j.T + damping, error)
            norm = float(np.linalg.norm(step))
            if norm > IK_MAX_STEP_RAD:
                step *= IK_MAX_STEP_RAD / norm
            q = np.clip(q + step, self.lower_rad, self.upper_rad)
        return None

    def clearance_m(self, q_rad: np.ndarray, gripper: bool = True) -> float:
        """Smallest distance (m) between the arm's collision geoms (``gripper`` False: the
        gripper's left out) and the scene's (table, bin, floor), up to 1 m."""
        data = self.mj_data
        data.qpos[self.qpos_index] = q_rad
        mujoco.mj_kinematics(self.mj_model, data)
        best = 1.0
        for a in self.arm_geoms:
            if not gripper and a in self.gripper_geoms:
                continue
            for s in self.scene_geoms:
                best = min(best, mujoco.mj_geomDistance(self.mj_model, data, a, s, best,
                                                        self._fromto))  # fmt: skip
        return best

    def obstacle_clearance_m(self, q_rad: np.ndarray, reach_m: float) -> float:
        """Smallest distance (m) between the arm's links, the gripper left out, and the
        virtual obstacles, up to ``reach_m``."""
        data = self.mj_data
        data.qpos[self.qpos_index] = q_rad
        mujoco.mj_kinematics(self.mj_model, data)
        best = reach_m
        for a in self.arm_geoms:
            if a in self.gripper_geoms:
                continue
            for o in self.obstacle_geoms:
                best = min(best, mujoco.mj_geomDistance(self.mj_model, data, a, o, best,
                                                        self._fromto))  # fmt: skip
        return best

    def check_point(
        self,
        q_rad: np.ndarray,
        where: str,
        *,
        limit_margin_rad: float,
        min_manipulability: float = 0.0,
        max_condition: float = math.inf,
        gripper_clear: bool = True,
        obstacle_reach_m: float = 0.0,
    ) -> None:
        """Raise :class:`Unreachable` when ``q_rad`` breaks a limit, a singularity bound,
        the clearance margin or (``obstacle_reach_m`` > 0) puts an arm link, the gripper
        left out, within that distance of a virtual obstacle (``where`` names the point
        in the message)."""
        low = self.lower_rad + limit_margin_rad
        high = self.upper_rad - limit_margin_rad
        if np.any((q_rad < low) | (q_rad > high)):
            raise Unreachable("joint limit", where, f" (margin {limit_margin_rad:g} rad)")
        _, _, jacobian = tool_pose_and_jacobian(self.arm, q_rad)
        w = manipulability(jacobian[:3])
        if w < min_manipulability:
            raise Unreachable("near a singularity", where, f" (manipulability {w:.3f})")
        cond = position_condition_number(jacobian[:3])
        if cond > max_condition:
            raise Unreachable("near a singularity", where, f" (condition number {cond:.1f})")
        clearance = self.clearance_m(q_rad, gripper=gripper_clear)
        if clearance < CLEARANCE_MARGIN_M:
            raise Unreachable("too close to the scene", where, f" ({clearance * 1e3:.0f} mm)")
        if obstacle_reach_m > 0:
            distance_m = self.obstacle_clearance_m(q_rad, obstacle_reach_m)
            if distance_m < obstacle_reach_m:
                raise Unreachable(
                    "arm within the obstacle's influence", where, f" ({distance_m * 1e3:.0f} mm)"
                )

    def follow(
        self,
        q_rad: np.ndarray,
        points_m: Iterable[np.ndarray],
        where: str,
        world_r: np.ndarray | None = None,
        **bounds: float | bool,
    ) -> np.ndarray:
        """Walk the tool through ``points_m`` from ``q_rad``, each solved from the last
        and checked (:meth:`check_point`); returns the joint angles at the last point."""
        for i, point in enumerate(points_m):
            q = self.solve(q_rad, point, world_r)
            label = f"{where} point {i} {np.round(point, 3).tolist()}"
            if q is None:
                raise Unreachable("out of reach", label)
            if float(np.abs(q - q_rad).max()) > MAX_JOINT_STEP_RAD:
                raise Unreachable("configuration change", label)
            self.check_point(q, label, **bounds)  # type: ignore[arg-type]
            q_rad = q
        return q_rad


def segment(start_m: np.ndarray, end_m: np.ndarray, spacing_m: float = CHECK_SPACING_M) -> list:
    """Points from ``start_m`` to ``end_m`` (both included) at most ``spacing_m`` apart."""
    start, end = np.asarray(start_m, dtype=float), np.asarray(end_m, dtype=float)
    count = max(1, math.ceil(float(np.linalg.norm(end - start)) / spacing_m))
    return [start + (end - start) * (k / count) for k in range(count + 1)]


# --- Tasks ------------------------------------------------------------------------------------


def _literal(values: Sequence[float] | float) -> str:
    """A TOML literal of rounded floats, as ``--set`` takes it."""
    if isinstance(values, int | float):
        return repr(round(float(values), 4))
    return "[" + ", ".join(_literal(v) for v in values) + "]"


def _command(run_args: str, overrides: Sequence[str], config_file: str | None) -> str:
    config = f" --config {shlex.quote(config_file)}" if config_file else ""
    sets = " ".join(f"--set {shlex.quote(o)}" for o in overrides)
    return f"teleop run {run_args}{config} {sets}"


@dataclass(frozen=True)
class PathTask:
    """One random path (``path.*``, ``control.path_speed_m_s``) and its run length."""

    index: int
    seed: int
    center_m: tuple[float, float, float]
    radius_m: float
    z_amplitude_m: float
    path_speed_m_s: float
    duration_s: float

    def overrides(self) -> list[str]:
        """The ``--set`` values that make a run follow this path."""
        return [
            f"path.center_m={_literal(self.center_m)}",
            f"path.radius_m={_literal(self.radius_m)}",
            f"path.z_amplitude_m={_literal(self.z_amplitude_m)}",
            f"control.path_speed_m_s={_literal(self.path_speed_m_s)}",
            f"run.seed={self.seed}",
            f"run.duration_s={_literal(self.duration_s)}",
        ]

    def command(self, base: Sequence[str] = (), config_file: str | None = None) -> str:
        """The command line that runs this task by hand (after the sweep's own ``--set``
        values ``base`` and ``--config``)."""
        return _command("path-following --inprocess", [*base, *self.overrides()], config_file)

    def params(self) -> dict[str, object]:
        return {
            "center_m": list(self.center_m),
            "radius_m": self.radius_m,
            "z_amplitude_m": self.z_amplitude_m,
            "path_speed_m_s": self.path_speed_m_s,
            "duration_s": self.duration_s,
        }


@dataclass(frozen=True)
class GraspTask:
    """One random grasp scene (``scene.*``): cube, bin and obstacle placements."""

    index: int
    seed: int
    cube_p_m: tuple[float, float, float]
    bin_p_m: tuple[float, float, float]
    obstacle_p_m: tuple[float, float, float]
    obstacle_radius_m: float
    obstacle_in_the_way: bool

    def overrides(self) -> list[str]:
        """The ``--set`` values that make a run play this scene."""
        return [
            f"scene.cube_p_m={_literal(self.cube_p_m)}",
            f"scene.bin_p_m={_literal(self.bin_p_m)}",
            f"scene.obstacle_p_m=[{_literal(self.obstacle_p_m)}]",
            f"scene.obstacle_radius_m=[{_literal(self.obstacle_radius_m)}]",
            f"run.seed={self.seed}",
        ]

    def command(self, base: Sequence[str] = (), config_file: str | None = None) -> str:
        """The command line that runs this task by hand (after the sweep's own ``--set``
        values ``base`` and ``--config``)."""
        return _command("grasp --mode lockstep", [*base, *self.overrides()], config_file)

    def params(self) -> dict[str, object]:
        return {
            "cube_p_m": list(self.cube_p_m),
            "bin_p_m": list(self.bin_p_m),
            "obstacle_p_m": list(self.obstacle_p_m),
            "obstacle_radius_m": self.obstacle_radius_m,
            "obstacle_in_the_way": self.obstacle_in_the_way,
        }


@dataclass
class Generated:
    """What a generator drew: the tasks kept and why the other candidates were not."""

    tasks: list
    candidates: int
    rejected: Counter = field(default_factory=Counter)  # Unreachable.kind -> count


def _rounded(values: Iterable[float], digits: int = 3) -> tuple[float, ...]:
    return tuple(round(float(v), digits) for v in values)


def path_laps_duration_s(path: PathConfig, speed_m_s: float, settle_s: float) -> float:
    """Settling time plus one lap of the circle at ``speed_m_s``, at least
    :data:`MIN_MEASURED_S` (s)."""
    lap_m = 2.0 * math.pi * math.hypot(path.radius_m, path.z_amplitude_m * path.z_omega_rad
                                       / path.omega_rad)  # fmt: skip
    return round(settle_s + max(MIN_MEASURED_S, lap_m / speed_m_s), 1)


def check_path(checker: ReachabilityChecker, path: PathConfig) -> None:
    """Raise :class:`Unreachable` unless the arm can go from its home pose to the path and
    follow one whole period of it (see the module docstring)."""
    desired = DesiredPath(path)
    home_p, _ = checker.tool_pose(checker.home_q_rad)
    s0 = desired.closest_global(home_p)
    bounds = {
        "limit_margin_rad": PATH_JOINT_LIMIT_MARGIN_RAD,
        "min_manipulability": MIN_PATH_MANIPULABILITY,
    }
    q = checker.follow(checker.home_q_rad, segment(home_p, desired.point(s0)), "way in", **bounds)
    ds_per_m = 1.0 / math.sqrt(sum(v * v for v in desired.derivatives(s0)[0]))
    period_s = desired.search_window_s
    count = max(8, math.ceil(period_s / (CHECK_SPACING_M * ds_per_m)))
    points = [desired.point(s0 + period_s * k / count) for k in range(count + 1)]
    checker.follow(q, points, "path", **bounds)


def random_path_tasks(config: Config, count: int, seed: int) -> Generated:
    """``count`` reachable random paths, the same for the same ``seed``."""
    rng = np.random.default_rng(seed)
    checker = ReachabilityChecker(config)
    out = Generated(tasks=[], candidates=0)
    while len(out.tasks) < count:
        if out.candidates >= MAX_CANDIDATES_PER_TASK * count:
            raise RuntimeError(f"only {len(out.tasks)} reachable paths in {out.candidates} draws")
        out.candidates += 1
        distance = rng.uniform(*PATH_CENTRE_DISTANCE_M)
        azimuth = rng.uniform(*PATH_CENTRE_AZIMUTH_RAD)
        center = _rounded(
            (
                distance * math.cos(azimuth),
                distance * math.sin(azimuth),
                rng.uniform(*PATH_CENTRE_HEIGHT_M),
            )  # fmt: skip
        )
        radius = round(float(rng.uniform(*PATH_RADIUS_M)), 3)
        amplitude = round(float(rng.uniform(*PATH_Z_AMPLITUDE_M)), 3)
        speed = round(float(rng.uniform(*PATH_SPEED_M_S)), 3)
        path = PathConfig(
            center_m=center,  # type: ignore[arg-type]
            radius_m=radius,
            omega_rad=config.path.omega_rad,
            z_amplitude_m=amplitude,
            z_omega_rad=config.path.z_omega_rad,
        )
        try:
            check_path(checker, path)
        except Unreachable as exc:
            out.rejected[exc.kind] += 1
            continue
        index = len(out.tasks)
        out.tasks.append(
            PathTask(
                index=index,
                seed=seed + index,
                center_m=center,  # type: ignore[arg-type]
                radius_m=radius,
                z_amplitude_m=amplitude,
                path_speed_m_s=speed,
                duration_s=path_laps_duration_s(path, speed, config.run.settle_s),
            )
        )
    return out


def _table_point(rng: np.random.Generator, distance_m: tuple[float, float],
                 azimuth_rad: tuple[float, float]) -> np.ndarray:  # fmt: skip
    d, a = rng.uniform(*distance_m), rng.uniform(*azimuth_rad)
    return np.array([d * math.cos(a), d * math.sin(a)])


def table_extent_m(checker: ReachabilityChecker) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) x-y corners of the table top (m), read from the scene's ``table`` geom."""
    model = checker.mj_model
    table = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "table")
    centre, half = model.geom_pos[table][:2], model.geom_size[table][:2]
    return centre - half, centre + half


@dataclass(frozen=True)
class Move:
    """One phase of the operator's task as the tool travels it (world, m): from the end of
    the move before, through the route's waypoints, to the phase's target."""

    phase: str
    points_m: tuple[np.ndarray, ...]  # start, waypoints..., target
    holding: bool  # the phase carries the held object


def operator_moves(scenario: Scenario, knowledge: SceneKnowledge, start_p_m: np.ndarray,
                   objects_p_m: dict[str, np.ndarray]) -> list[Move]:  # fmt: skip
    """The moves of ``scenario`` from ``start_p_m``, the objects where they lie, planned as
    the operator plans them (:class:`teleop.devices.scripted.operator.ScriptedOperator`): each
    phase's target is its anchor (an object as it lies when the phase starts, or the tool)
    plus its offset, reached along :func:`plan_route` around the keep-out volumes of that
    phase. Phases that do not move the tool are left out."""
    tool = np.asarray(start_p_m, dtype=float)
    bin_p = objects_p_m.get("bin")
    moves = []
    for phase in scenario.phases:
        anchor = phase.target.relative_to
        origin = tool if anchor == TOOL_ANCHOR else np.asarray(objects_p_m[anchor], dtype=float)
        target = origin + np.array(phase.target.offset_m)
        if float(np.linalg.norm(target - tool)) <= phase.tolerance_m:
            continue
        volumes = knowledge.keep_outs(bin_p, holding=phase.carrying)
        route = plan_route(tool, target, volumes)
        moves.append(Move(phase.name, (tool, *route, target), phase.carrying))
        tool = target
    return moves


def carry_move(checker: ReachabilityChecker, cube_p_m: np.ndarray,
               bin_p_m: np.ndarray) -> tuple[np.ndarray, ...]:  # fmt: skip
    """The straight carry of the operator's task with nothing in the way: (start, end) of
    its longest move that holds the object (world, m)."""
    home_p, _ = checker.tool_pose(checker.home_q_rad)
    moves = operator_moves(checker.scenario, SceneKnowledge(), home_p,
                           {"cube": cube_p_m, "bin": bin_p_m})  # fmt: skip
    carrying = [m for m in moves if m.holding] or moves
    longest = max(carrying, key=lambda m: float(np.linalg.norm(m.points_m[-1] - m.points_m[0])))
    return longest.points_m


def check_grasp(checker: ReachabilityChecker, task: GraspTask) -> None:
    """Raise :class:`Unreachable` unless the arm, tool pointing down, makes every move of
    the operator's task from its home pose (:func:`operator_moves`), its links out of the
    obstacle's influence, and the obstacle keeps clear of the targets and of the arm's
    start pose."""
    config = checker.config
    scene = SceneConfig(
        cube_p_m=task.cube_p_m,
        bin_p_m=task.bin_p_m,
        obstacle_p_m=(task.obstacle_p_m,),
        obstacle_radius_m=(task.obstacle_radius_m,),
    )
    checker.set_scene(scene)
    knowledge = SceneKnowledge.from_model(checker.mj_model, config)
    cube = np.array(task.cube_p_m)
    home_p, home_r = checker.tool_pose(checker.home_q_rad)
    moves = operator_moves(checker.scenario, knowledge, home_p,
                           {"cube": cube, "bin": np.array(task.bin_p_m)})  # fmt: skip
    reach = config.teleop.obstacle_influence_m + OBSTACLE_TARGET_GAP_M + task.obstacle_radius_m
    obstacle = np.array(task.obstacle_p_m)
    for move in moves:
        if float(np.linalg.norm(move.points_m[-1] - obstacle)) < reach:
            raise Unreachable("target within the obstacle's influence", move.phase)
    world_r = approach_down_orientation(home_r)
    bounds = {
        "limit_margin_rad": config.teleop.joint_limit_margin_rad,
        "max_condition": config.teleop.singularity_slowdown_cond,
        "obstacle_reach_m": config.teleop.obstacle_influence_m,
    }
    q = checker.follow(checker.home_q_rad, [home_p], "start", world_r, **bounds)
    for move in moves:
        for k, (start, end) in enumerate(itertools.pairwise(move.points_m)):
            at_cube = min(np.linalg.norm(start - cube), np.linalg.norm(end - cube)) < GRASP_ZONE_M
            where = move.phase if len(move.points_m) == 2 else f"{move.phase} leg {k}"
            q = checker.follow(q, segment(start, end), where, world_r, **bounds,
                               gripper_clear=not at_cube)  # fmt: skip


def random_grasp_tasks(config: Config, count: int, seed: int) -> Generated:
    """``count`` reachable random grasp scenes, the same for the same ``seed``."""
    rng = np.random.default_rng(seed)
    checker = ReachabilityChecker(config)
    low, high = table_extent_m(checker)
    low, high = low + TABLE_EDGE_MARGIN_M, high - TABLE_EDGE_MARGIN_M
    home_start = checker.home_q_rad
    out = Generated(tasks=[], candidates=0)
    while len(out.tasks) < count:
        if out.candidates >= MAX_CANDIDATES_PER_TASK * count:
            raise RuntimeError(f"only {len(out.tasks)} reachable scenes in {out.candidates} draws")
        out.candidates += 1
        cube_xy = _table_point(rng, OBJECT_DISTANCE_M, OBJECT_AZIMUTH_RAD)
        bin_xy = _table_point(rng, OBJECT_DISTANCE_M, OBJECT_AZIMUTH_RAD)
        in_the_way = len(out.tasks) % OBSTACLE_IN_THE_WAY_EVERY == OBSTACLE_IN_THE_WAY_EVERY - 1
        radius = round(float(rng.uniform(*OBSTACLE_RADIUS_M)), 3)
        if in_the_way:
            carry = carry_move(
                checker, np.array([*cube_xy, CUBE_Z_M]), np.array([*bin_xy, BIN_Z_M])
            )
            middle = (carry[0] + carry[-1]) / 2
            obstacle = middle + rng.uniform(-1, 1, 3) * OBSTACLE_IN_THE_WAY_SCATTER_M
        else:
            obstacle = np.array(
                [
                    *_table_point(rng, OBSTACLE_DISTANCE_M, OBJECT_AZIMUTH_RAD),
                    rng.uniform(*OBSTACLE_HEIGHT_M),
                ]  # fmt: skip
            )
        if not (np.all(cube_xy >= low) and np.all(cube_xy <= high)):
            out.rejected["cube off the table"] += 1
            continue
        if not (np.all(bin_xy - BIN_HALF_M >= low) and np.all(bin_xy + BIN_HALF_M <= high)):
            out.rejected["bin off the table"] += 1
            continue
        if np.abs(cube_xy - bin_xy).max() < BIN_HALF_M + CUBE_Z_M + CUBE_BIN_GAP_M:
            out.rejected["cube too close to the bin"] += 1
            continue
        index = len(out.tasks)
        task = GraspTask(
            index=index,
            seed=seed + index,
            cube_p_m=_rounded((*cube_xy, CUBE_Z_M)),  # type: ignore[arg-type]
            bin_p_m=_rounded((*bin_xy, BIN_Z_M)),  # type: ignore[arg-type]
            obstacle_p_m=_rounded(obstacle),  # type: ignore[arg-type]
            obstacle_radius_m=radius,
            obstacle_in_the_way=in_the_way,
        )
        try:
            check_grasp(checker, task)
            _check_obstacle_clear_of_start(checker, task, home_start, config)
        except Unreachable as exc:
            out.rejected[exc.kind] += 1
            continue
        out.tasks.append(task)
    return out


def _check_obstacle_clear_of_start(
    checker: ReachabilityChecker, task: GraspTask, q_rad: np.ndarray, config: Config
) -> None:
    """The arm's start pose lies outside the obstacle's influence (its scene is set)."""
    model, data = checker.mj_model, checker.mj_data
    data.qpos[checker.qpos_index] = q_rad
    mujoco.mj_kinematics(model, data)
    fromto = np.zeros(6)
    reach = config.teleop.obstacle_influence_m + OBSTACLE_TARGET_GAP_M
    for obstacle in obstacle_geoms(model, config.robot.obstacle_prefix):
        for a in checker.arm_geoms:
            if mujoco.mj_geomDistance(model, data, a, obstacle, reach, fromto) < reach:
                raise Unreachable("start within the obstacle's influence")
