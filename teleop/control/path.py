"""Control laws of the paper's family: path following and dynamic compensation.

Kinematic controller (position task, redundant arm):
    q'_c = J# (v_hd + K e0 tanh(h~ / e0)) + (I - J# J) (L grad w(q) + g_clear + g_limits)
with h~ = P(s*) - h the error to the closest path point P(s*), v_hd the desired
velocity along the path's tangent with speed v_P / (1 + k |h~|), J# the damped
pseudo-inverse of the 3xN position Jacobian (its damping grows smoothly near
singularities, Nakamura's variable damping) and w the manipulability. With a
:class:`teleop.control.clearance.ClearanceModel` and ``clearance.avoid`` the null space
also pushes links away from what is near (g_clear) and joints away from their limits
(g_limits), and the command is then held to the approach speed each close pair allows
(:func:`hold_clearance`): the tool leaves the path rather than the arm touching the
table, the bin or itself, and the run's metrics show the stall.

Dynamic compensation turns the commanded joint velocities q'_c into references for
the arm's velocity loops, q'_ref, using the model M q'' + C q' + g = q'_ref with
M = H^-1 M0, C q' = H^-1 (c0 + (D + H) q'), g = H^-1 g0 and H = diag(kv) read
from the MJCF actuators (see ``kinematics.ServoParameters``):
    q'_ref = M (q''_c + Kd (q'_c - q')) + C q' + g.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from teleop.bus.messages import Event
from teleop.control.clearance import Clearance, ClearanceModel, close_pairs
from teleop.control.desired_path import DesiredPath
from teleop.control.kinematics import (
    ArmModel,
    damped_least_squares,
    manipulability_and_gradient,
    mass_matrix_and_bias,
    tool_position_and_jacobian,
)
from teleop.core.config import ClearanceConfig, Config, ControlConfig, PathConfig

# Damping (m/rad) of the one-row pseudo-inverses that push a link away or cap its
# approach: a point the joints barely move gets a bounded joint motion.
ROW_DAMPING_M_PER_RAD = 0.01
# Passes over the close pairs when holding their approach speeds (each pass projects the
# command onto each violated cap in turn; two or three settle the usual one to three pairs).
HOLD_PASSES = 3
# Joint limits at or beyond this magnitude (rad) mean "no limit" (a joint that turns a
# full turn each way).
CONTINUOUS_LIMIT_RAD = 2.0 * math.pi - 1e-3


@dataclass(frozen=True)
class ControlOutput:
    """One control cycle's command and what it was computed from (world frame, SI)."""

    qd_ref_rad_s: np.ndarray  # (n,) sent to the plant's velocity loops
    qd_c_rad_s: np.ndarray  # (n,) kinematic command, before dynamic compensation
    tool_p_m: np.ndarray  # (3,) tool point h
    desired_p_m: np.ndarray  # (3,) closest path point P(s*)
    path_error_m: float  # |h~|
    manipulability: float
    path_s: float
    path_arc_m: float = 0.0  # signed arc length of P(s) followed since the start
    path_speed_m_s: float = 0.0  # speed commanded along the path, v_P / (1 + k |h~|)
    clearance: Clearance | None = None  # the cycle's clearance (None: not measured)
    held_pairs: int = 0  # close pairs whose approach speed the command was held to


def limit_speed(qd_rad_s: list[float], max_rad_s: list[float]) -> tuple[list[float], float]:
    """The joint rates divided by ``ratio`` >= 1 (the direction kept) so that every
    |q'_i| <= max_i (rad/s); returns them and the ratio (1: nothing cut)."""
    ratio = max(map(operator.truediv, map(abs, qd_rad_s), max_rad_s))
    if ratio > 1.0:
        return [v / ratio for v in qd_rad_s], ratio
    return qd_rad_s, 1.0


