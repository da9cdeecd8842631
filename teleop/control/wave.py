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

A delay that varies breaks the constant-delay argument: a wave that arrives late is
held longer than it was sent for, and waves that arrive bunched are squeezed in time, so
the channel can give out energy nobody put in (seen over a real link whose deliveries
spread by a few ms: the stiff contact rattled as without waves). :class:`WaveEnergyBank`
keeps a receiver's side passive whatever the delay does: each wave that arrives brings
the energy it carried over one sample period, and what is passed on is scaled down to
what came (the energy reservoir of time-varying-delay wave channels, e.g. Ryu and
Preusche 2007). Under a constant delay every wave is passed on whole.

Pure: the services call it under their own locks.
"""

from __future__ import annotations

import math
from typing import Any

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


class WaveEnergyBank:
    """A receiver's account of a wave channel's energy: what the waves that came brought,
    less what it passed on; a wave passed on beyond that is scaled down to it.

    ``sample_period_s``: the time one received wave stands for (the sender's period).
    ``reserve_periods``: how much unspent energy stays banked, in sample periods of the
    newest wave (a wave that came early lends its unspent energy to one that comes late;
    beyond that it is let go, which only dissipates). A small reserve empties at every
    late wave, and under a link's jitter the wave passed on ripples; whatever the
    reserve, no more is passed on than came (docs/sites.md has the figures).
    """

    # Rounding of the sums may not clip a wave passed on in step with its arrivals.
    _ROUNDING = 1e-9

    def __init__(self, sample_period_s: float, reserve_periods: float = 25.0) -> None:
        if sample_period_s <= 0 or reserve_periods < 1:
            raise ValueError("the sample period must be > 0 and the reserve >= 1 period")
        self.sample_period_s = sample_period_s
        self.reserve_periods = reserve_periods
        self.reset()

    def reset(self) -> None:
        """Nothing received, nothing banked."""
        self.banked_j = 0.0
        self.received_j = 0.0
        self.withheld_j = 0.0
        self.scaled_passes = 0

    def receive(self, wave: np.ndarray) -> None:
        """A wave arrived: the energy it brings over one sample period is banked."""
        w = np.asarray(wave, dtype=np.float64)
        brought_j = 0.5 * float(w @ w) * self.sample_period_s
        self.received_j += brought_j
        self.banked_j = min(self.banked_j + brought_j, self.reserve_periods * brought_j)

    def pass_on(self, wave: np.ndarray, dt_s: float) -> np.ndarray:
        """``wave`` for the next ``dt_s``, scaled down to the energy banked, and spent."""
        passed = self.fit(wave, dt_s)
        self.spend(passed, dt_s)
        return passed

    def fit(self, wave: np.ndarray, dt_s: float) -> np.ndarray:
        """``wave`` scaled down so that ``dt_s`` of it takes no more than is banked (a
        receiver that learns only afterwards how long it passed a wave on spends it then:
        :meth:`spend`)."""
        w = np.asarray(wave, dtype=np.float64)
        need_j = 0.5 * float(w @ w) * dt_s
        if need_j == 0.0 or need_j <= self.banked_j * (1.0 + self._ROUNDING):
            return w
        self.scaled_passes += 1
        available_j = max(self.banked_j, 0.0)
        self.withheld_j += need_j - available_j
        return w * math.sqrt(available_j / need_j)

    def spend(self, wave: np.ndarray, dt_s: float) -> None:
        """``wave`` was passed on for ``dt_s``: its energy leaves the bank (a wave held
        longer than foreseen leaves a debt that the next waves pay)."""
        w = np.asarray(wave, dtype=np.float64)
        before_j = self.banked_j
        self.banked_j -= 0.5 * float(w @ w) * dt_s
        if 0.0 > self.banked_j >= -self._ROUNDING * abs(before_j):
            self.banked_j = 0.0  # the rounding :meth:`fit` let through

    def summary(self) -> dict[str, float | int]:
        """What came, what was held back, and how often (the run's summary)."""
        return {
            "received_j": self.received_j,
            "withheld_j": self.withheld_j,
            "scaled_passes": self.scaled_passes,
        }


class RobotWavePort:
    """The robot's end of the channel, matched: the tool's rate from the wave that came,
    the wave back from the robot's resistance (see the module's docstring).

    :meth:`resist` takes the newest resistance (from a plant state), :meth:`rate` decodes
    a handle's wave with it, :meth:`wave_back` encodes the newest rate and resistance. In
    lockstep one tick does all three in that order; in realtime the feedback of a state
    does ``resist`` then ``wave_back``, a handle sample ``rate``.

    The handle's waves are passed on within the energy they brought
    (:class:`WaveEnergyBank`, one per ``sample_period_s``): each is in force until the
    next, at most ``max_hold_s`` (the plant brakes on a command older than that).

    The robot seen through the bus is not passive by itself: its resistance comes a
    period or two after the rate that caused it, and a stiff contact that lags its rate
    gives back more than it took (a spring of stiffness K lagging by t acts as a negative
    damper of about K t; at a 4 ms bus period a 1500 N/m contact outweighs the matching
    damper b and the channel rings). A passivity observer counts what the robot's
    surroundings absorbed (the rate in force times each new resistance, per period);
    when they have given out more than they took, a damper in series with them
    (:attr:`damping_n_s_m`, at most :data:`MAX_DAMPING_PER_B` times b) dissipates the
    difference over the next period: the rate is decoded against it and the wave back
    carries it (the time-domain passivity approach at the robot's port).
    """

    # The passivity controller's damper, at most this many times the wave impedance.
    MAX_DAMPING_PER_B = 20.0

    def __init__(self, b_n_s_m: float, sample_period_s: float, max_hold_s: float) -> None:
        if b_n_s_m <= 0:
            raise ValueError("the wave impedance must be > 0")
        self.b_n_s_m = b_n_s_m
        self._root_2b = math.sqrt(2.0 * b_n_s_m)
        self.bank = WaveEnergyBank(sample_period_s)
        self.max_hold_s = max_hold_s
        self.reset()

    def reset(self) -> None:
        """A new run: nothing in flight, at rest."""
        self.rate_m_s = np.zeros(3)
        self.resistance_n = np.zeros(3)
        self.bank.reset()
        self._passed_u = np.zeros(3)
        self._passed_at_s: float | None = None
        self.absorbed_j = 0.0  # by the robot's surroundings (observed)
        self.dissipated_j = 0.0  # by the series damper
        self.damping_n_s_m = 0.0
        self.damped_cycles = 0

    def resist(self, resistance_n: np.ndarray) -> None:
        """The robot's newest resistance (N, device frame: minus the feedback force), one
        period after the last: what its surroundings absorbed meanwhile is observed."""
        self.resistance_n = np.asarray(resistance_n, dtype=np.float64)
        self.absorbed_j += float(self.rate_m_s @ self.resistance_n) * self.bank.sample_period_s

    def rate(self, u_wave: np.ndarray, now_s: float) -> np.ndarray:
        """The tool's rate (m/s, device frame) the wave ``u`` that came at ``now_s`` (the
        controller's clock) asks against the newest resistance ``e``, the matching damper
        and the series damper ``d``: ``r = (sqrt(2 b) u - e - b r - d r) / b``, i.e.
        ``(sqrt(2 b) u - e) / (2 b + d)``, with ``u`` within the energy banked (the wave
        before it spent until now) and ``d`` what dissipates the surroundings' deficit."""
        if self._passed_at_s is not None:
            held_s = min(max(now_s - self._passed_at_s, 0.0), self.max_hold_s)
            self.bank.spend(self._passed_u, held_s)
        self.bank.receive(u_wave)
        period_s = self.bank.sample_period_s
        self._passed_u = self.bank.fit(u_wave, period_s)
        self._passed_at_s = now_s
        drive = self._root_2b * self._passed_u - self.resistance_n
        two_b = 2.0 * self.b_n_s_m
        self.damping_n_s_m = 0.0
        deficit_j = -(self.absorbed_j + self.dissipated_j)
        if deficit_j > 0.0:
            undamped = drive / two_b
            speed_sq = float(undamped @ undamped)
            if speed_sq > 0.0:
                self.damping_n_s_m = min(
                    deficit_j / (speed_sq * period_s), self.MAX_DAMPING_PER_B * self.b_n_s_m
                )
                self.damped_cycles += 1
        self.rate_m_s = drive / (two_b + self.damping_n_s_m)
        self.dissipated_j += self.damping_n_s_m * float(self.rate_m_s @ self.rate_m_s) * period_s
        return self.rate_m_s

    def wave_back(self) -> np.ndarray:
        """The wave back to the handle: ``(b r - (e + d r + b r)) / sqrt(2 b) = -(e + d r)
        / sqrt(2 b)`` (the matching damper's part cancels: nothing of free motion comes
        back; the series damper's does not: the handle feels what it dissipates)."""
        return -(self.resistance_n + self.damping_n_s_m * self.rate_m_s) / self._root_2b

    def summary(self) -> dict[str, Any]:
        """The robot's end: the handle's waves' bank, what the robot's surroundings
        absorbed (J; below zero they gave out), what the series damper dissipated."""
        return {
            **self.bank.summary(),
            "absorbed_j": self.absorbed_j,
            "dissipated_j": self.dissipated_j,
            "damped_cycles": self.damped_cycles,
        }
