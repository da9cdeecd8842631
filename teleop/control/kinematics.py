"""Kinematics and dynamics of the arm, computed by Pinocchio from the scene MJCF.

The controller's model is built from the SAME file as the MuJoCo plant
(``pinocchio.buildModelFromMJCF``); the gripper's finger joints are locked, which
leaves the serial arm chain with the fingers' mass lumped into the gripper link.

Model/data split: :func:`build_arm_model` runs once; everything else is a pure
function of ``(arm, q, ...)`` that writes only into ``arm.data`` scratch space.
All vectors are in the world frame (z up, origin at the arm base); ``q_rad`` and
``qd_rad_s`` are in the order of ``RobotConfig.arm_joints``.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
import pinocchio as pin

from teleop.core.config import ModelError, RobotConfig


@dataclass(frozen=True)
class ServoParameters:
    """The arm's low-level velocity loops, read from the MJCF actuators and joints.

    The plant obeys M0 q'' + c0(q, q') + g0(q) = kv (q'_ref - q') - damping q', the
    paper's model M q'' + C q' + g = q'_ref scaled by H = diag(kv).
    """

    kv_nms_per_rad: np.ndarray  # (n,) velocity-loop gain of each joint
    damping_nms_per_rad: np.ndarray  # (n,) joint viscous damping
    max_speed_rad_s: np.ndarray  # (n,) actuator ctrlrange bound on q'_ref


@dataclass
class ArmModel:
    """Pinocchio model and scratch data of the arm chain, plus its servo parameters."""

    model: pin.Model
    data: pin.Data
    tool_frame_id: int
    joint_names: tuple[str, ...]
    servo: ServoParameters

    @property
    def n_joints(self) -> int:
        return self.model.nv


def _servo_parameters(robot: RobotConfig) -> ServoParameters:
    """Read kv, damping and speed limits from the MJCF through MuJoCo's compiled model."""
    mj = mujoco.MjModel.from_xml_path(str(robot.scene_path))
    kv, damping, speed = [], [], []
    for joint_name, actuator_name in zip(robot.arm_joints, robot.arm_actuators, strict=True):
        joint_id = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_JOINT, joint_name)
        actuator_id = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_ACTUATOR, actuator_name)
        if joint_id < 0 or actuator_id < 0:
            raise ModelError(
                f"{robot.scene_path}: no joint {joint_name!r} or actuator {actuator_name!r}"
            )
        if mj.actuator_trnid[actuator_id, 0] != joint_id:
            raise ModelError(f"actuator {actuator_name!r} does not drive joint {joint_name!r}")
        # A MuJoCo velocity actuator has gain kv on ctrl and bias -kv on the joint velocity.
        gain = float(mj.actuator_gainprm[actuator_id, 0])
        if gain <= 0 or not np.isclose(mj.actuator_biasprm[actuator_id, 2], -gain):
            raise ModelError(f"actuator {actuator_name!r} is not a velocity actuator")
        kv.append(gain)
        damping.append(float(mj.dof_damping[mj.jnt_dofadr[joint_id]]))
        limited = mj.actuator_ctrllimited[actuator_id]
        speed.append(float(mj.actuator_ctrlrange[actuator_id, 1]) if limited else np.inf)
    return ServoParameters(np.array(kv), np.array(damping), np.array(speed))