@dataclass(frozen=True)
class CompensationTerms:
    """The dynamic compensation's terms at one joint state (q, q'), in floats:
    q'_ref = base + (H^-1 M0(q)) q''_ref with q''_ref = q''_c + Kd (q'_c - q').

    Everything but q'_c depends on the joint state only, so the teleoperation cycle
    prepares these with the rest of its joint-state terms, ahead of the handle sample,
    and keeps a 6x6 product of floats for the cycle itself. The same numbers as one
    Newton-Euler pass (pin.rnea) at q''_ref, to rounding.
    """

    # Lists, never written once built.
    qd_rad_s: list[float]  # the measured q' they were computed at
    mass_over_kv_s: list[list[float]]  # rows of H^-1 M0(q) (kg m^2 / N m s)
    base_rad_s: list[float]  # q' + H^-1 (c0 + g0 + D q')


def compensation_terms(arm: ArmModel, q_rad: np.ndarray, qd_rad_s: np.ndarray) -> CompensationTerms:
    """:class:`CompensationTerms` at (q, q'); writes ``arm.data`` (Pinocchio scratch)."""
    servo = arm.servo
    mass, bias = mass_matrix_and_bias(arm, q_rad, qd_rad_s)
    qd = qd_rad_s.tolist()
    kv = servo.kv_nms_per_rad.tolist()
    damping = servo.damping_nms_per_rad.tolist()
    # List comprehensions: tuple(generator) costs twice as much, 6 times per state.
    return CompensationTerms(
        qd_rad_s=qd,
        mass_over_kv_s=[[m / kv_i for m in row] for row, kv_i in zip(mass, kv, strict=True)],
        base_rad_s=[
            v + (b + d * v) / kv_i for v, b, d, kv_i in zip(qd, bias, damping, kv, strict=True)
        ],
    )


def velocity_reference(
    control: ControlConfig,
    terms: CompensationTerms | None,
    qd_c_rad_s: Sequence[float],
    previous_qd_c_rad_s: Sequence[float] | None,
    period_s: float,
) -> list[float]:
    """q'_ref for the velocity loops from the kinematic command q'_c, in floats.

    ``terms``: the compensation's at the measured joint state (:func:`compensation_terms`,
    computed only with ``control.compensation``), q''_c taken as the change of q'_c since
    the previous cycle (from the measured q' on the first one); None: q'_c unchanged.
    """
    if terms is None:
        return list(qd_c_rad_s)
    previous = terms.qd_rad_s if previous_qd_c_rad_s is None else previous_qd_c_rad_s
    gain = control.velocity_gain_per_s
    qdd_ref = [
        (qd_c - qd_prev) / period_s + gain * (qd_c - qd)
        for qd_c, qd_prev, qd in zip(qd_c_rad_s, previous, terms.qd_rad_s, strict=True)
    ]
    return [
        base + sum(map(operator.mul, row, qdd_ref))
        for base, row in zip(terms.base_rad_s, terms.mass_over_kv_s, strict=True)
    ]


def singular_damping_sq(control: ControlConfig, manipulability: float) -> float:
    """lambda^2 (m^2) of the damped pseudo-inverse: damping_m^2, plus up to
    singular_damping_m^2 as the manipulability w falls below singular_manipulability w0,
    smoothly: (1 - (w / w0)^2) singular_damping_m^2 (zero slope at w0 as a function of
    w^2, so the command does not jump as the arm enters the zone)."""
    base = control.damping_m * control.damping_m
    ratio = manipulability / control.singular_manipulability
    if ratio >= 1.0:
        return base
    return base + (1.0 - ratio * ratio) * control.singular_damping_m**2


def limited_joints(arm: ArmModel) -> list[tuple[int, float, float]]:
    """(joint index, lower, upper) of the arm's joints with a finite range (rad)."""
    lower = arm.model.lowerPositionLimit.tolist()
    upper = arm.model.upperPositionLimit.tolist()
    return [
        (k, lo, hi)
        for k, (lo, hi) in enumerate(zip(lower, upper, strict=True))
        if not (lo <= -CONTINUOUS_LIMIT_RAD and hi >= CONTINUOUS_LIMIT_RAD)
    ]


