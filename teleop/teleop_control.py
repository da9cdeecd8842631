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
arm point away. Then, like MoveIt Servo, the motion is slowed down near singularities
and joint limits and capped in tool speed, and dynamic compensation (shared with path
following) turns the kinematic command into references for the velocity loops.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from teleop.config import ControlConfig, TeleopConfig
from teleop.control import limit_speed, velocity_reference
from teleop.kinematics import ArmModel, tool_position_and_jacobian
from teleop.proximity import ProximitySample

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
# Joint limits at or beyond this magnitude (rad) mean "no limit": a joint that can turn a
# full turn each way (the shoulder pan, UR-style wrists) is treated as continuous.
CONTINUOUS_LIMIT_RAD = 2.0 * math.pi - 1e-3


def view_to_world(yaw_rad: float) -> np.ndarray:
    """Rz(yaw) (3, 3): maps view/device-frame vectors to the world frame."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rate_command(d_m: np.ndarray, yaw_rad: float, cfg: TeleopConfig) -> np.ndarray:
    """World tool-velocity reference (3,) in m/s from the handle offset ``d_m`` (3,) in m.

    Radial deadband, continuous at its edge: v = gain (|d| - deadband) d/|d| beyond it,
    zero inside (the hand's tremor and the handle's rest offset command nothing). The
    device/view-frame velocity is rotated to the world by Rz(yaw) and capped in norm at
    ``max_tool_speed_m_s``.
    """
    d = np.asarray(d_m, dtype=float)
    norm = float(np.linalg.norm(d))
    if norm <= cfg.deadband_m:
        return np.zeros(3)
    speed = min(cfg.rate_gain_per_s * (norm - cfg.deadband_m), cfg.max_tool_speed_m_s)
    return view_to_world(yaw_rad) @ (d * (speed / norm))


def teleop_reference(
    d_m: np.ndarray, yaw_rad: float, clutch: bool, cfg: TeleopConfig
) -> np.ndarray:
    """:func:`rate_command`, or zero while the clutch is held (the operator re-centres)."""
    return np.zeros(3) if clutch else rate_command(d_m, yaw_rad, cfg)


def _norm(v: np.ndarray) -> float:
    """Euclidean norm of a short vector (np.linalg.norm costs ~3 us at this size)."""
    return math.sqrt(float(v @ v))


def position_condition_number(jacobian_position: np.ndarray) -> float:
    """Condition number s_max / s_min of the (3, n) position Jacobian (inf if singular).

    From the eigenvalues of the 3x3 J J^T (the squared singular values), cheaper than
    an SVD of J.
    """
    eigenvalues = np.linalg.eigvalsh(jacobian_position @ jacobian_position.T)
    if eigenvalues[0] <= 0.0:
        return math.inf
    return math.sqrt(float(eigenvalues[-1] / eigenvalues[0]))


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
    to_upper = np.minimum(np.maximum((upper_rad - q_rad) / margin_rad, 0.0), 1.0)
    to_lower = np.minimum(np.maximum((q_rad - lower_rad) / margin_rad, 0.0), 1.0)
    return np.where(qd_rad_s > 0, to_upper, np.where(qd_rad_s < 0, to_lower, 1.0))


def damped_least_squares(jacobian: np.ndarray, task: np.ndarray, damping: float) -> np.ndarray:
    """q' = J^T (J J^T + lambda^2 I)^-1 task, with lambda grown near singularities.

    The damping is ``damping`` away from singularities and rises smoothly to
    SINGULAR_DAMPING as the smallest singular value falls below SINGULAR_VALUE_THRESHOLD
    (Nakamura's variable damping), which bounds the joint rates at a singularity.
    """
    u, sigma, vt = np.linalg.svd(jacobian, full_matrices=False)
    sigma_min = float(sigma[-1])
    lam2 = damping * damping
    if sigma_min < SINGULAR_VALUE_THRESHOLD:
        lam2 += (1.0 - (sigma_min / SINGULAR_VALUE_THRESHOLD) ** 2) * SINGULAR_DAMPING**2
    return vt.T @ ((sigma / (sigma * sigma + lam2)) * (u.T @ task))


def point_jacobian_along(
    arm: ArmModel, frame_id: int, world_p_m: np.ndarray, world_n: np.ndarray
) -> np.ndarray:
    """Row (n,) mapping joint rates to the speed (m/s) of a point along a direction.

    The point ``world_p_m`` is rigidly attached to the Pinocchio frame ``frame_id``; its
    velocity is the frame's v_o + w x r with r = p - o, so along the unit ``world_n``
    it is n^T Jv - (n x r)^T Jw. Reads the joint Jacobians that
    :func:`tool_position_and_jacobian` left in ``arm.data``: call it first, at the same q.
    """
    frame_jacobian = pin.getFrameJacobian(
        arm.model, arm.data, frame_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
    )
    r = np.asarray(world_p_m, dtype=float) - arm.data.oMf[frame_id].translation
    n = np.asarray(world_n, dtype=float)
    n_cross_r = np.array(
        (n[1] * r[2] - n[2] * r[1], n[2] * r[0] - n[0] * r[2], n[0] * r[1] - n[1] * r[0])
    )
    return n @ frame_jacobian[:3] - n_cross_r @ frame_jacobian[3:]


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


@dataclass(frozen=True)
class TeleopOutput:
    """One teleoperation cycle (world frame, SI units)."""

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


class TeleopController:
    """Joint velocity references that make the tool follow the operator's velocity.

    State kept between cycles: the held orientation (captured at the first update after
    :meth:`reset`), the integrated desired position and the previous kinematic command
    (for the compensation's acceleration). ``mj_body_names`` (MuJoCo body names indexed
    by body id, :func:`teleop.proximity.body_names`) maps a :class:`ProximitySample`'s
    ``arm_body`` to the Pinocchio frame of the same name; without it obstacles are
    ignored (and counted in ``unmapped_obstacle_samples``).
    """

    def __init__(
        self,
        arm: ArmModel,
        teleop_cfg: TeleopConfig,
        control_cfg: ControlConfig,
        period_s: float,
        mj_body_names: Sequence[str] = (),
    ) -> None:
        self.arm = arm
        self.teleop = teleop_cfg
        self.control = control_cfg
        self.period_s = period_s
        self.max_speed_rad_s = np.minimum(
            control_cfg.max_joint_speed_rad_s, arm.servo.max_speed_rad_s
        )
        lower = arm.model.lowerPositionLimit.copy()
        upper = arm.model.upperPositionLimit.copy()
        continuous = (lower <= -CONTINUOUS_LIMIT_RAD) & (upper >= CONTINUOUS_LIMIT_RAD)
        self.lower_rad = np.where(continuous, -np.inf, lower)
        self.upper_rad = np.where(continuous, np.inf, upper)
        self._body_frames: dict[int, int] = {}
        for body, name in enumerate(mj_body_names):
            if name and arm.model.existFrame(name, pin.FrameType.BODY):
                self._body_frames[body] = arm.model.getFrameId(name, pin.FrameType.BODY)
        self.unmapped_obstacle_samples = 0
        self._p_des: np.ndarray | None = None
        self._r_des: np.ndarray | None = None
        self._previous_qd_c: np.ndarray | None = None
        self._previous_nominal: np.ndarray | None = None
        self._previous_tool_speed = 0.0

    def reset(self) -> None:
        """Forget the held pose: the next update holds the orientation it finds
        (straightened to point down when ``teleop.approach_down``)."""
        self._p_des = None
        self._r_des = None
        self._previous_qd_c = None
        self._previous_nominal = None
        self._previous_tool_speed = 0.0

    def update(
        self,
        q_rad: np.ndarray,
        qd_rad_s: np.ndarray,
        world_v_ref_m_s: np.ndarray,
        obstacle: ProximitySample | None,
        gripper_cmd: float,
        clutch: bool = False,
    ) -> TeleopOutput:
        """One control cycle from the measured joint state and the operator's reference."""
        tcfg, dt = self.teleop, self.period_s
        tool_p, jacobian = tool_position_and_jacobian(self.arm, q_rad)
        tool_r = self.arm.data.oMf[self.arm.tool_frame_id].rotation
        v_ref = np.zeros(3) if clutch else np.asarray(world_v_ref_m_s, dtype=float)
        if self._r_des is None:
            self._r_des = approach_down_orientation(tool_r) if tcfg.approach_down else tool_r.copy()
        if self._p_des is None or clutch:
            self._p_des = tool_p.copy()
        # Integrate the operator's reference, but never let the goal run away from a tool
        # that the safety scaling holds back (the hold would wind up).
        error = self._p_des + v_ref * dt - tool_p
        error_norm = _norm(error)
        if error_norm > POSITION_HOLD_MAX_ERROR_M:
            error *= POSITION_HOLD_MAX_ERROR_M / error_norm
        self._p_des = tool_p + error
        rotation_error = pin.log3(self._r_des @ tool_r.T)  # world-frame rotation vector
        task = np.concatenate(
            (v_ref + POSITION_HOLD_GAIN_PER_S * error, ORIENTATION_GAIN_PER_S * rotation_error)
        )
        qd_c = damped_least_squares(jacobian, task, self.control.damping_m)
        qd_c = self._limit_acceleration(qd_c, qd_rad_s)
        obstacle_active = False
        if obstacle is not None and obstacle.distance_m < tcfg.obstacle_influence_m:
            qd_c, obstacle_active = self._avoid(qd_c, obstacle)

        jv = jacobian[:3]
        cond = position_condition_number(jv)
        scale = 1.0
        if cond > tcfg.singularity_slowdown_cond and self._toward_singularity(q_rad, qd_c, cond):
            scale = singularity_scale(cond, tcfg)
        qd_c = qd_c * scale
        limit_factors = joint_limit_scale(
            q_rad, qd_c, self.lower_rad, self.upper_rad, tcfg.joint_limit_margin_rad
        )
        qd_c = qd_c * limit_factors
        # The drives track with a small lag; when the tool moved faster than it was told
        # last cycle, command that much less so the MEASURED speed respects the cap.
        v_tool = jv @ qd_rad_s
        overshoot = _norm(v_tool) - self._previous_tool_speed
        max_speed = tcfg.max_tool_speed_m_s - max(0.0, overshoot)
        tool_speed = _norm(jv @ qd_c)
        if tool_speed > max_speed:
            cap = max(0.0, max_speed) / tool_speed
            qd_c = qd_c * cap
            scale *= cap
        qd_c = limit_speed(qd_c, self.max_speed_rad_s)
        self._previous_tool_speed = _norm(jv @ qd_c)

        qd_ref = velocity_reference(
            self.arm, self.control, q_rad, qd_rad_s, qd_c, self._previous_qd_c, dt
        )
        self._previous_qd_c = qd_c
        return TeleopOutput(
            qd_ref_rad_s=limit_speed(qd_ref, self.max_speed_rad_s),
            qd_c_rad_s=qd_c,
            world_v_ref_m_s=v_ref,
            world_v_tool_m_s=v_tool,
            world_p_tool_m=tool_p,
            speed_scale=scale,
            joint_limit_scale=float(np.min(limit_factors)),
            cond=cond,
            orientation_error_rad=_norm(rotation_error),
            obstacle_active=obstacle_active,
            gripper_cmd=float(np.clip(gripper_cmd, 0.0, 1.0)),
        )

    def _avoid(self, qd_c: np.ndarray, obstacle: ProximitySample) -> tuple[np.ndarray, bool]:
        """Add the joint motion that pushes the closest arm point away from the obstacle.

        The arm point's speed along the away direction n gains
        obstacle_avoid_gain (d0 - d) m/s on top of what the task gives it, through the
        minimum-norm joint motion j_n^T / (j_n j_n^T + lambda^2) of the point's projected
        Jacobian j_n (:func:`point_jacobian_along`). Additive on purpose: pushed into an
        obstacle at speed v, the point settles where gain (d0 - d) = v, i.e.
        d = d0 - v / gain (0.0175 m at 0.25 m/s with the defaults), and the felt
        repulsion k (d0 - d) grows with how hard the operator pushes.
        """
        frame = self._body_frames.get(obstacle.arm_body)
        if frame is None:
            self.unmapped_obstacle_samples += 1
            return qd_c, False
        j_n = point_jacobian_along(self.arm, frame, obstacle.world_p_arm_m, obstacle.world_n_away)
        tcfg = self.teleop
        away_m_s = tcfg.obstacle_avoid_gain_per_s * (
            tcfg.obstacle_influence_m - obstacle.distance_m
        )
        gain = away_m_s / (float(j_n @ j_n) + AVOID_DAMPING_M_PER_RAD**2)
        return qd_c + gain * j_n, True

    def _limit_acceleration(self, qd_c: np.ndarray, qd_rad_s: np.ndarray) -> np.ndarray:
        """Bound the change of the nominal command per cycle (direction of change kept).

        The first cycle after a reset starts from the measured joint velocities.
        """
        previous = self._previous_nominal if self._previous_nominal is not None else qd_rad_s
        qd_c = previous + limit_speed(qd_c - previous, MAX_JOINT_ACCEL_RAD_S2 * self.period_s)
        self._previous_nominal = qd_c
        return qd_c

    def _toward_singularity(self, q_rad: np.ndarray, qd_c: np.ndarray, cond: float) -> bool:
        """Whether following qd_c for SINGULARITY_LOOKAHEAD_S raises the condition number."""
        _, ahead = tool_position_and_jacobian(self.arm, q_rad + qd_c * SINGULARITY_LOOKAHEAD_S)
        return position_condition_number(ahead[:3]) > cond
