"""Sim-time schedules shared by producers and consumers of slower streams.

The plant's state seq is the simulation tick (one per physics step). A producer that
runs slower than the plant (operator at 100 Hz, HMD at 90 Hz) samples on the ticks
where its own clock advances, and publishes each record ahead of use: valid from
``sample_tick + lead_ticks``. A consumer at tick ``k`` then knows exactly which
record applies (:func:`expected_valid_from`): in lockstep it waits for that record,
which makes the whole run deterministic; in realtime it takes the newest one.
"""

from __future__ import annotations

import math
import threading

import numpy as np

# Tolerance on tick arithmetic in floating point (fraction of a tick).
_EPS = 1e-9


def is_sample_tick(tick: int, rate_hz: float, timestep_s: float) -> bool:
    """True on the plant ticks where a producer at ``rate_hz`` takes a sample (tick 0 too)."""
    if tick == 0:
        return True
    per_tick = rate_hz * timestep_s
    return math.floor(tick * per_tick + _EPS) > math.floor((tick - 1) * per_tick + _EPS)


def last_sample_tick(tick: int, rate_hz: float, timestep_s: float) -> int:
    """The latest sample tick <= ``tick`` (``tick`` >= 0)."""
    j = tick
    while not is_sample_tick(j, rate_hz, timestep_s):
        j -= 1
    return j


def expected_valid_from(
    tick: int, rate_hz: float, timestep_s: float, lead_ticks: int
) -> int | None:
    """valid_from_tick of the record that applies at ``tick``; None before the first one."""
    if tick < lead_ticks:
        return None
    return last_sample_tick(tick - lead_ticks, rate_hz, timestep_s) + lead_ticks


class TickedInputs:
    """Thread-safe store of records keyed by their ``valid_from_tick``.

    Zenoh callbacks :meth:`put` records; a loop asks for the one that applies at a
    tick, waiting (event driven) for it in lockstep. Old records are pruned.
    """

    def __init__(self, keep: int = 64) -> None:
        self._cond = threading.Condition()
        self._records: dict[int, np.ndarray] = {}
        self._keep = keep

    def put(self, valid_from_tick: int, rec: np.ndarray) -> None:
        with self._cond:
            self._records[valid_from_tick] = rec
            if len(self._records) > self._keep:
                for old in sorted(self._records)[: len(self._records) - self._keep]:
                    del self._records[old]
            self._cond.notify_all()

    def wait_for(self, valid_from_tick: int, timeout_s: float) -> np.ndarray | None:
        """The record valid from exactly that tick, waiting up to ``timeout_s``."""
        with self._cond:
            self._cond.wait_for(lambda: valid_from_tick in self._records, timeout_s)
            return self._records.get(valid_from_tick)

    def latest_at(self, tick: int) -> np.ndarray | None:
        """The record with the largest valid_from_tick <= ``tick`` (realtime use)."""
        with self._cond:
            eligible = [t for t in self._records if t <= tick]
            return self._records[max(eligible)] if eligible else None

    def clear(self) -> None:
        with self._cond:
            self._records.clear()