def joint_limit_push(
    q_rad: np.ndarray, limits: list[tuple[int, float, float]], config: ClearanceConfig
) -> list[float]:
    """Null-space joint rates (n,) in rad/s pushing each joint out of the margin at its
    limits: gain * (depth into the margin)."""
    push = [0.0] * len(q_rad)
    margin, gain = config.joint_limit_margin_rad, config.joint_limit_gain_per_s
    for k, lower, upper in limits:
        q = float(q_rad[k])
        if q > upper - margin:
            push[k] = -gain * (q - (upper - margin))
        elif q < lower + margin:
            push[k] = gain * ((lower + margin) - q)
    return push


def clearance_push(
    rows: list[tuple[float, np.ndarray]], config: ClearanceConfig
) -> np.ndarray | None:
    """Null-space joint rates pushing every close link away: each pair's distance grows at
    gain * depth m/s through the minimum-norm motion j^T / (j j^T + damping^2).
    ``rows``: (the pair's depth into its slowdown zone as :func:`push_depth_m` shapes it,
    in m; approach row j (n,))."""
    push = None
    for depth_m, row in rows:
        away = (
            config.null_space_gain_per_s * depth_m / (float(row @ row) + ROW_DAMPING_M_PER_RAD**2)
        )
        push = away * row if push is None else push + away * row
    return push


def hold_clearance(
    qd_rad_s: np.ndarray, caps: list[tuple[float, np.ndarray]]
) -> tuple[np.ndarray, int]:
    """The command changed as little as possible so that no close pair approaches faster
    than its cap: j q' >= -cap for each (cap in m/s, approach row j). Returns the command
    and how many pairs needed it.

    Projections onto each violated half-space in turn (HOLD_PASSES sweeps): the motion
    along the pair's normal is cut, the rest of the motion (along the obstacle) is kept.
    """
    held: set[int] = set()
    for _ in range(HOLD_PASSES):
        changed = False
        for index, (cap, row) in enumerate(caps):
            rate = float(row @ qd_rad_s)
            if rate < -cap:
                qd_rad_s = (
                    qd_rad_s + ((-cap - rate) / (float(row @ row) + ROW_DAMPING_M_PER_RAD**2)) * row
                )
                held.add(index)
                changed = True
        if not changed:
            break
    return qd_rad_s, len(held)


def joint_limit_hold(
    q_rad: np.ndarray,
    qd_rad_s: list[float],
    limits: list[tuple[int, float, float]],
    config: ClearanceConfig,
) -> list[float]:
    """Each joint's rate toward a limit scaled by its distance to it over the margin (1
    outside the margin, 0 at the limit); rates away from the limit are kept."""
    margin = config.joint_limit_margin_rad
    out = qd_rad_s
    for k, lower, upper in limits:
        q, rate = float(q_rad[k]), float(qd_rad_s[k])
        room = upper - q if rate > 0 else q - lower
        if rate != 0.0 and room < margin:
            if out is qd_rad_s:
                out = qd_rad_s.copy()
            out[k] = rate * max(room, 0.0) / margin
    return out


