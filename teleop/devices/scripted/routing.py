"""How the scripted operator plans a move: around or over what it sees in the way.

A person moving the tool to a target does not push it straight through a virtual
obstacle's repulsion or drag the gripper over a bin wall: they see both and go over
them (or around, when over is too high). :class:`SceneKnowledge` is what the operator
knows of the scene's fixed geometry, read once from the same scene file and config as the
plant (the virtual obstacles' spheres, the bin's walls relative to its origin);
:func:`plan_route` turns a straight move into a few waypoints that keep the tool point out
of every :class:`KeepOut` volume.

The keep-out volumes are about the tool point, so they are the obstacles grown by what
the tool carries around it: a virtual obstacle's sphere by the controller's influence
distance (where its repulsion starts) plus ``TOOL_CLEARANCE_M``; the bin's box by
``BIN_MARGIN_M`` sideways and, above its walls, by the fingertips below the tool point
and a held object's half height.

Frames and units: world frame (z up, origin at the arm base), metres.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import mujoco
import numpy as np

from teleop.core.config import Config
from teleop.sim.proximity import BIN_BODY, apply_scene_overrides, obstacle_geoms

# Clearance the operator keeps between the tool point and a virtual obstacle's influence
# zone (m): the gripper around the tool point reaches a few centimetres out.
TOOL_CLEARANCE_M = 0.03
# Sideways margin around the bin's walls (m) and height above them (m) for the tool point.
BIN_MARGIN_M = 0.03
# The fingertips reach this far below the tool point (m; teleop/assets/scene_arm6.xml).
FINGERTIP_DROP_M = 0.02
# Half the height of a held object (m): the 5 cm cube hangs this far below the tool point.
HELD_HALF_HEIGHT_M = 0.025
# The operator does not route higher than this (m): above it, a detour to the side.
MAX_ROUTE_HEIGHT_M = 0.55
# A sideways detour passes the obstacle's keep-out sphere at these multiples of its radius.
AROUND_FACTORS = (1.15, 1.4, 1.8)
# An over-route passes this far (m) above the highest volume it clears.
OVER_MARGIN_M = 0.01
# Rounds of raising an over-route past volumes its legs meet.
OVER_ROUNDS = 4
# Below this length (m) a move or direction is treated as a point.
TINY_M = 1e-9


@dataclass(frozen=True)
class KeepOut:
    """A volume the tool point stays out of: a sphere (``radius_m`` > 0) or an
    axis-aligned box (``low_m``..``high_m``)."""

    name: str
    low_m: np.ndarray  # (3,) box corner, or the sphere's centre
    high_m: np.ndarray  # (3,) box corner, or the sphere's centre
    radius_m: float = 0.0

    @classmethod
    def sphere(cls, name: str, centre_m: np.ndarray, radius_m: float) -> KeepOut:
        centre = np.asarray(centre_m, dtype=float)
        return cls(name, centre, centre, radius_m)

    @property
    def top_m(self) -> float:
        """The highest point of the volume (m)."""
        return float(self.high_m[2]) + self.radius_m

    def contains(self, p_m: np.ndarray) -> bool:
        """Whether point ``p_m`` lies inside the volume."""
        if self.radius_m > 0:
            return float(np.linalg.norm(np.asarray(p_m) - self.low_m)) < self.radius_m
        return bool(np.all(p_m > self.low_m) and np.all(p_m < self.high_m))

    def meets(self, start_m: np.ndarray, end_m: np.ndarray) -> bool:
        """Whether the straight move ``start_m`` -> ``end_m`` passes through the volume."""
        start, end = np.asarray(start_m, dtype=float), np.asarray(end_m, dtype=float)
        if self.radius_m > 0:
            return distance_to_segment(self.low_m, start, end) < self.radius_m
        return _segment_meets_box(start, end, self.low_m, self.high_m)


def distance_to_segment(p_m: np.ndarray, start_m: np.ndarray, end_m: np.ndarray) -> float:
    """Distance (m) from point ``p_m`` to the segment ``start_m``-``end_m``."""
    d = end_m - start_m
    length2 = float(d @ d)
    u = 0.0 if length2 < TINY_M else min(1.0, max(0.0, float((p_m - start_m) @ d) / length2))
    return float(np.linalg.norm(start_m + u * d - p_m))


def _segment_meets_box(start: np.ndarray, end: np.ndarray, low: np.ndarray,
                       high: np.ndarray) -> bool:  # fmt: skip
    """Slab test: whether the segment crosses the open box (low, high)."""
    t0, t1 = 0.0, 1.0
    d = end - start
    for axis in range(3):
        if abs(d[axis]) < TINY_M:
            if not low[axis] < start[axis] < high[axis]:
                return False
            continue
        a = (low[axis] - start[axis]) / d[axis]
        b = (high[axis] - start[axis]) / d[axis]
        t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
        if t0 >= t1:
            return False
    return True


@dataclass(frozen=True)
class SceneKnowledge:
    """What the operator knows of the scene's fixed geometry.

    ``obstacles``: the virtual obstacles' (centre (3,), radius) in m; ``bin_low_m`` and
    ``bin_high_m``: the bin's bounding box relative to its origin (None: no bin known);
    ``influence_m``: the controller's obstacle influence distance; ``rest_z_m``: the
    height (world z, m) of each movable object's origin where the scene places it, at
    rest (name -> z; an object not listed: unknown).
    """

    obstacles: tuple[tuple[tuple[float, float, float], float], ...] = ()
    bin_low_m: tuple[float, float, float] | None = None
    bin_high_m: tuple[float, float, float] | None = None
    influence_m: float = 0.0
    rest_z_m: Mapping[str, float] = field(default_factory=dict)

    @classmethod
    def from_config(cls, config: Config) -> SceneKnowledge:
        """Read the obstacles and the bin from the scene file, placed as ``config.scene``
        places them (the plant's own model and overrides)."""
        model = mujoco.MjModel.from_xml_path(str(config.robot.scene_path))
        apply_scene_overrides(model, config.scene, config.robot)
        return cls.from_model(model, config)

    @classmethod
    def from_model(cls, model: mujoco.MjModel, config: Config) -> SceneKnowledge:
        """Read the obstacles and the bin from ``model``, a compiled scene whose objects
        are already placed (e.g. by :func:`apply_scene_overrides`)."""
        obstacles = tuple(
            (tuple(float(v) for v in model.geom_pos[g]), float(model.geom_rbound[g]))
            for g in obstacle_geoms(model, config.robot.obstacle_prefix)
        )
        bin_body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, BIN_BODY)
        low = high = None
        if bin_body >= 0:
            geoms = np.flatnonzero(model.geom_bodyid == bin_body)
            centres, half = model.geom_pos[geoms], model.geom_size[geoms]  # boxes, body frame
            low = tuple(float(v) for v in (centres - half).min(axis=0))
            high = tuple(float(v) for v in (centres + half).max(axis=0))
        rest_z = {}
        for name in config.robot.object_bodies:
            body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
            if body >= 0:
                rest_z[name] = float(model.body_pos[body][2])
        return cls(obstacles, low, high, config.teleop.obstacle_influence_m, rest_z)

    def in_bin(self, p_m: np.ndarray, bin_p_m: np.ndarray | None) -> bool:
        """Whether point ``p_m`` lies within the bin's walls seen from above (the bin's
        origin at ``bin_p_m``; False when no bin is known or seen)."""
        if bin_p_m is None or self.bin_low_m is None or self.bin_high_m is None:
            return False
        low = np.asarray(bin_p_m)[:2] + np.asarray(self.bin_low_m)[:2]
        high = np.asarray(bin_p_m)[:2] + np.asarray(self.bin_high_m)[:2]
        xy = np.asarray(p_m)[:2]
        return bool(np.all(xy > low) and np.all(xy < high))

    def keep_outs(self, bin_p_m: np.ndarray | None, holding: bool) -> list[KeepOut]:
        """The volumes the tool point keeps out of, with the bin at ``bin_p_m`` (its
        observed origin; None: no bin) and ``holding`` an object under the tool."""
        volumes = [
            KeepOut.sphere(f"obstacle {i}", np.array(c), r + self.influence_m + TOOL_CLEARANCE_M)
            for i, (c, r) in enumerate(self.obstacles)
        ]
        if bin_p_m is not None and self.bin_low_m is not None and self.bin_high_m is not None:
            below = FINGERTIP_DROP_M + (2 * HELD_HALF_HEIGHT_M if holding else 0.0)
            grow = np.array([BIN_MARGIN_M, BIN_MARGIN_M, BIN_MARGIN_M + below])
            low = np.asarray(bin_p_m) + self.bin_low_m - grow * np.array([1, 1, 0])
            # The box reaches down to the table: the tool never passes under the bin.
            low[2] = -math.inf
            volumes.append(KeepOut("bin", low, np.asarray(bin_p_m) + self.bin_high_m + grow))
        return volumes


