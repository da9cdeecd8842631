"""Virtual obstacles: where they are, and how close the arm is to them.

Obstacles are MJCF geoms whose names start with ``RobotConfig.obstacle_prefix`` and
whose ``contype``/``conaffinity`` are 0: physics ignores them, the controller avoids
them and the operator feels them (paper section 4.3, fictitious forces). Their true
pose lives in the plant's MuJoCo model, so the distance is computed there, every
step, with MuJoCo's own narrow phase (``mj_geomDistance``) against the arm's
collision geoms, and sent to the controller as a :class:`ProximitySample`.

Everything here is in the world frame (z up, origin at the arm base), in metres.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import mujoco
import numpy as np

from teleop.core.config import ModelError, RobotConfig, SceneConfig

# Distances are searched up to the avoidance influence distance plus this margin (m),
# so a sample just outside the influence zone still reports a true distance.
DEFAULT_SEARCH_DISTANCE_M = 0.15
# Reported when no obstacle is within the search distance (m): "far", finite for messages.
FAR_DISTANCE_M = 1.0e3
# Witness points closer than this (m) give no usable direction; fall back to geom centres.
MIN_DIRECTION_LENGTH_M = 1e-9
# Name of the bin body in the scene (the drop-off target); the config only moves it.
BIN_BODY = "bin"


@dataclass(frozen=True)
class ProximitySample:
    """The closest pair (arm geom, obstacle geom) in the world frame.

    ``distance_m`` is signed (negative when the arm penetrates the obstacle).
    ``world_n_away`` is the unit direction in which moving the arm point increases the
    distance (from the obstacle towards the arm point). ``arm_body`` is the MuJoCo body
    id of the arm geom, ``obstacle`` the MuJoCo geom id of the obstacle (-1 when far).
    """

    distance_m: float
    world_p_arm_m: np.ndarray  # (3,)
    world_p_obstacle_m: np.ndarray  # (3,)
    world_n_away: np.ndarray  # (3,) unit
    arm_body: int
    obstacle: int

    @property
    def near(self) -> bool:
        """True when an obstacle was found within the search distance."""
        return self.obstacle >= 0

    def write_to(self, state: np.ndarray) -> None:
        """Fill the proximity fields of a PLANT_STATE record (the plant's half)."""
        state["distance_m"] = self.distance_m
        state["world_p_arm_m"] = self.world_p_arm_m
        state["world_p_obstacle_m"] = self.world_p_obstacle_m
        state["world_n_away"] = self.world_n_away
        state["arm_body"] = self.arm_body
        state["obstacle_geom"] = self.obstacle

    @classmethod
    def from_state(cls, state: np.ndarray) -> ProximitySample | None:
        """The closest obstacle a PLANT_STATE record carries (the controller's half);
        None when none is in reach."""
        if int(state["obstacle_geom"]) < 0:
            return None
        return cls(
            distance_m=float(state["distance_m"]),
            world_p_arm_m=np.array(state["world_p_arm_m"]),
            world_p_obstacle_m=np.array(state["world_p_obstacle_m"]),
            world_n_away=np.array(state["world_n_away"]),
            arm_body=int(state["arm_body"]),
            obstacle=int(state["obstacle_geom"]),
        )


def _natural_key(name: str) -> list[int | str]:
    """Sort key that puts obstacle_2 before obstacle_10."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def obstacle_geoms(model: mujoco.MjModel, prefix: str) -> list[int]:
    """Geom ids whose names start with ``prefix``, in natural name order."""
    named = []
    for g in range(model.ngeom):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or ""
        if name.startswith(prefix):
            named.append((name, g))
    return [g for _, g in sorted(named, key=lambda item: _natural_key(item[0]))]


def arm_collision_geoms(model: mujoco.MjModel, robot: RobotConfig) -> list[int]:
    """Colliding geoms of the moving arm: the subtree of the first arm joint's body.

    That subtree is the arm chain and the gripper; the fixed base, the world (table,
    floor) and free objects (cube, bin) are outside it by construction.
    """
    joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, robot.arm_joints[0])
    if joint < 0:
        raise ModelError(f"no joint {robot.arm_joints[0]!r} in the model")
    root = int(model.jnt_bodyid[joint])

    def in_subtree(body: int) -> bool:
        while body > 0:
            if body == root:
                return True
            body = int(model.body_parentid[body])
        return False

    return [
        g
        for g in range(model.ngeom)
        if in_subtree(int(model.geom_bodyid[g]))
        and (model.geom_contype[g] or model.geom_conaffinity[g])
    ]


class ObstacleProximity:
    """Closest distance from the arm to the virtual obstacles, one call per plant step.

    Geom ids are resolved once; :meth:`closest` reads the current ``data`` (geom poses
    from the last ``mj_forward``/``mj_step``) and writes nothing into it.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        robot: RobotConfig,
        search_distance_m: float = DEFAULT_SEARCH_DISTANCE_M,
    ) -> None:
        self.model = model
        self.data = data
        self.search_distance_m = search_distance_m
        self.obstacles = obstacle_geoms(model, robot.obstacle_prefix)
        self.arm_geoms = arm_collision_geoms(model, robot)
        if not self.arm_geoms:
            raise ModelError("the arm has no collision geoms")
        self._pairs = [(a, o) for o in self.obstacles for a in self.arm_geoms]
        self._fromto = np.zeros(6)
        self._best = np.zeros(6)

    def closest(self) -> ProximitySample:
        """The closest arm/obstacle pair, or a far sample when none is within reach."""
        model, data = self.model, self.data
        best_distance = self.search_distance_m
        best_pair: tuple[int, int] | None = None
        fromto, best = self._fromto, self._best
        for arm_geom, obstacle in self._pairs:
            distance = mujoco.mj_geomDistance(
                model, data, arm_geom, obstacle, best_distance, fromto
            )
            if distance < best_distance:
                best_distance = distance
                best_pair = (arm_geom, obstacle)
                best[:] = fromto
        if best_pair is None:
            return ProximitySample(
                distance_m=FAR_DISTANCE_M,
                world_p_arm_m=np.zeros(3),
                world_p_obstacle_m=np.zeros(3),
                world_n_away=np.array([0.0, 0.0, 1.0]),
                arm_body=-1,
                obstacle=-1,
            )
        arm_geom, obstacle = best_pair
        p_arm, p_obstacle = best[:3].copy(), best[3:].copy()
        # fromto runs from the arm geom to the obstacle; when they overlap the witness
        # points cross over, so the sign of the distance orients the direction.
        direction = (p_arm - p_obstacle) * (1.0 if best_distance >= 0 else -1.0)
        length = float(np.linalg.norm(direction))
        if length < MIN_DIRECTION_LENGTH_M:
            direction = data.geom_xpos[arm_geom] - data.geom_xpos[obstacle]
            length = float(np.linalg.norm(direction))
        n_away = direction / length if length > 0 else np.array([0.0, 0.0, 1.0])
        return ProximitySample(
            distance_m=float(best_distance),
            world_p_arm_m=p_arm,
            world_p_obstacle_m=p_obstacle,
            world_n_away=n_away,
            arm_body=int(model.geom_bodyid[arm_geom]),
            obstacle=obstacle,
        )