class PathFollowingController:
    """Experiment 1: follow the desired path with no time law, maximising manipulability.

    Holds only what must persist between cycles: the tracked path parameter, the arc
    length followed and the previous kinematic command (to differentiate it for the
    compensation). ``clearance``: measures the arm's clearance every cycle (and, with
    ``clearance.avoid``, keeps it); None: neither.
    """

    def __init__(
        self,
        arm: ArmModel,
        control: ControlConfig,
        path: PathConfig,
        period_s: float,
        clearance: ClearanceModel | None = None,
    ) -> None:
        self.arm = arm
        self.control = control
        self.path = DesiredPath(path)
        self.period_s = period_s
        self.clearance = clearance
        self._max_speed_rad_s = np.minimum(
            control.max_joint_speed_rad_s, arm.servo.max_speed_rad_s
        ).tolist()
        self._limits = limited_joints(arm)
        self._s: float | None = None
        self._arc_m = 0.0
        self._previous_qd_c: list[float] | None = None

    def reset(self) -> None:
        self._s = None
        self._arc_m = 0.0
        self._previous_qd_c = None

    def update(
        self, q_rad: np.ndarray, qd_rad_s: np.ndarray, gripper_opening_m: float | None = None
    ) -> ControlOutput:
        """One control cycle from the measured joint state (``gripper_opening_m``: each
        finger's slide, for the clearance; None: fully open).

        The law's arithmetic on 3-vectors and joint vectors is in Python floats: at this
        size each numpy call costs more than the arithmetic it does, and the cycle runs
        once per exchange in every run."""
        ctl = self.control
        tool_p, jacobian = tool_position_and_jacobian(self.arm, q_rad)
        s = self._track(tool_p)
        desired = self.path.point(s)
        v_task, error_norm, speed = self._task_velocity(tool_p, desired, s)

        # J# v + (I - J# J) g, g the null-space objective: maximise the manipulability and,
        # with clearance.avoid, push links away from what is near and joints off their limits.
        w, w_gradient = manipulability_and_gradient(jacobian)
        g = [ctl.null_space_gain * v for v in w_gradient]
        clearance, caps = None, []
        if self.clearance is not None:
            clearance = self.clearance.measure(
                q_rad, self.clearance.open_m if gripper_opening_m is None else gripper_opening_m
            )
            if self.clearance.config.avoid:
                g, caps = self._avoidance(q_rad, qd_rad_s, clearance, g)
        rows = jacobian[:3].tolist()
        qd_c = damped_least_squares(rows, singular_damping_sq(ctl, w), v_task, g)
        if qd_c is None:  # undamped at an exact singularity: the least-squares solution
            jv = jacobian[:3]
            qd_c = (np.linalg.pinv(jv) @ (np.array(v_task) - jv @ g) + g).tolist()
        held = 0
        if caps:
            held_qd_c, held = hold_clearance(np.array(qd_c), caps)
            qd_c = held_qd_c.tolist()
        if self.clearance is not None and self.clearance.config.avoid and self._limits:
            qd_c = joint_limit_hold(q_rad, qd_c, self._limits, self.clearance.config)
        qd_c, _ = limit_speed(qd_c, self._max_speed_rad_s)
        # control.max_tool_speed_m_s, below the plant's limit: the plant's cut would make the
        # velocity loops track another direction than the one the clearance was held on.
        # Scaled down whole, the caps still hold.
        tool_v = [sum(map(operator.mul, row, qd_c)) for row in rows]
        tool_speed_m_s = math.sqrt(sum(v * v for v in tool_v))
        if tool_speed_m_s > ctl.max_tool_speed_m_s:
            cut = ctl.max_tool_speed_m_s / tool_speed_m_s
            qd_c = [v * cut for v in qd_c]

        compensation = compensation_terms(self.arm, q_rad, qd_rad_s) if ctl.compensation else None
        qd_ref = velocity_reference(ctl, compensation, qd_c, self._previous_qd_c, self.period_s)
        self._previous_qd_c = qd_c
        if caps:
            # The compensation adds the velocity loops' dynamics to q'_c: the reference
            # the plant applies must keep the caps too, or a fast arm braking on q'_c
            # still closes in through q'_ref (the measured rate lags q'_c).
            held_qd_ref, _ = hold_clearance(np.array(qd_ref), caps)
            qd_ref = held_qd_ref.tolist()
        return ControlOutput(
            qd_ref_rad_s=np.array(limit_speed(qd_ref, self._max_speed_rad_s)[0]),
            qd_c_rad_s=np.array(qd_c),
            tool_p_m=tool_p,
            desired_p_m=np.array(desired),
            path_error_m=error_norm,
            manipulability=w,
            path_s=s,
            path_arc_m=self._arc_m,
            path_speed_m_s=speed,
            clearance=clearance,
            held_pairs=held,
        )

    def _task_velocity(
        self, tool_p_m: np.ndarray, desired_p_m: tuple[float, float, float], s: float
    ) -> tuple[tuple[float, float, float], float, float]:
        """v_hd + K e0 tanh(h~ / e0): the path's tangent at the speed v_P / (1 + k |h~|)
        plus the saturated pull back onto the path (world frame, m/s); with |h~| (m) and
        that speed (m/s)."""
        ctl = self.control
        px, py, pz = tool_p_m.tolist()
        ex, ey, ez = desired_p_m[0] - px, desired_p_m[1] - py, desired_p_m[2] - pz
        error_norm = math.sqrt(ex * ex + ey * ey + ez * ez)
        (tx, ty, tz), _ = self.path.derivatives(s)
        speed = ctl.path_speed_m_s / (1.0 + ctl.speed_error_gain_per_m * error_norm)
        along = speed / math.sqrt(tx * tx + ty * ty + tz * tz)
        e0 = ctl.position_saturation_m
        pull = ctl.position_gain_per_s * e0
        v_task = (
            tx * along + pull * math.tanh(ex / e0),
            ty * along + pull * math.tanh(ey / e0),
            tz * along + pull * math.tanh(ez / e0),
        )
        return v_task, error_norm, speed

    def _track(self, tool_p_m: np.ndarray) -> float:
        """The path parameter s* of the point closest to the tool, followed from the last
        cycle's (searched over the whole path on the first), and the arc length the
        tracked point has travelled (the midpoint rule on |P'(s)|)."""
        if self._s is None:
            self._s = self.path.closest_global(tool_p_m)
            return self._s
        previous_s = self._s
        self._s = self.path.closest_local(tool_p_m, previous_s)
        (tx, ty, tz), _ = self.path.derivatives(0.5 * (previous_s + self._s))
        self._arc_m += (self._s - previous_s) * math.sqrt(tx * tx + ty * ty + tz * tz)
        return self._s

    def _avoidance(
        self, q_rad: np.ndarray, qd_rad_s: np.ndarray, clearance: Clearance, g: list[float]
    ) -> tuple[list[float], list[tuple[float, np.ndarray]]]:
        """The null-space objective with the clearance and joint-limit pushes added, and
        the approach caps (cap m/s, row) of the pairs inside their slowdown distance, at
        their closing speed measured from ``qd_rad_s``. Reads the joint Jacobians at
        ``q_rad`` that the tool Jacobian left in arm.data."""
        config = self.clearance.config if self.clearance is not None else None
        assert config is not None
        close = close_pairs(config, self.arm, clearance, qd_rad_s)
        caps = [(c.cap_m_s, c.row) for c in close]
        push = clearance_push([(c.push_depth_m, c.row) for c in close], config)
        if push is not None:
            g = list(map(operator.add, g, push.tolist()))
        if self._limits:
            g = list(map(operator.add, g, joint_limit_push(q_rad, self._limits, config)))
        return g, caps


