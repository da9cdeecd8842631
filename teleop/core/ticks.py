"""Sim-time schedules shared by producers and consumers of slower streams.

The plant's state seq is the simulation tick (one per physics step). A producer that
runs slower than the plant (operator at 100 Hz, HMD at 90 Hz) samples on the ticks
where its own clock advances, and publishes each record ahead of use: valid from
``sample_tick + lead_ticks``. A consumer at tick ``k`` then knows exactly which
record applies (:func:`expected_valid_from`): in lockstep it waits for that record,
which makes the whole run deterministic; in realtime it takes the newest one.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Generic, TypeVar

import numpy as np

if TYPE_CHECKING:
    from teleop.core.config import Config

# What a TickedInputs holds per tick (a record, or a record with where it came from).
Held = TypeVar("Held")

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


def next_sample_tick(tick: int, rate_hz: float, timestep_s: float) -> int:
    """The first sample tick > ``tick``."""
    j = tick + 1
    while not is_sample_tick(j, rate_hz, timestep_s):
        j += 1
    return j


def period_ticks(rate_hz: float, timestep_s: float) -> int:
    """The period of a stream at ``rate_hz`` in plant ticks of ``timestep_s``, rounded to
    the nearest whole tick (at least one)."""
    return max(1, round(1.0 / (rate_hz * timestep_s)))


def lead_ticks(rate_hz: float, timestep_s: float) -> int:
    """How far ahead a producer at ``rate_hz`` publishes (plant ticks): one of its periods,
    so a record is in before the first tick it applies to."""
    return period_ticks(rate_hz, timestep_s)


def expected_valid_from(
    tick: int, rate_hz: float, timestep_s: float, lead_ticks: int
) -> int | None:
    """valid_from_tick of the record that applies at ``tick``; None before the first one."""
    if tick < lead_ticks:
        return None
    return last_sample_tick(tick - lead_ticks, rate_hz, timestep_s) + lead_ticks


@dataclass(frozen=True)
class SampleSchedule:
    """A producer slower than the bus on the run's ticks: it samples at ``rate_hz`` on
    ticks of ``tick_s`` (``Config.tick_s``, the bus period), and each record is valid from
    ``lead_ticks`` after its sample tick. The one timing helper of the device loops (the
    haptic device's hand inputs, the HMD, the scripted and the person's operators) and of
    their consumers, who pick the record that applies at a tick with :meth:`valid_from_for`.
    """

    rate_hz: float
    tick_s: float
    lead_ticks: int

    @classmethod
    def of(cls, rate_hz: float, tick_s: float, lead: int | None = None) -> SampleSchedule:
        """The schedule at ``rate_hz``, leading by ``lead`` ticks (default :func:`lead_ticks`:
        one of its periods)."""
        return cls(rate_hz, tick_s, lead_ticks(rate_hz, tick_s) if lead is None else lead)

    @property
    def lead_s(self) -> float:
        """The lead in s (whole ticks)."""
        return self.lead_ticks * self.tick_s

    def ticks(self, duration_s: float) -> int:
        """``duration_s`` in whole ticks (rounded)."""
        return round(duration_s / self.tick_s)

    @property
    def gap_ticks(self) -> int:
        """The most ticks from one sample to the next: a rate that does not divide the bus
        rate samples at uneven gaps (100 Hz on 250 Hz ticks: every 2 or 3 ticks)."""
        return max(1, math.ceil(1.0 / (self.rate_hz * self.tick_s) - _EPS))

    def is_sample(self, tick: int) -> bool:
        return is_sample_tick(tick, self.rate_hz, self.tick_s)

    def last_sample(self, tick: int) -> int:
        return last_sample_tick(tick, self.rate_hz, self.tick_s)

    def next_sample(self, tick: int) -> int:
        return next_sample_tick(tick, self.rate_hz, self.tick_s)

    def valid_from_for(self, tick: int) -> int | None:
        """``valid_from_tick`` of the record that applies at ``tick`` (None: none yet)."""
        return expected_valid_from(tick, self.rate_hz, self.tick_s, self.lead_ticks)


def hand_schedule(config: Config) -> SampleSchedule:
    """HAND_INPUT's schedule: the operator (scripted or a person's) samples at
    ``operator.decision_rate_hz``, each input valid one of its periods later; the haptic
    device takes the one valid at its tick."""
    return SampleSchedule.of(config.operator.decision_rate_hz, config.tick_s)


def scene_schedule(config: Config) -> SampleSchedule:
    """TOOL_POSE's and OBJECT_POSES' schedule: the plant sends them on the sample ticks of
    ``plant.scene_rate_hz``, exactly that many a second, valid as soon as they are sent."""
    return SampleSchedule.of(config.plant.scene_rate_hz, config.tick_s, 0)


def status_schedule(config: Config) -> SampleSchedule:
    """CONTROL_STATUS's and TELEOP_STATUS's schedule: the controller sends them on the
    sample ticks of ``control.status_rate_hz``."""
    return SampleSchedule.of(config.control.status_rate_hz, config.tick_s, 0)


def head_schedule(config: Config) -> SampleSchedule:
    """HEAD_POSE's schedule: the HMD samples at ``hmd.rate_hz``; a record sampled at tick
    ``k`` carries the pose predicted ``hmd.prediction_s`` ahead (in whole ticks), valid from
    ``k + lead_ticks``. A consumer at tick ``n`` uses the record whose ``valid_from_tick``
    is ``valid_from_for(n)``: in lockstep it waits for exactly that record
    (:meth:`TickedInputs.wait_for`), in realtime it takes the newest one not after ``n``
    (:meth:`TickedInputs.latest_at`). Before the first record applies (``n < lead_ticks``)
    there is none: the configured rest pose (``hmd.head_p_m``, ``hmd.head_yaw_rad``)."""
    lead = round(config.hmd.prediction_s / config.tick_s)
    return SampleSchedule.of(config.hmd.rate_hz, config.tick_s, lead)


class TickedInputs(Generic[Held]):
    """Thread-safe store of records keyed by their ``valid_from_tick``.

    Zenoh callbacks :meth:`put` records; a loop asks for the one that applies at a
    tick, waiting (event driven) for it in lockstep. Old records are pruned.
    """

    def __init__(self, keep: int = 64) -> None:
        self._cond = threading.Condition()
        self._records: dict[int, Held] = {}
        self._ticks: list[int] = []  # the keys of _records, sorted (latest_at bisects it)
        self._keep = keep

    def put(self, valid_from_tick: int, rec: Held) -> None:
        with self._cond:
            if valid_from_tick not in self._records:
                bisect.insort(self._ticks, valid_from_tick)
            self._records[valid_from_tick] = rec
            if len(self._ticks) > self._keep:
                for old in self._ticks[: len(self._ticks) - self._keep]:
                    del self._records[old]
                del self._ticks[: len(self._ticks) - self._keep]
            self._cond.notify_all()

    def wait_for(self, valid_from_tick: int, timeout_s: float) -> Held | None:
        """The record valid from exactly that tick, waiting up to ``timeout_s``."""
        with self._cond:
            self._cond.wait_for(lambda: valid_from_tick in self._records, timeout_s)
            return self._records.get(valid_from_tick)

    def at(self, valid_from_tick: int) -> Held | None:
        """The record valid from exactly that tick, if it is kept (no wait)."""
        with self._cond:
            return self._records.get(valid_from_tick)

    def newest_tick(self) -> int | None:
        """The largest valid_from_tick stored (None: none)."""
        with self._cond:
            return self._ticks[-1] if self._ticks else None

    def latest_at(self, tick: int) -> Held | None:
        """The record with the largest valid_from_tick <= ``tick`` (realtime use)."""
        with self._cond:
            index = bisect.bisect_right(self._ticks, tick)
            return self._records[self._ticks[index - 1]] if index else None

    def clear(self) -> None:
        with self._cond:
            self._records.clear()
            self._ticks.clear()


class TickBarrier:
    """Joins per-tick records of several streams; calls back once a tick is complete.

    Lockstep needs every input of a cycle to belong to the same plant tick (the records
    of different publishers arrive in no guaranteed order). ``put`` may be called from
    any Zenoh callback; the callback that completes a tick runs ``on_complete(tick,
    records)`` itself (no thread hand-off), in increasing tick order. A tick older than
    the newest completed one can no longer complete and is dropped.
    """

    def __init__(
        self,
        streams: tuple[str, ...],
        on_complete: Callable[[int, dict[str, np.ndarray]], None],
        keep_ticks: int = 64,
    ) -> None:
        self.streams = frozenset(streams)
        self._on_complete = on_complete
        self._lock = threading.Lock()
        self._pending: dict[int, dict[str, np.ndarray]] = {}
        self._last_completed = -1
        self._keep_ticks = keep_ticks
        self.dropped = 0  # records of ticks that could no longer complete

    def put(self, stream: str, tick: int, rec: np.ndarray) -> None:
        with self._lock:
            if tick <= self._last_completed:
                self.dropped += 1
                return
            records = self._pending.setdefault(tick, {})
            records[stream] = rec
            if records.keys() != self.streams:
                if len(self._pending) > self._keep_ticks:
                    oldest = min(self._pending)
                    del self._pending[oldest]
                    self.dropped += 1
                return
            del self._pending[tick]
            for stale in [t for t in self._pending if t < tick]:
                del self._pending[stale]
                self.dropped += 1
            self._last_completed = tick
            self._on_complete(tick, records)

    def reset(self) -> None:
        """Forget everything (a new run starts at tick 0 again)."""
        with self._lock:
            self._pending.clear()
            self._last_completed = -1
