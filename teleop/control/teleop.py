"""Teleoperation control law (paper experiment 2) with MoveIt-Servo-style safety.

Frames:
    device frame: the haptic handle's axes, x forward (away from the operator), y left,
        z up; ``d_m`` is the handle's offset from the workspace centre (m).
    view frame: the world frame rotated by the HMD yaw about world z, so "forward" on
        the handle is forward where the operator looks. Device and view axes coincide.
    world frame: z up, origin at the arm base (the plant's and Pinocchio's frame).

Rate control: the handle offset commands a tool VELOCITY (not a position), so a 0.1 m
device covers the whole arm workspace. The controller turns it into joint velocity
references for a 6D task: the linear velocity the operator asks for, and an
orientation hold (the 6-DOF arm is redundant for position only; without the hold the
wrist wanders and a top grasp becomes impossible). A small position hold keeps the tool
from drifting when the operator commands nothing. Virtual obstacles push the closest
arm point away. With a :class:`teleop.control.clearance.ClearanceModel` the arm also
keeps clear of the table, the bin and itself: links inside their slowdown distance and
joints near their limits are pushed away in the null space of the 6D task (one dimension
on the 7-DOF arm, none on the 6-DOF one), the speed at which each close pair closes in is
capped to stop at its stop distance (:func:`teleop.control.path.hold_clearance`, the same
rule as path following), and the operator feels both as separate feedback components
(``world_scene_f_n``, ``world_limits_f_n``). Then, like MoveIt Servo, the motion is
slowed down near singularities and joint limits and capped in tool speed, and dynamic
compensation (shared with path following) turns the kinematic command into references
for the velocity loops.

Cost: the law runs once per haptic sample (1 kHz) on the bilateral loop's critical path.
At these sizes (3- and 6-vectors, 3x3 and 6x6 matrices) a numpy call's overhead
outweighs what it computes, so the cycle works on Python floats
between the Pinocchio calls and calls LAPACK directly for the two factorisations
(tests/benchmarks/teleop_control_cost.py measures it against the numpy form).
The part that depends only on the joint state (tool pose and Jacobian, the least
squares' matrix, condition number, measured tool velocity, the dynamic compensation's
terms, the clearance and everything derived from it) is :meth:`TeleopController.prepare`:
the plant state arrives before the handle sample, so a caller can run it ahead and pass
its :class:`JointStateTerms` to ``update``, which is then left with products of floats
(the handle-dependent half runs no numpy, LAPACK or Pinocchio call away from obstacles,
close pairs and singularities).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import operator
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import pinocchio as pin
from scipy.linalg import lapack

from teleop.control.clearance import Clearance, ClearanceModel, PairKind, close_pairs
from teleop.control.kinematics import (
    ArmModel,
    point_jacobian_along,
    tool_jacobian,
    tool_pose_and_jacobian,
)
from teleop.control.path import (
    CompensationTerms,
    clearance_push,
    compensation_terms,
    hold_clearance,
    limit_speed,
    velocity_reference,
)
from teleop.core.config import ControlConfig, TeleopConfig
from teleop.sim.proximity import ProximitySample

# Position hold: servo gain (1/s) towards the integrated desired position, and the
# largest error it acts on (m). The bound keeps the hold from winding up while the
# safety scaling or obstacle avoidance stop the tool: it then pushes at most
# POSITION_HOLD_GAIN_PER_S * POSITION_HOLD_MAX_ERROR_M = 0.05 m/s.
POSITION_HOLD_GAIN_PER_S = 10.0
POSITION_HOLD_MAX_ERROR_M = 0.005
# Below this horizontal length the tool x axis gives no heading (it points up or down).
MIN_HEADING_NORM = 1e-6
# Orientation hold: angular velocity (rad/s) per rad of orientation error.
ORIENTATION_GAIN_PER_S = 10.0
# Adaptive damping of the 6D least squares: below this singular value of the 6xN
# Jacobian (mixed m and rad units, ~1 = well conditioned) the damping grows smoothly
# to SINGULAR_DAMPING, so a wrist or elbow singularity gives bounded joint rates.
SINGULAR_VALUE_THRESHOLD = 0.05
SINGULAR_DAMPING = 0.05
_SINGULAR_VALUE_THRESHOLD_SQUARED = SINGULAR_VALUE_THRESHOLD**2
# Damping of the one-row avoidance pseudo-inverse (m/rad): a point the joints barely move
# (near the base) gets a bounded push instead of huge joint rates.
AVOID_DAMPING_M_PER_RAD = 0.01
# Singularity look-ahead (s): the motion is slowed only if following it for this long
# increases the condition number (moving away from a singularity stays allowed).
SINGULARITY_LOOKAHEAD_S = 0.01
# Acceleration limit of the nominal joint command (rad/s^2): a step of the operator's
# reference would otherwise saturate the wrist drives, whose lag makes the tool overshoot
# the speed cap. Safety scaling acts after it, so stops stay immediate.
MAX_JOINT_ACCEL_RAD_S2 = 10.0
# Rows of the task: tool linear and angular velocity.
TASK_DIMENSION = 6
# Joint limits at or beyond this magnitude (rad) mean "no limit": a joint that can turn a
# full turn each way (the shoulder pan, UR-style wrists) is treated as continuous.
CONTINUOUS_LIMIT_RAD = 2.0 * math.pi - 1e-3
# A close pair or joint whose motion the operator's tool velocity barely drives (m/s per
# m/s, rad/s per m/s) gives no felt direction: no push-back from it.
MIN_FEEDBACK_DIRECTION = 1e-6


def _norm(v: np.ndarray) -> float:
    """Euclidean norm of a 3-vector (np.linalg.norm's overhead outweighs it at this size)."""
    return math.hypot(*v.tolist())


@functools.lru_cache(maxsize=16)
def _identity(size: int, scale: float = 1.0) -> np.ndarray:
    """Read-only ``scale`` I (size, size), for constant scales: built once instead of
    an np.eye and a product per call."""
    identity = scale * np.eye(size)
    identity.flags.writeable = False
    return identity


def position_condition_number(jacobian_position: np.ndarray) -> float:
    """Condition number s_max / s_min of the (3, n) position Jacobian (inf if singular).

    From the eigenvalues of the 3x3 J J^T (the squared singular values), cheaper than
    an SVD of J.
    """
    return _condition_number_of_gram(jacobian_position @ jacobian_position.T)


def _condition_number_of_gram(gram: np.ndarray) -> float:
    """sqrt(l_max / l_min) of a Gram matrix J J^T (inf if singular): the condition number
    of J."""
    return _condition_and_manipulability(gram)[0]


def _condition_and_manipulability(gram: np.ndarray) -> tuple[float, float]:
    """The condition number sqrt(l_max / l_min) of J (inf if singular) and Yoshikawa's
    manipulability sqrt(det(J J^T)), from the eigenvalues of its Gram matrix J J^T.
    LAPACK's dsyevd directly, as np.linalg.eigvalsh does, without its argument checks and
    error-state handling."""
    eigenvalues, _, info = lapack.dsyevd(gram, compute_v=0, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"dsyevd failed (info {info})")
    values = eigenvalues.tolist()
    smallest, largest = values[0], values[-1]
    manipulability = math.sqrt(max(math.prod(values), 0.0))
    if smallest <= 0.0:
        return math.inf, manipulability
    return math.sqrt(largest / smallest), manipulability


def singularity_scale(cond: float, cfg: TeleopConfig) -> float:
    """Speed factor from the position Jacobian's condition number (MoveIt Servo).

    1 below ``singularity_slowdown_cond``, linear down to 0 at ``singularity_stop_cond``.
    """
    low, high = cfg.singularity_slowdown_cond, cfg.singularity_stop_cond
    if not math.isfinite(cond) or cond >= high:
        return 0.0
    if cond <= low:
        return 1.0
    return (high - cond) / (high - low)


def joint_limit_scale(
    q_rad: np.ndarray,
    qd_rad_s: np.ndarray,
    lower_rad: np.ndarray,
    upper_rad: np.ndarray,
    margin_rad: float,
) -> np.ndarray:
    """Per-joint speed factors (n,): 1 away from limits, linear to 0 at a limit.

    Only the components moving TOWARD a limit within ``margin_rad`` of it are slowed, so a
    joint that reached its limit can always leave it. Infinite limits never scale.
    """
    return np.array(
        [
            _joint_limit_factor(q, qd, lower, upper, margin_rad)
            for q, qd, lower, upper in zip(
                np.asarray(q_rad).tolist(),
                np.asarray(qd_rad_s).tolist(),
                np.asarray(lower_rad).tolist(),
                np.asarray(upper_rad).tolist(),
                strict=True,
            )
        ]
    )


def _joint_limit_factor(
    q_rad: float, qd_rad_s: float, lower_rad: float, upper_rad: float, margin_rad: float
) -> float:
    """One joint's factor of :func:`joint_limit_scale`, in floats (the numpy form's
    where/minimum/maximum on 6-vectors cost more than the arithmetic)."""
    if qd_rad_s > 0.0:
        return min(max((upper_rad - q_rad) / margin_rad, 0.0), 1.0)
    if qd_rad_s < 0.0:
        return min(max((q_rad - lower_rad) / margin_rad, 0.0), 1.0)
    return 1.0


def damped_least_squares(jacobian: np.ndarray, task: np.ndarray, damping: float) -> np.ndarray:
    """q' = J^T (J J^T + lambda^2 I)^-1 task, with lambda grown near singularities.

    The damping is ``damping`` away from singularities and rises smoothly to
    SINGULAR_DAMPING as the smallest singular value falls below SINGULAR_VALUE_THRESHOLD
    (Nakamura's variable damping), which bounds the joint rates at a singularity.

    Solved by Cholesky through the Gram matrix J J^T, or J^T J for a tall J (the smaller
    one; the nonzero eigenvalues of both are the squared singular values), not by an SVD,
    which costs several times more at 6x6 (see :func:`_damped_gram_solve`). Agrees with
    the SVD form to rounding (~1e-14 relative).
    """
    rows, cols = jacobian.shape
    if rows > cols:  # (J^T J + lambda^2 I)^-1 J^T task, the same matrix identity
        return _damped_gram_solve(jacobian.T @ jacobian, jacobian.T @ task, damping)
    return jacobian.T @ _damped_gram_solve(jacobian @ jacobian.T, task, damping)


def _damped_gram_solve(gram: np.ndarray, rhs: np.ndarray, damping: float) -> np.ndarray:
    """(G + lambda^2 I)^-1 rhs for the Gram matrix G of a Jacobian, with the adaptive
    lambda of :func:`damped_least_squares`: :func:`_damped_gram_factor` then
    :func:`_damped_gram_factor_solve` (what LAPACK's dposv does, bit for bit)."""
    return _damped_gram_factor_solve(_damped_gram_factor(gram, damping), rhs)


def _damped_gram_factor(gram: np.ndarray, damping: float) -> np.ndarray:
    """Upper Cholesky factor (LAPACK dpotrf) of G + lambda^2 I, lambda adaptive as in
    :func:`damped_least_squares`.

    Separate from the solve because it depends on the joint state only: the teleoperation
    cycle factors ahead of the handle sample (:meth:`TeleopController.prepare`).

    The smallest singular value is needed only below the threshold: the Cholesky
    factorisation of G - threshold^2 I succeeds exactly when it is above, so G's
    eigenvalues are computed only near a singularity. There, sigma_min^2 + lambda^2 >=
    min(SINGULAR_VALUE_THRESHOLD, SINGULAR_DAMPING)^2 keeps G + lambda^2 I well conditioned.
    """
    size = gram.shape[0]
    _, below_threshold = lapack.dpotrf(gram - _identity(size, _SINGULAR_VALUE_THRESHOLD_SQUARED))
    if below_threshold:
        eigenvalues, _, info = lapack.dsyevd(gram, compute_v=0, lower=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"dsyevd failed (info {info})")
        sigma_min_squared = max(float(eigenvalues[0]), 0.0)
        shortfall = max(1.0 - sigma_min_squared / _SINGULAR_VALUE_THRESHOLD_SQUARED, 0.0)
        lam2 = damping * damping + shortfall * SINGULAR_DAMPING**2
        damped_gram = gram + lam2 * _identity(size)
    else:  # the configured damping, a constant: its identity is cached
        damped_gram = gram + _identity(size, damping * damping)
    factor, info = lapack.dpotrf(damped_gram)
    if info != 0:
        raise np.linalg.LinAlgError(f"dpotrf failed (info {info})")
    return factor


def _damped_gram_factor_solve(factor: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """(G + lambda^2 I)^-1 rhs from the upper factor of :func:`_damped_gram_factor`
    (LAPACK dpotrs: the two triangular solves dposv runs after its dpotrf)."""
    solution, info = lapack.dpotrs(factor, rhs)
    if info != 0:
        raise np.linalg.LinAlgError(f"dpotrs failed (info {info})")
    return solution


def approach_down_orientation(world_r_tool: np.ndarray) -> np.ndarray:
    """The tool orientation with its approach axis (z) straight down, heading kept.

    A top grasp needs the fingers vertical: a few degrees of tilt left over from the
    start pose put one fingertip on the table before the tool reaches the object's
    centre. The heading is the tool x axis projected on the horizontal plane.
    """
    x_axis = np.array([world_r_tool[0, 0], world_r_tool[1, 0], 0.0])
    norm = float(np.linalg.norm(x_axis))
    if norm < MIN_HEADING_NORM:  # x axis vertical: fall back to the y axis's heading
        x_axis = np.cross(world_r_tool[:, 1], [0.0, 0.0, 1.0])
        norm = float(np.linalg.norm(x_axis))
    x_axis /= norm
    z_axis = np.array([0.0, 0.0, -1.0])
    return np.column_stack((x_axis, np.cross(z_axis, x_axis), z_axis))


class TeleopOutput(NamedTuple):
    """One teleoperation cycle (world frame, SI units).

    ``world_v_tool_m_s`` and ``world_p_tool_m`` are the cycle's :class:`JointStateTerms`
    arrays, read-only (copy them to change them). A NamedTuple: immutable like a frozen
    dataclass, and several times cheaper to build on the loop's critical path.
    """

    qd_ref_rad_s: np.ndarray  # (n,) to the plant's velocity loops
    qd_c_rad_s: np.ndarray  # (n,) kinematic command before dynamic compensation
    world_v_ref_m_s: np.ndarray  # (3,) operator's reference (zero while clutched)
    world_v_tool_m_s: np.ndarray  # (3,) actual tool velocity J(q) q' from the measured q'
    world_p_tool_m: np.ndarray  # (3,)
    speed_scale: float  # singularity slowdown x tool-speed cap, in [0, 1]
    joint_limit_scale: float  # smallest per-joint limit factor, in [0, 1]
    cond: float  # condition number of the 3xN position Jacobian
    orientation_error_rad: float  # angle between held and actual tool orientation
    obstacle_active: bool  # the avoidance term acted this cycle
    gripper_cmd: float  # opening fraction in [0, 1], passed through
    held_pairs: int = 0  # close pairs whose approach speed the command was held to


@dataclass(frozen=True)
class JointStateTerms:
    """The part of a teleoperation cycle that depends only on the joint state (q, q').

    The plant state arrives before the handle sample it is answered with, so
    :meth:`TeleopController.prepare` computes these ahead and
    :meth:`TeleopController.update` only adds what depends on the operator, the obstacle
    and the controller's own state. The same values (and operations) ``update`` computes
    when no terms are given, so its outputs are bit for bit the same either way. The arrays are
    read-only: the terms may be kept and used later, and two of them end up in the
    :class:`TeleopOutput`.
    """

    world_p_tool_m: np.ndarray  # (3,) tool point
    world_p_tool_xyz_m: tuple[float, float, float]  # the same as floats
    world_r_tool: np.ndarray  # (3, 3) tool orientation
    # The linear rows (3, n) of the tool Jacobian (LOCAL_WORLD_ALIGNED, m/rad) as floats,
    # for products with the cycle's joint-rate floats (lists here and below: never
    # written once built).
    jacobian_position_rows: list[list[float]]
    # Rows of the damped least squares' matrix (n, 6), task velocity -> joint rates:
    # J^T (J J^T + lambda^2 I)^-1, or (J^T J + lambda^2 I)^-1 J^T for an arm with fewer
    # joints than task rows (see damped_least_squares).
    task_to_qd_rows: list[list[float]]
    cond: float  # condition number of the (3, n) position Jacobian
    world_v_tool_m_s: np.ndarray  # (3,) Jv q' from the measured q'
    measured_tool_speed_m_s: float  # |world_v_tool_m_s|
    q_rad: tuple[float, ...]  # the joint positions the terms were computed at, as floats
    # The orientation hold's error, log3(R_des R^T) (3,), world frame, and the held
    # orientation R_des it was computed with (None, None: none was held yet).
    world_rotation_error: np.ndarray | None = None
    held_r: np.ndarray | None = None
    # The dynamic compensation's terms (None: control.compensation is off).
    compensation: CompensationTerms | None = None
    manipulability: float = 0.0  # sqrt(det(Jv Jv^T)) of the position Jacobian (m^3)
    # The arm's clearance at this joint state (None: not measured), and with
    # ``clearance.avoid`` what the law and the feedback make of it:
    clearance: Clearance | None = None
    # (cap m/s, approach row (n,)) of each pair inside its slowdown distance
    clearance_caps: tuple[tuple[float, np.ndarray], ...] = ()
    # (I - J# J) of the pushes away from close pairs and joint limits (n,), rad/s
    null_push_rad_s: list[float] | None = None
    # The push-back felt on the handle (3,), N, world frame (None: zero)
    world_f_scene_n: np.ndarray | None = None  # table, bin, static geoms
    world_f_limits_n: np.ndarray | None = None  # joint limits, the arm's links


class TeleopController:
    """Joint velocity references that make the tool follow the operator's velocity.

    State kept between cycles: the held orientation (captured at the first update after
    :meth:`reset`), the integrated desired position and the previous kinematic command
    (for the compensation's acceleration). ``mj_body_names`` (MuJoCo body names indexed
    by body id, :func:`teleop.sim.proximity.body_names`) maps a :class:`ProximitySample`'s
    ``arm_body`` to the Pinocchio frame of the same name; without it obstacles are
    ignored (and counted in ``unmapped_obstacle_samples``). ``clearance``: measures the
    arm's clearance in every :meth:`prepare` (and, with ``clearance.avoid``, keeps it and
    renders it); None: neither.
    """

    def __init__(
        self,
        arm: ArmModel,
        teleop_cfg: TeleopConfig,
        control_cfg: ControlConfig,
        period_s: float,
        mj_body_names: Sequence[str] = (),
        clearance: ClearanceModel | None = None,
    ) -> None:
        self.arm = arm
        self.teleop = teleop_cfg
        self.control = control_cfg
        self.period_s = period_s
        self.clearance = clearance
        self.max_speed_rad_s = np.minimum(
            control_cfg.max_joint_speed_rad_s, arm.servo.max_speed_rad_s
        )
        lower = arm.model.lowerPositionLimit.copy()
        upper = arm.model.upperPositionLimit.copy()
        continuous = (lower <= -CONTINUOUS_LIMIT_RAD) & (upper >= CONTINUOUS_LIMIT_RAD)
        self.lower_rad = np.where(continuous, -np.inf, lower)
        self.upper_rad = np.where(continuous, np.inf, upper)
        # The per-cycle limits in floats (the cycle works on floats, see the module). Only
        # joints with a finite limit are scaled: an infinite one gives a factor of 1.
        self._speed_limits_rad_s = self.max_speed_rad_s.tolist()
        self._max_change_per_cycle_rad_s = MAX_JOINT_ACCEL_RAD_S2 * period_s
        self._limited_joints = [
            (joint, lower, upper)
            for joint, (lower, upper) in enumerate(
                zip(self.lower_rad.tolist(), self.upper_rad.tolist(), strict=True)
            )
            if math.isfinite(lower) or math.isfinite(upper)
        ]
        # J J^T (task x task) is the least squares' Gram matrix unless the arm has fewer
        # joints than task rows (then J^T J is, see damped_least_squares).
        self._wide_jacobian = arm.n_joints >= TASK_DIMENSION
        # prepare()'s own Pinocchio scratch: it never writes arm.data, which update() uses
        # (look-ahead, dynamics), so terms computed ahead stay valid whatever runs between.
        self._prepare_arm = dataclasses.replace(arm, data=arm.model.createData())
        self._body_frames: dict[int, int] = {}
        for body, name in enumerate(mj_body_names):
            if name and arm.model.existFrame(name, pin.FrameType.BODY):
                self._body_frames[body] = arm.model.getFrameId(name, pin.FrameType.BODY)
        self.unmapped_obstacle_samples = 0
        self._p_des: tuple[float, float, float] | None = None
        self._r_des: np.ndarray | None = None
        self._previous_qd_c: list[float] | None = None
        self._previous_nominal: list[float] | None = None
        self._previous_tool_speed = 0.0

    def reset(self) -> None:
        """Forget the held pose: the next update holds the orientation it finds
        (straightened to point down when ``teleop.approach_down``)."""
        self._p_des = None
        self._r_des = None
        self._previous_qd_c = None
        self._previous_nominal = None
        self._previous_tool_speed = 0.0

    def prepare(
        self, q_rad: np.ndarray, qd_rad_s: np.ndarray, gripper_opening_m: float | None = None
    ) -> JointStateTerms:
        """The terms of :meth:`update` that depend only on the joint state and the model.

        The plant state is known before the handle sample that completes the cycle: this
        half (tool pose and Jacobian, Gram matrix and its damped Cholesky factor,
        condition number, measured tool velocity, the clearance at ``q_rad`` and
        ``gripper_opening_m``, each finger's slide, None: open) can run off the critical path, and
        ``update(..., terms=...)`` does the rest. It changes nothing of the controller's
        state (held pose, previous commands, counters): call it any number of times, for
        any state, and use the result later. It reads the held orientation, once there is
        one, for the hold's error; ``update`` uses that error only while the same
        orientation is held (after a reset it computes its own). It writes only its own
        Pinocchio scratch data, so it must not run in two threads at once (nor beside an
        ``update(terms=None)``, which calls it).

        Left out, because only the first cycle after a :meth:`reset` needs them: the
        straightened orientation to hold and the measured q' as the previous command.
        """
        arm = self._prepare_arm
        compensation = None
        if self.control.compensation:  # first: the Jacobian's pass below must come last,
            compensation = compensation_terms(arm, q_rad, qd_rad_s)  # see update()'s obstacle
        tool_p, tool_r, jacobian = tool_pose_and_jacobian(arm, q_rad)
        # J J^T (6, 6): the least squares' Gram matrix; its top-left block is Jv Jv^T.
        jjt = jacobian @ jacobian.T
        damping = self.control.damping_m
        if self._wide_jacobian:  # J^T (J J^T + lambda^2 I)^-1 = ((J J^T + lambda^2 I)^-1 J)^T
            factor = _damped_gram_factor(jjt, damping)
            task_to_qd = _damped_gram_factor_solve(factor, jacobian).T
        else:  # (J^T J + lambda^2 I)^-1 J^T: the smaller Gram matrix, as damped_least_squares
            factor = _damped_gram_factor(jacobian.T @ jacobian, damping)
            task_to_qd = _damped_gram_factor_solve(factor, jacobian.T)
        jv = jacobian[:3]
        cond, manipulability = _condition_and_manipulability(jjt[:3, :3])
        v_tool = jv @ qd_rad_s
        held_r = self._r_des  # held from the first update on: its error is ready too
        rotation_error = None if held_r is None else pin.log3(held_r @ tool_r.T)
        clearance, caps, null_push, f_scene, f_limits = None, (), None, None, None
        if self.clearance is not None:  # reads the joint Jacobians left in arm.data
            clearance, caps, null_push, f_scene, f_limits = self._clearance_terms(
                arm, q_rad, qd_rad_s, gripper_opening_m, jacobian, task_to_qd
            )
        for array in (tool_p, tool_r, v_tool, rotation_error, f_scene, f_limits):
            if array is not None:
                array.flags.writeable = False
        return JointStateTerms(
            world_p_tool_m=tool_p,
            world_p_tool_xyz_m=tuple(tool_p.tolist()),
            world_r_tool=tool_r,
            jacobian_position_rows=jv.tolist(),
            task_to_qd_rows=task_to_qd.tolist(),
            cond=cond,
            world_v_tool_m_s=v_tool,
            measured_tool_speed_m_s=_norm(v_tool),
            q_rad=tuple(q_rad.tolist()),
            world_rotation_error=rotation_error,
            held_r=held_r,
            compensation=compensation,
            manipulability=manipulability,
            clearance=clearance,
            clearance_caps=caps,
            null_push_rad_s=null_push,
            world_f_scene_n=f_scene,
            world_f_limits_n=f_limits,
        )

    def _clearance_terms(
        self,
        arm: ArmModel,
        q_rad: np.ndarray,
        qd_rad_s: np.ndarray,
        gripper_opening_m: float | None,
        jacobian: np.ndarray,
        task_to_qd: np.ndarray,
    ) -> tuple[
        Clearance,
        tuple[tuple[float, np.ndarray], ...],
        list[float] | None,
        np.ndarray | None,
        np.ndarray | None,
    ]:
        """The clearance at ``q_rad``, and with ``clearance.avoid``: the approach caps of
        the close pairs (at their closing speed measured from ``qd_rad_s``), the
        null-space push away from them and from the joint limits, and the push-back of the
        scene and of the arm's own limits felt on the handle.

        A pair inside its slowdown distance by ``depth`` m with approach row j (d' = j q')
        is felt as ``scene_stiffness * depth`` N along u = (j T)^T / |j T|, T the
        least squares' columns from the tool's linear velocity to joint rates: the tool
        motion the law turns into the fastest opening of the pair. A joint inside the
        limit margin by ``depth`` rad the same way, with ``joint_limit_stiffness`` and the
        tool motion that moves it away from its limit (its row of T). ``arm.data`` holds
        the joint Jacobians at ``q_rad``.
        """
        model = self.clearance
        assert model is not None
        config = model.config
        opening = model.open_m if gripper_opening_m is None else gripper_opening_m
        clearance = model.measure(q_rad, opening)
        if not config.avoid:
            return clearance, (), None, None, None
        linear_to_qd = task_to_qd[:, :3]  # (n, 3): tool linear velocity -> joint rates
        f_scene, f_limits = np.zeros(3), np.zeros(3)
        k_scene = self.teleop.scene_stiffness_n_per_m
        close = close_pairs(config, arm, clearance, qd_rad_s)
        for c in close:
            direction = c.row @ linear_to_qd  # (3,): opening speed per unit tool velocity
            norm = _norm(direction)
            if norm > MIN_FEEDBACK_DIRECTION:
                force = (k_scene * c.inside_m / norm) * direction
                if c.pair.kind == PairKind.SELF:
                    f_limits += force
                else:
                    f_scene += force
        caps = [(c.cap_m_s, c.row) for c in close]
        push = clearance_push([(c.push_depth_m, c.row) for c in close], config)
        margin = config.joint_limit_margin_rad
        k_limit = self.teleop.joint_limit_stiffness_n_per_rad
        q = q_rad.tolist()
        for joint, lower, upper in self._limited_joints:
            if q[joint] > upper - margin:
                depth, away = q[joint] - (upper - margin), -1.0
            elif q[joint] < lower + margin:
                depth, away = (lower + margin) - q[joint], 1.0
            else:
                continue
            if push is None:
                push = np.zeros(len(q))
            push[joint] += config.joint_limit_gain_per_s * depth * away
            direction = away * linear_to_qd[joint]  # tool motion that moves it away
            norm = _norm(direction)
            if norm > MIN_FEEDBACK_DIRECTION:
                f_limits += (k_limit * depth / norm) * direction
        null_push = None
        if push is not None:  # (I - J# J) g: what the 6D task leaves free
            null_push = (push - task_to_qd @ (jacobian @ push)).tolist()
        return clearance, tuple(caps), null_push, f_scene, f_limits

    def update(
        self,
        q_rad: np.ndarray,
        qd_rad_s: np.ndarray,
        world_v_ref_m_s: np.ndarray,
        obstacle: ProximitySample | None,
        gripper_cmd: float,
        clutch: bool = False,
        terms: JointStateTerms | None = None,
        gripper_opening_m: float | None = None,
    ) -> TeleopOutput:
        """One control cycle from the measured joint state and the operator's reference.

        ``terms``: :meth:`prepare` of this same (q_rad, qd_rad_s, gripper_opening_m),
        computed ahead (the caller guarantees they match; nothing checks it); None
        computes them here. The outputs are the same bit for bit either way.

        3-vectors are unpacked into floats and joint vectors kept as float lists between
        the Pinocchio and LAPACK calls (see the module docstring for why).
        """
        # Without terms prepare()'s scratch data holds this q's joint Jacobians (the
        # obstacle term reads them); terms from earlier may have been followed by others.
        arm_at_q = None
        if terms is None:
            terms = self.prepare(q_rad, qd_rad_s, gripper_opening_m)
            arm_at_q = self._prepare_arm
        v_ref = np.zeros(3) if clutch else np.asarray(world_v_ref_m_s, dtype=float)
        task, orientation_error_rad = self._task_velocity(terms, v_ref, clutch)
        qd_c = [sum(map(operator.mul, row, task)) for row in terms.task_to_qd_rows]
        qd_c = self._limit_acceleration(qd_c, qd_rad_s)
        obstacle_active = False
        if obstacle is not None and obstacle.distance_m < self.teleop.obstacle_influence_m:
            qd_c, obstacle_active = self._avoid(qd_c, obstacle, q_rad, arm_at_q)
        if terms.null_push_rad_s is not None:
            qd_c = list(map(operator.add, qd_c, terms.null_push_rad_s))
        qd_c, scale, joint_limit_factor = self._slow_near_limits(qd_c, q_rad, terms)
        # Last of the changes that turn the command: the speed caps below scale it as a
        # whole, which keeps every close pair's approach within its cap.
        held = 0
        caps = list(terms.clearance_caps)
        if caps:
            held_qd, held = hold_clearance(np.array(qd_c), caps)
            qd_c = held_qd.tolist()
        qd_c, cap = self._cap_speeds(qd_c, terms)
        scale *= cap

        qd_ref = velocity_reference(
            self.control, terms.compensation, qd_c, self._previous_qd_c, self.period_s
        )
        self._previous_qd_c = qd_c
        if caps:
            # As in path following: the compensation adds the velocity loops' dynamics to
            # q'_c, and the reference the plant applies must keep the caps too.
            qd_ref = hold_clearance(np.array(qd_ref), caps)[0].tolist()
        return TeleopOutput(
            qd_ref_rad_s=np.array(limit_speed(qd_ref, self._speed_limits_rad_s)[0]),
            qd_c_rad_s=np.array(qd_c),
            world_v_ref_m_s=v_ref,
            world_v_tool_m_s=terms.world_v_tool_m_s,
            world_p_tool_m=terms.world_p_tool_m,
            speed_scale=scale,
            joint_limit_scale=joint_limit_factor,
            cond=terms.cond,
            orientation_error_rad=orientation_error_rad,
            obstacle_active=obstacle_active,
            gripper_cmd=min(max(float(gripper_cmd), 0.0), 1.0),
            held_pairs=held,
        )

    def _task_velocity(
        self, terms: JointStateTerms, v_ref: np.ndarray, clutch: bool
    ) -> tuple[tuple[float, ...], float]:
        """The 6-D task velocity (world frame: m/s, then rad/s): the operator's reference
        plus the position hold towards the integrated goal and the orientation hold
        towards the held pose; and the orientation error's size (rad).

        The goal integrates the reference but never runs away from a tool that the
        safety scaling holds back (the hold would wind up): it stays within
        POSITION_HOLD_MAX_ERROR_M of the tool."""
        tool_r = terms.world_r_tool
        if self._r_des is None:
            approach_down = self.teleop.approach_down
            self._r_des = approach_down_orientation(tool_r) if approach_down else tool_r.copy()
            self._r_des.flags.writeable = False  # prepared terms keep it (held_r)
        px, py, pz = terms.world_p_tool_xyz_m
        vx, vy, vz = v_ref.tolist()
        if self._p_des is None or clutch:
            self._p_des = (px, py, pz)
        dt = self.period_s
        gx, gy, gz = self._p_des
        ex, ey, ez = gx + vx * dt - px, gy + vy * dt - py, gz + vz * dt - pz
        error_norm = math.hypot(ex, ey, ez)
        if error_norm > POSITION_HOLD_MAX_ERROR_M:
            shrink = POSITION_HOLD_MAX_ERROR_M / error_norm
            ex, ey, ez = ex * shrink, ey * shrink, ez * shrink
        self._p_des = (px + ex, py + ey, pz + ez)
        if terms.held_r is self._r_des and terms.world_rotation_error is not None:
            rotation_error = terms.world_rotation_error  # prepared with this held pose
        else:
            rotation_error = pin.log3(self._r_des @ tool_r.T)  # world-frame rotation vector
        rx, ry, rz = rotation_error.tolist()
        kp, kr = POSITION_HOLD_GAIN_PER_S, ORIENTATION_GAIN_PER_S
        task = (vx + kp * ex, vy + kp * ey, vz + kp * ez, kr * rx, kr * ry, kr * rz)
        return task, math.hypot(rx, ry, rz)

    def _slow_near_limits(
        self, qd_c: list[float], q_rad: np.ndarray, terms: JointStateTerms
    ) -> tuple[list[float], float, float]:
        """The command slowed on its way towards a singularity and scaled joint by joint
        near the joint limits; returns it, the singularity's speed scale and the smallest
        joint-limit factor (1: neither acted)."""
        cond = terms.cond
        scale = 1.0
        if cond > self.teleop.singularity_slowdown_cond and self._toward_singularity(
            q_rad, qd_c, cond
        ):
            scale = singularity_scale(cond, self.teleop)
            qd_c = [qd * scale for qd in qd_c]
        limit_factors = self._joint_limit_factors(terms.q_rad, qd_c)
        joint_limit_factor = min(limit_factors)
        if joint_limit_factor < 1.0:
            qd_c = list(map(operator.mul, qd_c, limit_factors))
        return qd_c, scale, joint_limit_factor

    def _cap_speeds(self, qd_c: list[float], terms: JointStateTerms) -> tuple[list[float], float]:
        """The command scaled as a whole under the tool-speed cap and the joints' speed
        limits; returns it and the tool-speed cap's factor (1: not capped).

        The drives track with a small lag: when the tool moved faster than it was told
        last cycle, the cap is that much lower, so the MEASURED speed respects it."""
        overshoot = terms.measured_tool_speed_m_s - self._previous_tool_speed
        max_speed = self.teleop.max_tool_speed_m_s - max(0.0, overshoot)
        tool_speed = math.hypot(
            *[sum(map(operator.mul, row, qd_c)) for row in terms.jacobian_position_rows]
        )
        cap = 1.0
        if tool_speed > max_speed:
            cap = max(0.0, max_speed) / tool_speed
            qd_c = [qd * cap for qd in qd_c]
            tool_speed *= cap
        qd_c, ratio = limit_speed(qd_c, self._speed_limits_rad_s)
        # Both limits scale the whole vector, so the tool speed scales with it.
        self._previous_tool_speed = tool_speed / ratio
        return qd_c, cap

    def _avoid(
        self,
        qd_c: list[float],
        obstacle: ProximitySample,
        q_rad: np.ndarray,
        arm_at_q: ArmModel | None,
    ) -> tuple[list[float], bool]:
        """Add the joint motion that pushes the closest arm point away from the obstacle.

        The arm point's speed along the away direction n gains
        obstacle_avoid_gain (d0 - d) m/s on top of what the task gives it, through the
        minimum-norm joint motion j_n^T / (j_n j_n^T + lambda^2) of the point's projected
        Jacobian j_n (:func:`point_jacobian_along`). Additive on purpose: pushed into an
        obstacle at speed v, the point settles where gain (d0 - d) = v, i.e.
        d = d0 - v / gain (0.0175 m at 0.25 m/s with the defaults), and the felt
        repulsion k (d0 - d) grows with how hard the operator pushes.

        ``arm_at_q``: an arm whose scratch data holds the joint Jacobians at ``q_rad``, or
        None to compute them again in ``arm.data`` (the same call on the same q gives the
        same values; only cycles with an obstacle in range pay it).
        """
        frame = self._body_frames.get(obstacle.arm_body)
        if frame is None:
            self.unmapped_obstacle_samples += 1
            return qd_c, False
        if arm_at_q is None:
            pin.computeJointJacobians(self.arm.model, self.arm.data, q_rad)
            arm_at_q = self.arm
        j_n = point_jacobian_along(arm_at_q, frame, obstacle.world_p_arm_m, obstacle.world_n_away)
        tcfg = self.teleop
        away_m_s = tcfg.obstacle_avoid_gain_per_s * (
            tcfg.obstacle_influence_m - obstacle.distance_m
        )
        j_n = j_n.tolist()
        gain = away_m_s / (sum([j * j for j in j_n]) + AVOID_DAMPING_M_PER_RAD**2)
        return [qd + gain * j for qd, j in zip(qd_c, j_n, strict=True)], True

    def _limit_acceleration(self, qd_c: list[float], qd_rad_s: np.ndarray) -> list[float]:
        """Bound the change of the nominal command per cycle (direction of change kept).

        The first cycle after a reset starts from the measured joint velocities.
        """
        previous = self._previous_nominal
        if previous is None:
            previous = qd_rad_s.tolist()
        change = list(map(operator.sub, qd_c, previous))
        ratio = max(map(abs, change)) / self._max_change_per_cycle_rad_s
        if ratio > 1.0:
            change = [dqd / ratio for dqd in change]
        self._previous_nominal = list(map(operator.add, previous, change))
        return self._previous_nominal

    def _joint_limit_factors(self, q_rad: Sequence[float], qd_rad_s: list[float]) -> list[float]:
        """:func:`joint_limit_scale` of the controller's joints (only the limited ones are
        computed, the others are 1)."""
        factors = [1.0] * len(qd_rad_s)
        if self._limited_joints:
            margin = self.teleop.joint_limit_margin_rad
            for joint, lower, upper in self._limited_joints:
                factors[joint] = _joint_limit_factor(
                    q_rad[joint], qd_rad_s[joint], lower, upper, margin
                )
        return factors

    def _toward_singularity(self, q_rad: np.ndarray, qd_c: list[float], cond: float) -> bool:
        """Whether following qd_c for SINGULARITY_LOOKAHEAD_S raises the condition number."""
        q_ahead = q_rad + np.array(qd_c) * SINGULARITY_LOOKAHEAD_S
        return position_condition_number(tool_jacobian(self.arm, q_ahead)[:3]) > cond