def build_arm_model(robot: RobotConfig) -> ArmModel:
    """Build the reduced Pinocchio model of the arm chain from the scene file.

    Every joint that is not in ``robot.arm_joints`` (fingers) is locked at its
    neutral position. Raises :class:`ModelError` when a configured name is missing or
    the arm joints are not the model's chain in the configured order.
    """
    path = robot.scene_path
    if not path.exists():
        raise ModelError(f"scene file not found: {path}")
    full = pin.buildModelFromMJCF(str(path))
    full_names = [full.names[i] for i in range(1, full.njoints)]
    missing = [name for name in robot.arm_joints if name not in full_names]
    if missing:
        raise ModelError(f"{path}: Pinocchio model has no joint(s) {missing}; has {full_names}")
    lock = [full.getJointId(name) for name in full_names if name not in robot.arm_joints]
    model = pin.buildReducedModel(full, lock, pin.neutral(full)) if lock else full
    names = tuple(model.names[i] for i in range(1, model.njoints))
    if names != tuple(robot.arm_joints):
        raise ModelError(f"arm joints in the model are {names}, config lists {robot.arm_joints}")
    for i in range(1, model.njoints):
        if model.joints[i].nq != 1 or "R" not in model.joints[i].shortname():
            raise ModelError(
                f"joint {model.names[i]!r}: only 1-DOF revolute arm joints are supported"
            )
    if not model.existFrame(robot.tool_site):
        raise ModelError(f"{path}: no site/frame {robot.tool_site!r} for the tool point")
    return ArmModel(
        model=model,
        data=model.createData(),
        tool_frame_id=model.getFrameId(robot.tool_site),
        joint_names=names,
        servo=_servo_parameters(robot),
    )


