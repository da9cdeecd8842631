"""The paper's desired path P(s): a circle in a horizontal plane with a vertical
oscillation, its derivatives, and the closest point to a given one.

Geometry only (numpy and the config): the controller follows it
(:class:`teleop.control.path.PathFollowingController`), the recorder draws it, the
tasks place their targets on it.
"""

from __future__ import annotations

import math

import numpy as np

from teleop.core.config import PathConfig

# Closest-point search: samples per path period for the first, global search, and
# Newton iterations for the local refinement that follows the point along the path.
GLOBAL_SEARCH_SAMPLES = 720
NEWTON_ITERATIONS = 3


class DesiredPath:
    """The paper's path P(s), its derivatives, and the closest point to a given point."""

    def __init__(self, config: PathConfig) -> None:
        self.center_m = tuple(float(v) for v in config.center_m)
        self.radius_m = config.radius_m
        self.omega = config.omega_rad
        self.z_amplitude_m = config.z_amplitude_m
        self.z_omega = config.z_omega_rad
        # Start-up search window: one period of the slower of the two motions.
        slowest = (
            min(self.omega, self.z_omega) if self.z_amplitude_m and self.z_omega else self.omega
        )
        self.search_window_s = 2 * np.pi / slowest

    def point(self, s: float) -> tuple[float, float, float]:
        """P(s) in m, world frame. Python floats: the controller takes it every cycle, where
        a 3-vector's numpy calls cost more than its arithmetic."""
        c = self.center_m
        return (
            self.radius_m * math.sin(self.omega * s) + c[0],
            self.radius_m * math.cos(self.omega * s) + c[1],
            self.z_amplitude_m * math.sin(self.z_omega * s) + c[2],
        )

    def derivatives(
        self, s: float
    ) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """(dP/ds, d2P/ds2) at s, in m per unit of s and its square."""
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
            x, y, z = self.point(s)
            dx, dy, dz = x - px, y - py, z - pz
            (f1, f2, f3), (g1, g2, g3) = self.derivatives(s)
            slope = f1 * f1 + f2 * f2 + f3 * f3 + dx * g1 + dy * g2 + dz * g3
            if slope <= 0:
                break
            s -= (dx * f1 + dy * f2 + dz * f3) / slope
        return s
