"""A haptic device that plays back recorded handle positions: a second HapticDevice.

Why: the haptic service must drive any device through :class:`HapticDevice` alone. This
one has no dynamics: each servo period it reports the next recorded handle position
(a recording of HAPTIC_STATE records, or any (n, 3) trajectory), as a real device
reports whatever the operator's hand did. It replays a recorded session's hand motion
into a live stack, and it is the test that the service's loop needs nothing beyond
the interface.

Device frame, m, m/s, N (as :mod:`teleop.devices.haptic.device`). The velocity is the finite
difference of consecutive recorded positions; the rendered force is the force sent,
saturated at the peak force; the hand input of :meth:`next_sample` is ignored (the
recording is the hand). After the last recorded sample the handle rests there.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from teleop.bus.messages import Button
from teleop.devices.haptic.device import (
    N_AXES,
    DeviceSample,
    HandInput,
    HapticDevice,
    saturate_force,
)


class ReplayDevice(HapticDevice):
    """Plays ``p_m`` (n, 3) back, one row per servo period ``period_s``.

    ``buttons``: one per row (default: none pressed). ``peak_force_n``: where a sent force
    saturates (norm, N).
    """

    def __init__(
        self,
        p_m: np.ndarray,
        period_s: float,
        peak_force_n: float,
        buttons: Sequence[int] | None = None,
    ) -> None:
        positions = np.array(p_m, dtype=np.float64)
        if positions.ndim != 2 or positions.shape[1] != N_AXES or len(positions) == 0:
            raise ValueError(f"p_m: expected a non-empty (n, 3) array, got {positions.shape}")
        if buttons is not None and len(buttons) != len(positions):
            raise ValueError(f"buttons: one per position ({len(positions)}), got {len(buttons)}")
        if period_s <= 0 or peak_force_n <= 0:
            raise ValueError("period_s and peak_force_n must be > 0")
        self.period_s = period_s
        self.peak_force_n = peak_force_n
        self._p_m = positions
        self._buttons = [Button(int(b)) for b in buttons] if buttons is not None else None
        self._force_n = np.zeros(N_AXES)
        self.connected = False
        self.reset()

    @classmethod
    def from_haptic_states(
        cls, records: np.ndarray, period_s: float, peak_force_n: float
    ) -> ReplayDevice:
        """A replay of HAPTIC_STATE records (a structured array, in seq order): their
        encoder positions and buttons."""
        return cls(records["device_p_m"], period_s, peak_force_n, records["buttons"].tolist())

    @property
    def samples_left(self) -> int:
        """Recorded samples not played yet."""
        return len(self._p_m) - 1 - self._index

    def connect(self) -> None:
        self.connected = True

    def disconnect(self) -> None:
        self._force_n[:] = 0.0
        self.connected = False

    def reset(self) -> None:
        """Back to the first recorded sample, no force."""
        self._index = 0
        self._force_n = np.zeros(N_AXES)
        self._sample = self._make_sample(np.zeros(N_AXES), np.zeros(N_AXES))

    def send_force(self, force_n: np.ndarray) -> None:
        self._force_n = saturate_force(force_n, self.peak_force_n)

    def read(self) -> DeviceSample:
        return self._sample

    def next_sample(self, hand: HandInput | None) -> DeviceSample:
        """The next recorded position (the last one again once the recording is over)."""
        previous = self._p_m[self._index]
        self._index = min(self._index + 1, len(self._p_m) - 1)
        v_m_s = (self._p_m[self._index] - previous) / self.period_s
        self._sample = self._make_sample(v_m_s, self._force_n.copy())
        return self._sample

    def _make_sample(self, v_m_s: np.ndarray, f_n: np.ndarray) -> DeviceSample:
        buttons = self._buttons[self._index] if self._buttons is not None else Button.NONE
        return DeviceSample(
            p_m=self._p_m[self._index].copy(), v_m_s=v_m_s, f_n=f_n, buttons=buttons
        )
