"""Clearance of the arm and gripper, every control cycle: how close each link is to the
scene and to the other links, and the joint-space rows that say how fast it closes in.

The geometry is the scene file's own, compiled by MuJoCo (the plant's model file; the
same scene overrides): distances and closest points come from MuJoCo's narrow phase
(``mj_geomDistance``) between

- the arm's collision geoms (:func:`teleop.sim.proximity.arm_collision_geoms`: the arm
  chain and the gripper) and every collision geom welded to the world (table, floor, the
  arm's fixed base, the bin): kind SCENE, or FINGER for the finger geoms, which a top
  grasp brings a few millimetres from the table;
- pairs of arm links two or more arm joints apart (adjacent links touch by design) that
  can come within ``clearance.self_slowdown_m`` of each other somewhere in the joint
  range (sampled once at start-up, MoveIt's "never in collision" rule): kind SELF.

Free bodies (the cube) are not obstacles: the fingers are meant to touch them. Virtual
obstacles (no contype) are the plant's :class:`teleop.sim.proximity.ObstacleProximity`.

Cost: each MuJoCo call from Python pays the binding's overhead, and the arm's geoms
against the scene's plus the self pairs are many (about 80 in the shipped scene). A broad
phase in one numpy pass (bounding spheres of the arm geoms against the scene geoms' world
boxes and each other) keeps only the pairs whose lower bound is within
``clearance.influence_m``; only those reach ``mj_geomDistance``.
tests/benchmarks/clearance_cost.py measures the cycle with and without it.

Everything is in the world frame (z up, origin at the arm base), in metres.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import mujoco
import numpy as np
import pinocchio as pin

from teleop.control.kinematics import ArmModel, point_jacobian_along
from teleop.core.config import ClearanceConfig, Config, ModelError, RobotConfig
from teleop.sim.contact import finger_bodies
from teleop.sim.proximity import apply_scene_overrides, arm_collision_geoms

# Self pairs: random joint configurations sampled at start-up to find the pairs of links
# that can come close, and the generator's fixed seed (the same pairs every run).
SELF_PAIR_SAMPLES = 400
SELF_PAIR_SEED = 0
# Witness points closer than this (m) give no direction; the geoms' centres do.
MIN_DIRECTION_LENGTH_M = 1e-9
# Extent (m) standing in for "unbounded" in a plane's world box.
PLANE_EXTENT_M = 1.0e3


class PairKind(enum.IntEnum):
    """What a pair is, which sets its thresholds (ClearanceConfig)."""

    SCENE = 0  # an arm or palm geom vs a static geom of the scene
    FINGER = 1  # a finger geom vs a static geom of the scene
    SELF = 2  # two arm links two or more joints apart


@dataclass(frozen=True)
class ClearancePair:
    """One close pair, world frame.

    ``world_n_away`` is the unit direction in which moving the arm point increases the
    distance (from the other point towards the arm point). For a SELF pair the other
    point is on the arm too (``other_frame`` >= 0): both move.
    """

    kind: PairKind
    distance_m: float  # signed: negative when the geoms overlap
    world_p_arm_m: np.ndarray  # (3,)
    world_p_other_m: np.ndarray  # (3,)
    world_n_away: np.ndarray  # (3,) unit
    arm_geom: int  # MuJoCo geom ids
    other_geom: int
    arm_frame: int  # Pinocchio frame ids of the bodies holding the points (-1: static)
    other_frame: int


@dataclass(frozen=True)
class Clearance:
    """One cycle's clearance: the pairs within their kind's slowdown distance (the ones
    the control law acts on) and the smallest distance of each kind over every pair
    within ``influence_m`` (``influence_m`` when none is closer)."""

    pairs: tuple[ClearancePair, ...]
    min_scene_m: float
    min_finger_m: float
    min_self_m: float

    @property
    def min_m(self) -> float:
        """Smallest distance over every kind (m)."""
        return min(self.min_scene_m, self.min_finger_m, self.min_self_m)

    @property
    def in_contact(self) -> bool:
        """Whether any pair touches or overlaps (an unintended contact)."""
        return self.min_m <= 0.0


def thresholds_m(config: ClearanceConfig, kind: PairKind) -> tuple[float, float]:
    """``(stop, slowdown)`` distances (m) of a pair kind."""
    if kind == PairKind.FINGER:
        return config.finger_stop_m, config.finger_slowdown_m
    if kind == PairKind.SELF:
        return config.self_stop_m, config.self_slowdown_m
    return config.stop_m, config.slowdown_m


def push_depth_m(config: ClearanceConfig, kind: PairKind, distance_m: float) -> float:
    """How deep (m) a pair counts as inside its slowdown zone for the null-space push:
    quadratic from the slowdown distance to the stop distance, then the depth itself.

    The push's rate is then zero with a zero slope where a pair enters the zone, so a
    link crossing into it does not step the null-space motion (a step the velocity loops
    track with a lag, which shows as a path error); at the stop distance it is as strong
    as the linear depth."""
    stop, slowdown = thresholds_m(config, kind)
    depth = slowdown - distance_m
    if depth <= 0.0:
        return 0.0
    return depth * min(depth / (slowdown - stop), 1.0)


def allowed_approach_m_s(
    config: ClearanceConfig, kind: PairKind, distance_m: float, closing_m_s: float = 0.0
) -> float:
    """Largest speed (m/s) at which a pair may close in: ``approach_speed_m_s`` at the
    slowdown distance and beyond, falling linearly to 0 at the stop distance, and on
    below it, negative: a pair inside its stop distance must open, at up to
    ``approach_speed_m_s``.

    The negative part restores the margin: the joints track a command with a small error
    (1 % of a wrist turning at 2 rad/s moves a finger millimetres per second), and
    without it a pair held at its stop distance by a zero cap drifts inside (a finger
    crept 1.1 mm past the shoulder's 5 mm stop over 0.3 s in a grasp), and a 6-DOF arm
    under a 6D task has no null space to push it back with.

    The distance counted is the one ``approach_lookahead_s`` ahead at the pair's measured
    closing speed ``closing_m_s`` (positive: closing in; opening counts as 0): the joints
    reach a command after a lag, and a pair that enters its slowdown zone fast would
    coast that lag's travel past its stop distance; on the distance ahead it brakes in
    time."""
    stop, slowdown = thresholds_m(config, kind)
    ahead_m = distance_m - config.approach_lookahead_s * max(closing_m_s, 0.0)
    fraction = (ahead_m - stop) / (slowdown - stop)
    return config.approach_speed_m_s * min(max(fraction, -1.0), 1.0)


@dataclass(frozen=True)
class ClosePair:
    """A pair inside its slowdown distance, with what both control laws make of it."""

    pair: ClearancePair
    row: np.ndarray  # (n,) approach row j: d' = j q' (approach_row)
    inside_m: float  # how far inside its slowdown distance (m, > 0)
    push_depth_m: float  # that depth as the null-space push counts it (push_depth_m)
    cap_m_s: float  # its allowed approach speed at its measured closing speed


def close_pairs(
    config: ClearanceConfig, arm: ArmModel, clearance: Clearance, qd_rad_s: np.ndarray
) -> list[ClosePair]:
    """The pairs of ``clearance`` inside their slowdown distance, in its order: each with
    its approach row at the q whose joint Jacobians ``arm.data`` holds (call a
    tool-Jacobian function first), its push depth, and its approach cap at the closing
    speed -row q' measured from ``qd_rad_s``."""
    close = []
    for pair in clearance.pairs:
        _, slowdown = thresholds_m(config, pair.kind)
        inside_m = slowdown - pair.distance_m
        if inside_m <= 0.0:
            continue
        row = approach_row(arm, pair)
        closing_m_s = -float(row @ qd_rad_s)
        close.append(
            ClosePair(
                pair,
                row,
                inside_m,
                push_depth_m(config, pair.kind, pair.distance_m),
                allowed_approach_m_s(config, pair.kind, pair.distance_m, closing_m_s),
            )
        )
    return close


class ClearanceModel:
    """The scene file compiled for distance queries, and the pairs to query.

    Owns its MuJoCo model and data (the controller's, not the plant's): :meth:`measure`
    poses the arm kinematically at the measured joint state and writes only there.
    ``arm`` maps MuJoCo bodies to Pinocchio frames of the same name (the bodies of the
    arm chain, the gripper and its fingers).
    """

    def __init__(self, config: Config, arm: ArmModel) -> None:
        robot = config.robot
        self.config = config.clearance
        self.model = mujoco.MjModel.from_xml_path(str(robot.scene_path))
        apply_scene_overrides(self.model, config.scene, robot)
        self.data = mujoco.MjData(self.model)
        joints = self._index_joints(robot)
        link = _link_index(self.model, set(joints))
        scene_arm_geoms = self._sort_geoms(robot, arm, link)
        self._scene_lo, self._scene_hi = self._scene_boxes()
        body = self.model.geom_bodyid
        candidates = [
            (a, b)
            for i, a in enumerate(self.arm_geoms)
            for b in self.arm_geoms[i + 1 :]
            if abs(link[int(body[a])] - link[int(body[b])]) >= 2
        ]
        self.self_pairs = self._reachable_pairs(candidates, self.config.self_slowdown_m)
        self._prepare_broad_phase(scene_arm_geoms)
        self._fromto = np.zeros(6)
        self.queries = 0  # mj_geomDistance calls (cost accounting)

    def _index_joints(self, robot: RobotConfig) -> list[int]:
        """The arm's joint ids; where the arm's and the fingers' positions are in qpos, and
        each finger's open slide (m)."""
        model = self.model
        joints = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n) for n in robot.arm_joints]
        if min(joints) < 0:
            raise ModelError(f"{robot.scene_path}: arm joints {robot.arm_joints} not all found")
        self._qpos_index = [int(model.jnt_qposadr[j]) for j in joints]
        contiguous = self._qpos_index == list(range(self._qpos_index[0], self._qpos_index[-1] + 1))
        self._qpos_at = (
            slice(self._qpos_index[0], self._qpos_index[-1] + 1) if contiguous else self._qpos_index
        )
        finger_joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, robot.gripper_joints[0])
        self.open_m = float(model.jnt_range[finger_joint][1])  # each finger's slide, open
        self._finger_qpos_index = [
            int(model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)])
            for n in robot.gripper_joints
        ]
        return joints

    def _sort_geoms(self, robot: RobotConfig, arm: ArmModel, link: dict[int, int]) -> list[int]:
        """The arm's collision geoms (each with its Pinocchio frame), the static scene's,
        and the arm geoms that meet the scene (returned), each a finger's or not."""
        model = self.model
        self.arm_geoms = arm_collision_geoms(model, robot)
        arm_set = set(self.arm_geoms)
        self.scene_geoms = [
            g
            for g in range(model.ngeom)
            if g not in arm_set
            and (model.geom_contype[g] or model.geom_conaffinity[g])
            and model.body_weldid[model.geom_bodyid[g]] == 0
        ]
        # The scene is link 0: the first link only turns on its base, at a fixed distance
        # from it and from everything around the base's axis (adjacent links, as below).
        scene_arm_geoms = [g for g in self.arm_geoms if link[int(model.geom_bodyid[g])] >= 2]
        self._frames = {}
        for g in self.arm_geoms:
            body = int(model.geom_bodyid[g])
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body) or ""
            if not arm.model.existFrame(name, pin.FrameType.BODY):
                raise ModelError(f"arm body {name!r} has no Pinocchio frame")
            self._frames[g] = arm.model.getFrameId(name, pin.FrameType.BODY)
        fingers = finger_bodies(model, robot)
        finger_geoms = {g for g in self.arm_geoms if int(model.geom_bodyid[g]) in fingers}
        self._scene_kinds = [
            PairKind.FINGER if g in finger_geoms else PairKind.SCENE for g in scene_arm_geoms
        ]
        return scene_arm_geoms

    def _prepare_broad_phase(self, scene_arm_geoms: list[int]) -> None:
        """The broad phase's index arrays and squared reach (cutoff + bounding radii)."""
        model = self.model
        cutoff = self.config.influence_m
        self._arm_index = np.array(scene_arm_geoms, dtype=int)
        self._scene_arm_list = scene_arm_geoms
        self._slowdown_m = [thresholds_m(self.config, kind)[1] for kind in PairKind]
        self._scene_reach_sq = ((cutoff + model.geom_rbound[self._arm_index]) ** 2)[:, None]
        self._self_a = np.array([a for a, _ in self.self_pairs], dtype=int)
        self._self_b = np.array([b for _, b in self.self_pairs], dtype=int)
        self._self_a_list, self._self_b_list = self._self_a.tolist(), self._self_b.tolist()
        self._self_reach_sq = (
            cutoff + model.geom_rbound[self._self_a] + model.geom_rbound[self._self_b]
        ) ** 2

    def _scene_boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """World boxes (lo, hi), each (m, 3), of the static scene geoms: they never move,
        so one mj_kinematics at start-up places them. A plane is the half-space below it."""
        model, data = self.model, self.data
        mujoco.mj_kinematics(model, data)
        lo, hi = [], []
        for g in self.scene_geoms:
            rotation = data.geom_xmat[g].reshape(3, 3)
            if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:
                if not np.allclose(rotation[:, 2], (0.0, 0.0, 1.0)):
                    raise ModelError("only horizontal planes are supported as scene geoms")
                top = float(data.geom_xpos[g][2])
                lo.append((-PLANE_EXTENT_M, -PLANE_EXTENT_M, top - PLANE_EXTENT_M))
                hi.append((PLANE_EXTENT_M, PLANE_EXTENT_M, top))
                continue
            centre_local, half_local = model.geom_aabb[g][:3], model.geom_aabb[g][3:]
            centre = data.geom_xpos[g] + rotation @ centre_local
            half = np.abs(rotation) @ half_local
            lo.append(centre - half)
            hi.append(centre + half)
        return np.array(lo), np.array(hi)

    def _reachable_pairs(
        self, candidates: list[tuple[int, int]], within_m: float
    ) -> list[tuple[int, int]]:
        """The candidate pairs that come within ``within_m`` in some sampled configuration
        (uniform over each arm joint's range, or +-pi when unlimited)."""
        model, data = self.model, self.data
        rng = np.random.default_rng(SELF_PAIR_SEED)
        low, high = [], []
        for adr in self._qpos_index:
            joint = int(np.flatnonzero(model.jnt_qposadr == adr)[0])
            limited = model.jnt_limited[joint]
            lo, hi = model.jnt_range[joint] if limited else (-math.pi, math.pi)
            low.append(max(lo, -math.pi))
            high.append(min(hi, math.pi))
        near: set[tuple[int, int]] = set()
        for _ in range(SELF_PAIR_SAMPLES):
            data.qpos[self._qpos_index] = rng.uniform(low, high)
            mujoco.mj_kinematics(model, data)
            for a, b in candidates:
                if (a, b) not in near:
                    if mujoco.mj_geomDistance(model, data, a, b, within_m, None) < within_m:
                        near.add((a, b))
        return [pair for pair in candidates if pair in near]

    def measure(self, q_rad: np.ndarray, gripper_opening_m: float) -> Clearance:
        """The clearance at joint positions ``q_rad`` (n,) and the finger opening (m,
        each finger's slide)."""
        model, data, cfg = self.model, self.data, self.config
        cutoff = cfg.influence_m
        data.qpos[self._qpos_at] = q_rad
        data.qpos[self._finger_qpos_index] = gripper_opening_m
        mujoco.mj_kinematics(model, data)
        # Broad phase: each arm geom's bounding sphere against each scene geom's world box
        # and against the other link of its self pairs; a pair goes to the narrow phase
        # when the bound is within the cutoff. Squared distances, few numpy calls.
        centres = data.geom_xpos[self._arm_index]
        gap = np.maximum(self._scene_lo - centres[:, None, :], centres[:, None, :] - self._scene_hi)
        np.maximum(gap, 0.0, out=gap)
        near = np.einsum("ijk,ijk->ij", gap, gap) < self._scene_reach_sq
        arm_index, scene_index = np.nonzero(near)
        # Narrow phase: every distance counts for the minima; a pair becomes a
        # ClearancePair (points, direction: what the law needs) only inside its kind's
        # slowdown distance, where the law acts on it.
        pairs: list[ClearancePair] = []
        mins = [cutoff, cutoff, cutoff]  # by PairKind
        slowdown, fromto, query = self._slowdown_m, self._fromto, mujoco.mj_geomDistance
        arm_geoms, kinds, scene_geoms = self._scene_arm_list, self._scene_kinds, self.scene_geoms
        for i, j in zip(arm_index.tolist(), scene_index.tolist(), strict=True):
            kind, arm_geom, other = kinds[i], arm_geoms[i], scene_geoms[j]
            distance = query(model, data, arm_geom, other, cutoff, fromto)
            if distance < mins[kind]:
                mins[kind] = distance
            if distance < slowdown[kind]:
                pairs.append(self._pair(kind, arm_geom, other, distance))
        self.queries += len(arm_index)
        if self.self_pairs:
            a, b = self._self_a, self._self_b
            gap = data.geom_xpos[a] - data.geom_xpos[b]
            near_self = np.nonzero(np.einsum("ij,ij->i", gap, gap) < self._self_reach_sq)[0]
            kind = PairKind.SELF
            for k in near_self.tolist():
                arm_geom, other = self._self_a_list[k], self._self_b_list[k]
                distance = query(model, data, arm_geom, other, cutoff, fromto)
                if distance < mins[kind]:
                    mins[kind] = distance
                if distance < slowdown[kind]:
                    pairs.append(self._pair(kind, arm_geom, other, distance))
            self.queries += len(near_self)
        return Clearance(
            pairs=tuple(pairs),
            min_scene_m=mins[PairKind.SCENE],
            min_finger_m=mins[PairKind.FINGER],
            min_self_m=mins[PairKind.SELF],
        )

    def _pair(
        self, kind: PairKind, arm_geom: int, other_geom: int, distance: float
    ) -> ClearancePair:
        """The pair whose ``mj_geomDistance`` just wrote its witness points to ``_fromto``."""
        data, fromto = self.data, self._fromto
        p_arm, p_other = fromto[:3].copy(), fromto[3:].copy()
        # fromto runs from the arm geom to the other; overlapping, the witness points
        # cross over, so the sign of the distance orients the direction.
        direction = (p_arm - p_other) * (1.0 if distance >= 0 else -1.0)
        length = math.hypot(*direction.tolist())
        if length < MIN_DIRECTION_LENGTH_M:
            direction = data.geom_xpos[arm_geom] - data.geom_xpos[other_geom]
            length = math.hypot(*direction.tolist())
        n_away = direction / length if length > 0 else np.array([0.0, 0.0, 1.0])
        return ClearancePair(
            kind=kind,
            distance_m=float(distance),
            world_p_arm_m=p_arm,
            world_p_other_m=p_other,
            world_n_away=n_away,
            arm_geom=arm_geom,
            other_geom=other_geom,
            arm_frame=self._frames[arm_geom],
            other_frame=self._frames.get(other_geom, -1) if kind == PairKind.SELF else -1,
        )

    def geom_name(self, geom: int) -> str:
        """A geom's name in the scene file (for events and reports)."""
        return mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_GEOM, geom) or f"geom {geom}"


def _link_index(model: mujoco.MjModel, arm_joints: set[int]) -> dict[int, int]:
    """Body id -> number of arm joints between it and the world (0: world, fixed base,
    free objects; a finger counts as its gripper: finger slides are not arm joints)."""
    index = {}
    for body in range(model.nbody):
        count, b = 0, body
        while b > 0:
            start = int(model.body_jntadr[b])
            count += sum(
                1 for j in range(start, start + int(model.body_jntnum[b])) if j in arm_joints
            )
            b = int(model.body_parentid[b])
        index[body] = count
    return index


def approach_row(arm: ArmModel, pair: ClearancePair) -> np.ndarray:
    """Row j (n,) with d'(distance) = j q' for the pair's witness points, at the q whose
    joint Jacobians ``arm.data`` holds (call a tool-Jacobian function first).

    j = n^T J_arm(p_arm) - n^T J_other(p_other), the second term for SELF pairs only
    (a scene point does not move)."""
    row = point_jacobian_along(arm, pair.arm_frame, pair.world_p_arm_m, pair.world_n_away)
    if pair.other_frame >= 0:
        row = row - point_jacobian_along(
            arm, pair.other_frame, pair.world_p_other_m, pair.world_n_away
        )
    return row