@dataclass(frozen=True)
class MotionEvent:
    """A run event the metrics saw (sent as a RUN_EVENT by the controller service)."""

    event: Event
    sim_time_s: float
    value: float


class MotionSafety:
    """What both tasks report about safe motion, from each cycle's clearance and
    manipulability: the smallest clearance of each kind, the cycles in unintended
    contact, the singularity crossings, and the events of their beginnings (CONTACT,
    SINGULARITY; value: the distance in m, the manipulability)."""

    def __init__(self, singularity_manipulability: float) -> None:
        self.singularity_manipulability = singularity_manipulability
        self.min_scene_m = math.inf
        self.min_finger_m = math.inf
        self.min_self_m = math.inf
        self.contact_cycles = 0
        self.singularity_crossings = 0
        self.events: list[MotionEvent] = []
        self._in_contact = False
        self._singular = False

    def add(
        self, sim_time_s: float, clearance: Clearance | None, manipulability: float | None
    ) -> None:
        if clearance is not None:
            self.min_scene_m = min(self.min_scene_m, clearance.min_scene_m)
            self.min_finger_m = min(self.min_finger_m, clearance.min_finger_m)
            self.min_self_m = min(self.min_self_m, clearance.min_self_m)
            contact = clearance.in_contact
            if contact:
                self.contact_cycles += 1
                if not self._in_contact:
                    self.events.append(MotionEvent(Event.CONTACT, sim_time_s, clearance.min_m))
            self._in_contact = contact
        if manipulability is not None:
            singular = manipulability < self.singularity_manipulability
            if singular and not self._singular:
                self.singularity_crossings += 1
                self.events.append(MotionEvent(Event.SINGULARITY, sim_time_s, manipulability))
            self._singular = singular

    def take_events(self) -> list[MotionEvent]:
        """The events seen since the last call (oldest first)."""
        events, self.events = self.events, []
        return events

    def summary(self) -> dict[str, Any]:
        measured = math.isfinite(self.min_scene_m)
        overall = min(self.min_scene_m, self.min_finger_m, self.min_self_m)
        return {
            "min_clearance_m": overall if measured else None,
            "min_clearance_scene_m": self.min_scene_m if measured else None,
            "min_clearance_finger_m": self.min_finger_m if measured else None,
            "min_clearance_self_m": self.min_self_m if measured else None,
            "arm_contacts": self.contact_cycles if measured else None,
            "singularity_crossings": self.singularity_crossings,
        }

    def problems(self) -> list[str]:
        """One line per reason the motion was not safe (empty: none)."""
        if not self.contact_cycles:
            return []
        overall = min(self.min_scene_m, self.min_finger_m, self.min_self_m)
        return [
            f"unintended contact in {self.contact_cycles} control cycle(s) "
            f"(min clearance {overall * 1e3:.1f} mm)"
        ]