def _clear(points: Sequence[np.ndarray], volumes: Sequence[KeepOut]) -> bool:
    return not any(v.meets(a, b) for a, b in itertools.pairwise(points) for v in volumes)


def _over(start: np.ndarray, target: np.ndarray, blocking: Sequence[KeepOut],
          volumes: Sequence[KeepOut]) -> list[np.ndarray] | None:  # fmt: skip
    """Up, across and down at a height above every volume met; None if too high."""
    z_m = max(v.top_m for v in blocking) + OVER_MARGIN_M
    for _ in range(OVER_ROUNDS):
        if z_m > MAX_ROUTE_HEIGHT_M:
            return None
        waypoints = []
        if start[2] < z_m:
            waypoints.append(np.array([start[0], start[1], z_m]))
        if target[2] < z_m:
            waypoints.append(np.array([target[0], target[1], z_m]))
        points = [start, *waypoints, target]
        met = [v for v in volumes for a, b in itertools.pairwise(points) if v.meets(a, b)]
        if not met:
            return waypoints
        z_m = max(z_m, *(v.top_m + OVER_MARGIN_M for v in met))
    return None


def _around(start: np.ndarray, target: np.ndarray, blocking: KeepOut,
            volumes: Sequence[KeepOut]) -> list[np.ndarray] | None:  # fmt: skip
    """One waypoint beside a blocking sphere, at the move's height there; the side
    toward the base axis first (the arm's links then stay on the near side)."""
    d = target - start
    across = np.array([-d[1], d[0], 0.0])
    if float(np.linalg.norm(across)) < TINY_M:
        return None  # a vertical move: over or nothing
    across /= np.linalg.norm(across)
    centre = blocking.low_m
    u = min(1.0, max(0.0, float((centre - start) @ d) / float(d @ d)))
    height = start[2] + u * d[2]
    toward_base = -1.0 if float(centre[:2] @ across[:2]) > 0 else 1.0
    for factor in AROUND_FACTORS:
        for side in (toward_base, -toward_base):
            w = np.array([*(centre[:2] + side * factor * blocking.radius_m * across[:2]), height])
            if _clear([start, w, target], volumes):
                return [w]
    return None


