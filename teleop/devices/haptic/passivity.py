"""Time-domain passivity at the haptic device: an observer of the energy the force
channel exchanges with the operator, and a controller that dissipates what it would
otherwise give out (Hannaford and Ryu's one-port passivity observer and controller).

Seen from the handle, everything behind the rendered force (the link to the robot, its
delay, the controller, the plant, the contact) is one port: the device applies
``f`` to the handle, which moves at ``v``. A passive environment never returns more
energy than the operator put in::

    W(k) = - sum_j f_j . v_j dt >= 0     (j <= k: the observed energy, J)

Delay makes the environment active: a force that answers where the handle was, not
where it is, pushes the hand along its motion and W falls below zero. The controller
then adds a damper ``-alpha v`` to the next force, axis by axis (each axis its own
port, whose energies sum to W), with ``alpha`` just large enough to bring that axis's
energy back to zero (at most ``max_damping_n_s_m``, a damping the device renders
stably), and nothing while that energy is positive: a passive environment is
rendered unchanged.

The observer runs whatever the ``teleop.stabiliser`` (the energy goes to the haptic
service's summary and the run's, ``passivity``: with ``none`` it shows how active the
channel is); the controller acts with ``tdpa`` only.
Pure and single-threaded: the haptic loop calls it under its own lock.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

# Below this squared speed (m^2/s^2) a damper can dissipate nothing worth its force.
_STILL_M2_S2 = 1e-10


class PassivityControl:
    """The observer and (``enabled``) the controller of one haptic device, period
    ``dt_s``."""

    def __init__(self, enabled: bool, max_damping_n_s_m: float, dt_s: float) -> None:
        if max_damping_n_s_m < 0 or dt_s <= 0:
            raise ValueError("max_damping_n_s_m >= 0 and dt_s > 0")
        self.enabled = enabled
        self.max_damping_n_s_m = max_damping_n_s_m
        self.dt_s = dt_s
        self.reset()

    def reset(self) -> None:
        """A new run: no energy exchanged yet."""
        self.observed_j = 0.0  # W: energy the environment took from the operator, net
        self.observer_min_j = 0.0
        self.energy_in_j = 0.0  # from the operator into the environment
        self.energy_out_j = 0.0  # from the environment to the operator
        self.dissipated_j = 0.0  # by the controller's damping
        self.active_steps = 0  # steps the controller damped
        self.correction_max_n = 0.0  # the largest force the controller took out
        self._velocity = [0.0] * 3
        self._axis_j = [0.0] * 3  # W of each device axis (their sum: observed_j)

    def observe(self, rendered_f_n: np.ndarray, v_m_s: np.ndarray) -> None:
        """One device period: the force the motors rendered during it and the handle's
        velocity at its end."""
        # Python floats: cheaper than numpy at this size, every servo period.
        dt_s, velocity = self.dt_s, v_m_s.tolist()
        axis_j = [-f * v * dt_s for f, v in zip(rendered_f_n.tolist(), velocity, strict=True)]
        energy_j = axis_j[0] + axis_j[1] + axis_j[2]  # into the environment
        if energy_j >= 0:
            self.energy_in_j += energy_j
        else:
            self.energy_out_j -= energy_j
        self._axis_j = [w + a for w, a in zip(self._axis_j, axis_j, strict=True)]
        self.observed_j += energy_j
        self.observer_min_j = min(self.observer_min_j, self.observed_j)
        self._velocity = velocity

    def control(self, force_n: np.ndarray) -> np.ndarray:
        """The force to render instead of ``force_n``: unchanged unless enabled and an
        axis's observed energy would fall below zero, else with the damping on that axis
        that keeps it at zero (at the newest observed velocity).

        Axis by axis, each its own one-port (their sum is the observed energy, so it
        stays at or above zero with them): a damper along the whole velocity vector
        would, from a handle's noisy velocity estimate (20 um encoders: about 1 cm/s of
        noise on an axis at rest), move a push along one axis into the others rather
        than take it out."""
        if not self.enabled:
            return force_n
        force = np.array(force_n, dtype=np.float64)
        correction = np.zeros(3)
        for axis in range(3):
            v = float(self._velocity[axis])
            speed2 = v * v
            predicted_j = float(self._axis_j[axis]) - float(force[axis]) * v * self.dt_s
            if predicted_j >= 0 or speed2 < _STILL_M2_S2:
                continue
            # Removing the force's whole component along the motion is always allowed (the
            # force only shrinks); damping beyond that, to restore an energy already below
            # zero, is capped at what the handle renders stably.
            along = max(float(force[axis]) * v, 0.0) / speed2
            alpha = min(-predicted_j / (speed2 * self.dt_s), along + self.max_damping_n_s_m)
            correction[axis] = alpha * v
            self.dissipated_j += alpha * speed2 * self.dt_s
        if not correction.any():
            return force_n
        self.active_steps += 1
        self.correction_max_n = max(self.correction_max_n, math.hypot(*correction.tolist()))
        return force - correction

    def summary(self, stabiliser: str) -> dict[str, Any]:
        """The energy account (J) of the run so far, JSON-ready."""
        return {
            "stabiliser": stabiliser,
            "energy_in_j": self.energy_in_j,
            "energy_out_j": self.energy_out_j,
            "observed_j": self.observed_j,
            "observer_min_j": self.observer_min_j,
            "dissipated_j": self.dissipated_j,
            "active_steps": self.active_steps,
            "correction_max_n": self.correction_max_n,
        }


def max_stable_damping_n_s_m(handle_mass_kg: float, dt_s: float) -> float:
    """The largest virtual damping a handle of ``handle_mass_kg`` renders without
    oscillating, at servo period ``dt_s`` (explicit damping: b dt / m < 2)."""
    return 2.0 * handle_mass_kg / dt_s if dt_s > 0 else math.inf