def tool_position_and_jacobian(arm: ArmModel, q_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tool-point position world_p_tool (3,) in m and its Jacobian (6, n).

    The Jacobian is Pinocchio's LOCAL_WORLD_ALIGNED frame Jacobian: rows 0-2 map joint
    rates to the tool point's linear velocity (m/s), rows 3-5 to angular velocity, both
    in world axes.
    """
    pin.computeJointJacobians(arm.model, arm.data, q_rad)
    pin.updateFramePlacements(arm.model, arm.data)
    position = arm.data.oMf[arm.tool_frame_id].translation.copy()
    jacobian = pin.getFrameJacobian(
        arm.model, arm.data, arm.tool_frame_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
    )
    return position, jacobian


def tool_jacobian(arm: ArmModel, q_rad: np.ndarray) -> np.ndarray:
    """The (6, n) tool Jacobian of :func:`tool_position_and_jacobian` alone.

    For look-aheads that need no pose: the frame Jacobian is built from the joint
    placements, so the frame placements are not updated (one Pinocchio pass less).
    """
    pin.computeJointJacobians(arm.model, arm.data, q_rad)
    return pin.getFrameJacobian(
        arm.model, arm.data, arm.tool_frame_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
    )


def tool_pose_and_jacobian(
    arm: ArmModel, q_rad: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """world_p_tool (3,) in m, world_R_tool (3, 3) and the Jacobian (6, n) of
    :func:`tool_position_and_jacobian`, for the 1 kHz teleoperation cycle.

    Leaves the joint Jacobians at ``q_rad`` in ``arm.data`` but updates only the tool
    frame's placement: updating every frame and reading ``data.oMf`` back costs more.
    """
    pin.computeJointJacobians(arm.model, arm.data, q_rad)
    world_T_tool = pin.updateFramePlacement(arm.model, arm.data, arm.tool_frame_id)
    jacobian = pin.getFrameJacobian(
        arm.model, arm.data, arm.tool_frame_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
    )
    return world_T_tool.translation.copy(), world_T_tool.rotation.copy(), jacobian


def manipulability(jacobian_position: np.ndarray) -> float:
    """Yoshikawa's measure w = sqrt(det(J J^T)) of the (3, n) position Jacobian."""
    det = np.linalg.det(jacobian_position @ jacobian_position.T)
    return float(np.sqrt(max(det, 0.0)))


def manipulability_and_gradient(jacobian: np.ndarray) -> tuple[float, list[float]]:
    """w = sqrt(det(Jv Jv^T)) and its gradient dw/dq (n floats), exact for revolute chains.

    For a revolute chain with joint axes z_i (angular rows) and position columns v_i,
    dv_i/dq_k = z_k x v_i when k <= i and z_i x v_k when k > i, and
    dw/dq_k = w sum_i a_i . dv_i/dq_k with a_i the columns of (J J^T)^-1 J. The
    triple product turns the sums into prefix/suffix sums, O(n) instead of O(n^2):
    dw/dq_k = w (z_k . sum_{i>=k} v_i x a_i + v_k . sum_{i<k} a_i x z_i).

    Scalar Python on purpose: it runs every 1 kHz cycle, and at n = 6 or 7 the twenty
    or so small numpy calls of the vectorised form cost more than the arithmetic
    (tests/benchmarks/teleop_control_cost.py measures the cycle).
    """
    vx, vy, vz, zx, zy, zz = jacobian.tolist()
    n = len(vx)
    # J J^T = [[a, b, c], [b, e, f], [c, f, i]] and its adjugate (cofactors).
    (c00, c01, c02, c11, c12, c22), det = _symmetric_adjugate(
        _dot(vx, vx), _dot(vx, vy), _dot(vx, vz), _dot(vy, vy), _dot(vy, vz), _dot(vz, vz)
    )
    if det <= 0.0:
        return 0.0, [0.0] * n
    w = math.sqrt(det)
    v_cross_a, a_cross_z = [], []
    for k in range(n):
        px, py, pz, ux, uy, uz = vx[k], vy[k], vz[k], zx[k], zy[k], zz[k]
        ax = (c00 * px + c01 * py + c02 * pz) / det
        ay = (c01 * px + c11 * py + c12 * pz) / det
        az = (c02 * px + c12 * py + c22 * pz) / det
        v_cross_a.append((py * az - pz * ay, pz * ax - px * az, px * ay - py * ax))
        a_cross_z.append((ay * uz - az * uy, az * ux - ax * uz, ax * uy - ay * ux))
    gradient = [0.0] * n
    sx = sy = sz = 0.0  # prefix sum of a_i x z_i over i < k
    for k in range(n):
        gradient[k] = vx[k] * sx + vy[k] * sy + vz[k] * sz
        dx, dy, dz = a_cross_z[k]
        sx, sy, sz = sx + dx, sy + dy, sz + dz
    sx = sy = sz = 0.0  # suffix sum of v_i x a_i over i >= k
    for k in range(n - 1, -1, -1):
        dx, dy, dz = v_cross_a[k]
        sx, sy, sz = sx + dx, sy + dy, sz + dz
        gradient[k] = w * (gradient[k] + zx[k] * sx + zy[k] * sy + zz[k] * sz)
    return w, gradient


def _dot(x: list[float], y: list[float]) -> float:
    # map(mul) adds the same products in the same order as a generator, bit for bit, at
    # about half its cost (no generator frame per term).
    return sum(map(operator.mul, x, y))


def damped_least_squares(
    rows: Sequence[Sequence[float]],
    damping_sq: float,
    v_task: Sequence[float],
    objective: Sequence[float],
) -> list[float] | None:
    """q' = J# (v - J g) + g with J# = J^T (J J^T + lambda^2 I)^-1, in Python floats.

    ``rows``: the three rows of the (3, n) position Jacobian J; ``damping_sq``: lambda^2
    (m^2); ``v_task``: the task velocity v (3,) in m/s; ``objective``: the null-space
    joint rates g (n,) in rad/s. The minimum-norm motion that achieves v, plus g
    projected onto J's null space. J J^T + lambda^2 I is inverted by its adjugate: at
    this size the closed form in floats costs a fraction of ``np.linalg.solve`` and of
    the numpy calls on 3-vectors around it. None when that matrix is singular (no
    damping at an exact singularity): the caller takes the least-squares solution.
    """
    vx, vy, vz = rows
    (c00, c01, c02, c11, c12, c22), det = _symmetric_adjugate(
        _dot(vx, vx) + damping_sq,
        _dot(vx, vy),
        _dot(vx, vz),
        _dot(vy, vy) + damping_sq,
        _dot(vy, vz),
        _dot(vz, vz) + damping_sq,
    )
    if det <= 0.0:
        return None
    # r = v - J g, then y = A^-1 r, then q' = J^T y + g.
    rx = v_task[0] - _dot(vx, objective)
    ry = v_task[1] - _dot(vy, objective)
    rz = v_task[2] - _dot(vz, objective)
    yx = (c00 * rx + c01 * ry + c02 * rz) / det
    yy = (c01 * rx + c11 * ry + c12 * rz) / det
    yz = (c02 * rx + c12 * ry + c22 * rz) / det
    return [a * yx + b * yy + c * yz + g for a, b, c, g in zip(vx, vy, vz, objective, strict=True)]


def _symmetric_adjugate(
    a: float, b: float, c: float, e: float, f: float, i: float
) -> tuple[tuple[float, float, float, float, float, float], float]:
    """Upper cofactors (c00, c01, c02, c11, c12, c22) and determinant of the symmetric
    matrix [[a, b, c], [b, e, f], [c, f, i]] (its adjugate is symmetric too)."""
    c00, c01, c02 = e * i - f * f, c * f - b * i, b * f - c * e
    c11, c12, c22 = a * i - c * c, b * c - a * f, a * e - b * b
    return (c00, c01, c02, c11, c12, c22), a * c00 + b * c01 + c * c02


def mass_matrix_and_bias(
    arm: ArmModel, q_rad: np.ndarray, qd_rad_s: np.ndarray
) -> tuple[list[list[float]], list[float]]:
    """``(M0(q) rows (n x n) in kg m^2, c0(q, q') + g0(q) (n) in N m)`` as floats: the
    inverse dynamics M0 q'' + c0 + g0 split into its joint-state terms, for a q'' known
    later. M0 includes the rotor armature read from the MJCF."""
    # Pinocchio 4.1's crba fills both triangles (older ones the upper one only; the test
    # against MuJoCo's full mass matrix would catch a half-filled one).
    mass = pin.crba(arm.model, arm.data, q_rad).tolist()
    return mass, pin.nonLinearEffects(arm.model, arm.data, q_rad, qd_rad_s).tolist()


def joint_space_dynamics(
    arm: ArmModel, q_rad: np.ndarray, qd_rad_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rigid-body terms of M0(q) q'' + c0(q, q') + g0(q) = tau (SI units).

    Returns ``(M0 (n, n) in kg m^2, c0 = C0(q, q') q' (n,) in N m, g0 (n,) in N m)``.
    M0 includes the rotor armature read from the MJCF.
    """
    mass, bias = mass_matrix_and_bias(arm, q_rad, qd_rad_s)
    gravity = pin.computeGeneralizedGravity(arm.model, arm.data, q_rad).copy()
    return np.array(mass), np.array(bias) - gravity, gravity


def point_jacobian_along(
    arm: ArmModel, frame_id: int, world_p_m: np.ndarray, world_n: np.ndarray
) -> np.ndarray:
    """Row (n,) mapping joint rates to the speed (m/s) of a point along a direction.

    The point ``world_p_m`` is rigidly attached to the Pinocchio frame ``frame_id``; its
    velocity is the frame's v_o + w x r with r = p - o, so along the unit ``world_n``
    it is n^T Jv - (n x r)^T Jw. Reads the joint Jacobians that
    :func:`tool_pose_and_jacobian` (or :func:`tool_position_and_jacobian`)
    left in ``arm.data``: call it first, at the same q. Updates the frame's placement.
    """
    frame_jacobian = pin.getFrameJacobian(
        arm.model, arm.data, frame_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
    )
    px, py, pz = np.asarray(world_p_m, dtype=float).tolist()
    ox, oy, oz = pin.updateFramePlacement(arm.model, arm.data, frame_id).translation.tolist()
    rx, ry, rz = px - ox, py - oy, pz - oz
    nx, ny, nz = np.asarray(world_n, dtype=float).tolist()
    # One (6,) row times the (6, n) Jacobian: [n, -(n x r)] . [Jv; Jw].
    row = (nx, ny, nz, nz * ry - ny * rz, nx * rz - nz * rx, ny * rx - nx * ry)
    return np.array(row) @ frame_jacobian
