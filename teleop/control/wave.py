"""Wave variables for the force channel under delay (``teleop.stabiliser = "wave"``).

Niemeyer and Slotine's scattering transform: instead of a velocity one way and a force
the other, each side sends a wave that mixes the two with a wave impedance ``b``
(N s/m, ``teleop.wave_impedance_n_s_m``)::

    u = (b r + e) / sqrt(2 b)      toward the robot     r: speed (m/s), e: force (N)
    v = (b r - e) / sqrt(2 b)      back to the handle   r e = (u^2 - v^2) / 2

The power a side puts into the channel is the difference of its waves' squares, so a
channel that only delays them stores the energy in flight and gives none back that was
not put in: it is passive under any constant delay, where the same delay on the plain
signals makes a stiff contact rattle (docs/sites.md).

The robot's end is matched to the channel: it adds a damper ``b`` to the robot's
resistance, so a wave that meets free motion is not sent back. A rate-commanded robot
resists nothing in free motion; unmatched, every wave would return whole and the rate
would ring at the round trip's period. With the match the robot's rate is the handle's
one trip after it was set, the wave back carries the robot's resistance alone, and the
handle feels that resistance a round trip late plus the damper ``b r``: the price of
passivity in transparency (``teleop.wave_impedance_n_s_m`` trades that drag against how
hard a contact must push to stop the tool).

In this rate control the speed is the handle's rate command, device frame: the offset
beyond the deadband times ``rate_gain_per_s``, capped at ``max_tool_speed_m_s``, zero
while the clutch is held (:func:`handle_rate_m_s`); the force ``e`` is what resists it,
the opposite of the force the handle renders. The handle's side (:func:`handle_wave`,
:func:`handle_resistance_n`) runs in the haptic service, the robot's side
(:class:`RobotWavePort`) in the controller: it decodes the tool's rate from the wave and
the robot's resistance (the feedback force of the contact, the weight, the obstacles,
the scene and the limits, without the handle's own workspace spring, which the handle
renders itself), and sends the wave back. Device frame throughout, vectors (3,).

Pure: the services call it under their own locks.
"""

from __future__ import annotations

import math

import numpy as np

from teleop.control.rate import device_rate
from teleop.core.config import TeleopConfig


def handle_rate_m_s(device_d_m: np.ndarray, clutch: bool, cfg: TeleopConfig) -> np.ndarray:
    """The handle's rate command (3,), m/s, device frame: the rate control's mapping of
    the offset ``device_d_m`` before the view's rotation (zero with the clutch held)."""
    return np.zeros(3) if clutch else np.array(device_rate(device_d_m, cfg))


def handle_resistance_n(rate_m_s: np.ndarray, v_wave: np.ndarray, b_n_s_m: float) -> np.ndarray:
    """The channel's resistance at the handle (N, device frame) from the handle's rate and
    the wave that came back: ``e = b r - sqrt(2 b) v``. The handle renders ``-e``."""
    return b_n_s_m * np.asarray(rate_m_s) - math.sqrt(2.0 * b_n_s_m) * np.asarray(v_wave)


def handle_wave(rate_m_s: np.ndarray, v_wave: np.ndarray, b_n_s_m: float) -> np.ndarray:
    """The wave the handle sends toward the robot: ``u = (b r + e) / sqrt(2 b)`` with the
    resistance ``e`` of :func:`handle_resistance_n`, i.e. ``sqrt(2 b) r - v``."""
    return math.sqrt(2.0 * b_n_s_m) * np.asarray(rate_m_s) - np.asarray(v_wave)


class RobotWavePort:
    """The robot's end of the channel, matched: the tool's rate from the wave that came,
    the wave back from the robot's resistance (see the module's docstring).

    :meth:`resist` takes the newest resistance (from a plant state), :meth:`rate` decodes
    a handle's wave with it, :meth:`wave_back` encodes the newest rate and resistance. In
    lockstep one tick does all three in that order; in realtime the feedback of a state
    does ``resist`` then ``wave_back``, a handle sample ``rate``.
    """

    def __init__(self, b_n_s_m: float) -> None:
        if b_n_s_m <= 0:
            raise ValueError("the wave impedance must be > 0")
        self.b_n_s_m = b_n_s_m
        self._root_2b = math.sqrt(2.0 * b_n_s_m)
        self.reset()

    def reset(self) -> None:
        """A new run: nothing in flight, at rest."""
        self.rate_m_s = np.zeros(3)
        self.resistance_n = np.zeros(3)

    def resist(self, resistance_n: np.ndarray) -> None:
        """The robot's newest resistance (N, device frame: minus the feedback force)."""
        self.resistance_n = np.asarray(resistance_n, dtype=np.float64)

    def rate(self, u_wave: np.ndarray) -> np.ndarray:
        """The tool's rate (m/s, device frame) the wave ``u`` asks against the newest
        resistance ``e`` and the matching damper: ``r = (sqrt(2 b) u - e - b r) / b``,
        i.e. ``(sqrt(2 b) u - e) / (2 b)``."""
        self.rate_m_s = (self._root_2b * np.asarray(u_wave) - self.resistance_n) / (
            2.0 * self.b_n_s_m
        )
        return self.rate_m_s

    def wave_back(self) -> np.ndarray:
        """The wave back to the handle: ``(b r - (e + b r)) / sqrt(2 b) = -e / sqrt(2 b)``
        (the matching damper's part cancels: nothing of free motion comes back)."""
        return -self.resistance_n / self._root_2b