def plan_route(start_m: np.ndarray, target_m: np.ndarray,
               volumes: Sequence[KeepOut]) -> list[np.ndarray]:  # fmt: skip
    """Waypoints (world, m) to pass through before ``target_m`` on the way from
    ``start_m`` so the tool point stays out of ``volumes``; empty for a clear straight
    move. Volumes that hold the start or the target are left out (the task puts the tool
    there). Over first; around a sphere when over is too high; the straight move when
    neither clears (the operator then finds out, and says so)."""
    start, target = np.asarray(start_m, dtype=float), np.asarray(target_m, dtype=float)
    volumes = [v for v in volumes if not v.contains(start) and not v.contains(target)]
    blocking = [v for v in volumes if v.meets(start, target)]
    if not blocking:
        return []
    route = _over(start, target, blocking, volumes)
    if route is None:
        spheres = [v for v in blocking if v.radius_m > 0]
        route = _around(start, target, spheres[0], volumes) if spheres else None
    return route or []


def route_length_m(start_m: np.ndarray, waypoints: Sequence[np.ndarray],
                   target_m: np.ndarray) -> float:  # fmt: skip
    """Length (m) of the polyline start -> waypoints -> target."""
    points = [np.asarray(start_m), *waypoints, np.asarray(target_m)]
    return float(sum(np.linalg.norm(b - a) for a, b in itertools.pairwise(points)))
