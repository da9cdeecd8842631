"""Control laws of the paper's family: path following and dynamic compensation.

Kinematic controller (position task, redundant arm):
    q'_c = J# (v_hd + K e0 tanh(h~ / e0)) + (I - J# J) L grad w(q)
with h~ = P(s*) - h the error to the closest path point P(s*), v_hd the desired
velocity along the path's tangent with speed v_P / (1 + k |h~|), J# the (damped)
pseudo-inverse of the 3xN position Jacobian and w the manipulability.

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
from dataclasses import dataclass, field

import numpy as np

from teleop.control.kinematics import (
    ArmModel,
    manipulability_and_gradient,
    mass_matrix_and_bias,
    symmetric_3x3_inverse,
    tool_position_and_jacobian,
)
from teleop.core.config import ControlConfig, PathConfig

# Closest-point search: samples per path period for the first, global search, and
# Newton iterations for the local refinement that follows the point along the path.
GLOBAL_SEARCH_SAMPLES = 720
NEWTON_ITERATIONS = 3


class DesiredPath:
    """The paper's path P(s), its derivatives, and the closest point to a given point."""

    def __init__(self, config: PathConfig) -> None:
        self.center_m = np.asarray(config.center_m, dtype=float)
        self.radius_m = config.radius_m
        self.omega = config.omega_rad
        self.z_amplitude_m = config.z_amplitude_m
        self.z_omega = config.z_omega_rad
        # Start-up search window: one period of the slower of the two motions.
        slowest = (
            min(self.omega, self.z_omega) if self.z_amplitude_m and self.z_omega else self.omega
        )
        self.search_window_s = 2 * np.pi / slowest

    def point(self, s: float) -> np.ndarray:
        """P(s) in m, world frame."""
        return np.array(self._point(s))

    def _point(self, s: float) -> tuple[float, float, float]:
        c = self.center_m
        return (
            self.radius_m * math.sin(self.omega * s) + c[0],
            self.radius_m * math.cos(self.omega * s) + c[1],
            self.z_amplitude_m * math.sin(self.z_omega * s) + c[2],
        )

    def derivatives(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """(dP/ds, d2P/ds2) at s."""
        first, second = self._derivatives(s)
        return np.array(first), np.array(second)

    def _derivatives(self, s: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
        r, w, a, wz = self.radius_m, self.omega, self.z_amplitude_m, self.z_omega
        sin_ws, cos_ws = math.sin(w * s), math.cos(w * s)
        sin_wzs, cos_wzs = math.sin(wz * s), math.cos(wz * s)
        first = (r * w * cos_ws, -r * w * sin_ws, a * wz * cos_wzs)
        second = (-r * w * w * sin_ws, -r * w * w * cos_ws, -a * wz * wz * sin_wzs)
        return first, second

    def closest_global(self, p_m: np.ndarray) -> float:
        """Path parameter of the closest point over one whole period (start-up)."""
        samples = np.linspace(0.0, self.search_window_s, GLOBAL_SEARCH_SAMPLES, endpoint=False)
        points = np.stack([self.point(s) for s in samples])
        s0 = float(samples[np.argmin(np.linalg.norm(points - p_m, axis=1))])
        return self.closest_local(p_m, s0)

    def closest_local(self, p_m: np.ndarray, s_guess: float) -> float:
        """Refine the closest point near ``s_guess`` (Newton on (P(s) - p) . P'(s) = 0).

        Scalar arithmetic on purpose: this runs every control cycle, and three small
        numpy arrays per iteration cost more than the math itself.
        """
        px, py, pz = (float(v) for v in p_m)
        s = s_guess
        for _ in range(NEWTON_ITERATIONS):
            x, y, z = self._point(s)
            dx, dy, dz = x - px, y - py, z - pz
            (f1, f2, f3), (g1, g2, g3) = self._derivatives(s)
            slope = f1 * f1 + f2 * f2 + f3 * f3 + dx * g1 + dy * g2 + dz * g3
            if slope <= 0:
                break
            s -= (dx * f1 + dy * f2 + dz * f3) / slope
        return s


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


def limit_speed(qd_rad_s: np.ndarray, max_rad_s: np.ndarray | float) -> np.ndarray:
    """Scale the whole vector down (keeping its direction) so every joint is within limits."""
    ratio = float((np.abs(qd_rad_s) / max_rad_s).max())
    return qd_rad_s / ratio if ratio > 1.0 else qd_rad_s


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


class PathFollowingController:
    """Experiment 1: follow the desired path with no time law, maximising manipulability.

    Holds only what must persist between cycles: the tracked path parameter and the
    previous kinematic command (to differentiate it for the compensation).
    """

    def __init__(
        self, arm: ArmModel, control: ControlConfig, path: PathConfig, period_s: float
    ) -> None:
        self.arm = arm
        self.control = control
        self.path = DesiredPath(path)
        self.period_s = period_s
        self.max_speed_rad_s = np.minimum(control.max_joint_speed_rad_s, arm.servo.max_speed_rad_s)
        self._damping_matrix = control.damping_m**2 * np.eye(3)
        self._s: float | None = None
        self._previous_qd_c: list[float] | None = None

    def reset(self) -> None:
        self._s = None
        self._previous_qd_c = None

    def update(self, q_rad: np.ndarray, qd_rad_s: np.ndarray) -> ControlOutput:
        """One control cycle from the measured joint state."""
        ctl = self.control
        tool_p, jacobian = tool_position_and_jacobian(self.arm, q_rad)
        jv = jacobian[:3]
        if self._s is None:
            self._s = self.path.closest_global(tool_p)
        else:
            self._s = self.path.closest_local(tool_p, self._s)
        desired_p = self.path.point(self._s)
        error = desired_p - tool_p
        error_norm = math.sqrt(float(error @ error))
        tangent, _ = self.path.derivatives(self._s)
        speed = ctl.path_speed_m_s / (1.0 + ctl.speed_error_gain_per_m * error_norm)
        v_desired = tangent * (speed / math.sqrt(float(tangent @ tangent)))
        e0 = ctl.position_saturation_m
        v_task = v_desired + ctl.position_gain_per_s * e0 * np.tanh(error / e0)

        # J# v + (I - J# J) g with J# = J^T A^-1, A = J J^T + damping^2 I, in one solve:
        # J^T A^-1 (v - J g) + g, where g = L grad w is the null-space objective.
        w, w_gradient = manipulability_and_gradient(jacobian)
        g = ctl.null_space_gain * w_gradient
        inverse, det = symmetric_3x3_inverse(jv @ jv.T + self._damping_matrix)
        if det > 0.0:
            qd_c = jv.T @ (inverse @ (v_task - jv @ g)) + g
        else:  # undamped at an exact singularity: the least-squares solution
            qd_c = np.linalg.pinv(jv) @ (v_task - jv @ g) + g
        qd_c = limit_speed(qd_c, self.max_speed_rad_s)

        compensation = compensation_terms(self.arm, q_rad, qd_rad_s) if ctl.compensation else None
        qd_ref = np.array(
            velocity_reference(ctl, compensation, qd_c.tolist(), self._previous_qd_c, self.period_s)
        )
        self._previous_qd_c = qd_c.tolist()
        return ControlOutput(
            qd_ref_rad_s=limit_speed(qd_ref, self.max_speed_rad_s),
            qd_c_rad_s=qd_c,
            tool_p_m=tool_p,
            desired_p_m=desired_p,
            path_error_m=error_norm,
            manipulability=w,
            path_s=self._s,
        )


@dataclass
class PathMetrics:
    """Accumulates the path-following figures of merit, after the settling time."""

    settle_s: float
    errors_m: list[float] = field(default_factory=list)
    min_manipulability: float = float("inf")

    def add(self, sim_time_s: float, output: ControlOutput) -> None:
        self.min_manipulability = min(self.min_manipulability, output.manipulability)
        if sim_time_s >= self.settle_s:
            self.errors_m.append(output.path_error_m)

    def summary(self) -> dict[str, float | None]:
        if not self.errors_m:
            return {
                "path_error_rms_m": None,
                "path_error_max_m": None,
                "min_manipulability": self.min_manipulability,
            }
        errors = np.asarray(self.errors_m)
        return {
            "path_error_rms_m": float(np.sqrt(np.mean(errors**2))),
            "path_error_max_m": float(errors.max()),
            "min_manipulability": float(self.min_manipulability),
        }