class PathMetrics:
    """Accumulates the path-following figures of merit.

    After the settling time: the path error, and ``path_progress``, the arc length of the
    path followed over the arc length the nominal speed v_P covers in the same time.
    Over the whole run: ``stalled_s``, the time in windows of ``clearance.stall_window_s``
    during which the tool made less progress than ``clearance.stall_progress`` of what the
    speed commanded along the path (v_P / (1 + k |h~|)) covers, progress being the arc
    followed plus the fall of the path error (on the way in from far, the tool closes in
    on the path while the closest point barely moves); a STALL event when a stall begins
    (value: the path error, m), and the clearance, contacts and singularity crossings
    (:class:`MotionSafety`).

    A cycle on a state the plant's watchdog braked in (``commanded=False``: no command
    moved the tool) is not a stall: the window starts afresh at the next commanded one. A
    frozen or restarted controller is the fault's business (its brake and resume times),
    not the motion's.
    """

    def __init__(
        self,
        settle_s: float,
        path_speed_m_s: float = 0.0,
        clearance: ClearanceConfig | None = None,
        singularity_manipulability: float = 0.0,
    ) -> None:
        self.settle_s = settle_s
        self.path_speed_m_s = path_speed_m_s
        stall = clearance if clearance is not None else ClearanceConfig()
        self.stall_window_s = stall.stall_window_s
        self.stall_progress = stall.stall_progress
        # The path error after settling, as running figures: a list of every cycle's grew
        # 32 B per cycle (32 KB/s at 1 kHz) under a `teleop up` that runs for hours.
        self.error_count = 0
        self.error_sq_sum_m2 = 0.0
        self.error_max_m = 0.0
        self.min_manipulability = float("inf")
        self.safety = MotionSafety(singularity_manipulability)
        self.stalled_s = 0.0
        self.stalls = 0
        self._settled: tuple[float, float] | None = None  # (sim time, arc) at settling
        self._last: tuple[float, float] | None = None  # (sim time, arc) of the newest cycle
        # (sim time, arc, path error) at the window's start, and the arc the commanded
        # speed covered since
        self._window: tuple[float, float, float] | None = None
        self._window_expected_m = 0.0
        self._stalled = False
        self._previous_s = 0.0

    @classmethod
    def for_config(cls, config: Config) -> PathMetrics:
        return cls(
            settle_s=config.run.settle_s,
            path_speed_m_s=config.control.path_speed_m_s,
            clearance=config.clearance,
            singularity_manipulability=config.control.singularity_event_manipulability,
        )

    @property
    def events(self) -> list[MotionEvent]:
        return self.safety.events

    def take_events(self) -> list[MotionEvent]:
        return self.safety.take_events()

    def add(self, sim_time_s: float, output: ControlOutput, commanded: bool = True) -> None:
        """One control cycle at ``sim_time_s``; ``commanded``: the state it answers was
        moved by commands (not held by the plant's brake)."""
        self.min_manipulability = min(self.min_manipulability, output.manipulability)
        if sim_time_s >= self.settle_s:
            error_m = output.path_error_m
            self.error_count += 1
            self.error_sq_sum_m2 += error_m * error_m
            self.error_max_m = max(self.error_max_m, error_m)
            if self._settled is None:
                self._settled = (sim_time_s, output.path_arc_m)
        self._last = (sim_time_s, output.path_arc_m)
        self.safety.add(sim_time_s, output.clearance, output.manipulability)
        if self.path_speed_m_s > 0:
            if commanded:
                self._check_stall(sim_time_s, output)
            else:
                self._window = None  # held, not commanded: a new window once commanded

    def _check_stall(self, sim_time_s: float, output: ControlOutput) -> None:
        if self._window is None:
            self._window = (sim_time_s, output.path_arc_m, output.path_error_m)
            self._window_expected_m = 0.0
            self._previous_s = sim_time_s
            return
        self._window_expected_m += output.path_speed_m_s * (sim_time_s - self._previous_s)
        self._previous_s = sim_time_s
        start_s, start_arc, start_error_m = self._window
        elapsed = sim_time_s - start_s
        if elapsed < self.stall_window_s:
            return
        expected, self._window_expected_m = self._window_expected_m, 0.0
        closed_in_m = max(start_error_m - output.path_error_m, 0.0)
        progress_m = output.path_arc_m - start_arc + closed_in_m
        stalled = progress_m < self.stall_progress * expected
        if stalled:
            self.stalled_s += elapsed
            if not self._stalled:
                self.stalls += 1
                self.safety.events.append(MotionEvent(Event.STALL, sim_time_s, output.path_error_m))
        self._stalled = stalled
        self._window = (sim_time_s, output.path_arc_m, output.path_error_m)

    def path_progress(self) -> float | None:
        if self._settled is None or self._last is None or self.path_speed_m_s <= 0:
            return None
        (t0, arc0), (t1, arc1) = self._settled, self._last
        if t1 <= t0:
            return None
        return (arc1 - arc0) / (self.path_speed_m_s * (t1 - t0))

    def problems(self) -> list[str]:
        """One line per reason the run is not good (empty: none)."""
        problems = []
        if self.stalled_s > 0:
            progress = self.path_progress()
            shown = f", path_progress {progress:.2f}" if progress is not None else ""
            problems.append(
                f"the tool stalled {self.stalled_s:.1f} s in {self.stalls} stall(s){shown}"
            )
        return problems + self.safety.problems()

    def summary(self) -> dict[str, Any]:
        figures: dict[str, Any] = {
            "path_error_rms_m": None,
            "path_error_max_m": None,
            "min_manipulability": self.min_manipulability,
        }
        if self.error_count:
            figures["path_error_rms_m"] = math.sqrt(self.error_sq_sum_m2 / self.error_count)
            figures["path_error_max_m"] = self.error_max_m
            figures["min_manipulability"] = float(self.min_manipulability)
        return {
            **figures,
            "path_progress": self.path_progress(),
            "stalled_s": self.stalled_s,
            "stalls": self.stalls,
            **self.safety.summary(),
            "motion_problems": self.problems(),
        }