def body_names(model: mujoco.MjModel) -> tuple[str, ...]:
    """Body names indexed by MuJoCo body id: the controller maps ``arm_body`` with them."""
    return tuple(
        mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) or "" for b in range(model.nbody)
    )


def apply_scene_overrides(model: mujoco.MjModel, scene: SceneConfig, robot: RobotConfig) -> None:
    """Move the cube, the bin and the obstacles to the configured places (world frame, m).

    Edits the model only; call ``mj_resetData`` (``Plant.reset``) afterwards. A free
    body's pose comes from its joint's qpos, whose initial value ``mj_resetData`` copies
    from ``model.qpos0`` (compiled from the body's ``pos``): both are set so the model
    stays self-consistent. Obstacles are spheres: their radius is ``geom_size[0]``,
    mirrored into the bounding radius and box that distance queries use to cull.
    Raises ValueError when the configuration does not match the scene.
    """
    if scene.cube_p_m:
        if not robot.object_bodies:
            raise ValueError("scene.cube_p_m: robot.object_bodies names no object")
        cube = _body_id(model, robot.object_bodies[0])
        model.body_pos[cube] = scene.cube_p_m
        joint = int(model.body_jntadr[cube])
        if joint >= 0 and model.jnt_type[joint] == mujoco.mjtJoint.mjJNT_FREE:
            adr = int(model.jnt_qposadr[joint])
            model.qpos0[adr : adr + 3] = scene.cube_p_m
    if scene.bin_p_m:
        model.body_pos[_body_id(model, BIN_BODY)] = scene.bin_p_m
    obstacles = obstacle_geoms(model, robot.obstacle_prefix)
    for key, values in (
        ("scene.obstacle_p_m", scene.obstacle_p_m),
        ("scene.obstacle_radius_m", scene.obstacle_radius_m),
    ):
        if values and len(values) != len(obstacles):
            raise ValueError(
                f"{key}: {len(values)} value(s) for {len(obstacles)} obstacle geom(s) "
                f"named {robot.obstacle_prefix!r}*"
            )
    for geom, position in zip(obstacles, scene.obstacle_p_m, strict=False):
        if model.geom_bodyid[geom] != 0:
            raise ValueError(f"scene.obstacle_p_m: obstacle geom {geom} is not a world geom")
        model.geom_pos[geom] = position
        model.geom_sameframe[geom] = 0  # no longer at its body's origin
    for geom, radius in zip(obstacles, scene.obstacle_radius_m, strict=False):
        if model.geom_type[geom] != mujoco.mjtGeom.mjGEOM_SPHERE:
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, geom)
            raise ValueError(f"scene.obstacle_radius_m: obstacle {name!r} is not a sphere")
        model.geom_size[geom, 0] = radius
        model.geom_rbound[geom] = radius
        model.geom_aabb[geom] = (0.0, 0.0, 0.0, radius, radius, radius)


def _body_id(model: mujoco.MjModel, name: str) -> int:
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
    if body < 0:
        raise ValueError(f"no body {name!r} in the scene")
    return body
