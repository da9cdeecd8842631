"""Raw latency stamps kept by a service during a run and written to its run dir at exit.

The latency report (:mod:`teleop.bench.latency`) is computed from these raw samples, never
from summaries of them, so every percentile it prints can be recomputed from the files.
A :class:`StampLog` is an append-only ``int64`` table: appending a row costs a slice
assignment (no allocation until the table doubles), cheap enough for a 1 kHz loop.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from teleop.bus.messages import Stage

# Rows allocated up front: about 65 s at 1 kHz before the first doubling.
DEFAULT_CAPACITY_ROWS = 65_536
# Rows kept at most (10 min at 1 kHz, 48 MB for a trace log): a long-running stack
# (`teleop up`) must not grow without bound; later rows are only counted.
DEFAULT_MAX_ROWS = 600_000
# Realtime teleoperation: an input of the loop (haptic sample, state, feedback) older than
# this when its callback runs (its producer's stamp to now) is shed, not answered: the
# service is behind (a CPU stall), its answer would be late anyway, and answering every
# queued input in order would keep it behind (measured on an overloaded host: backlogs of
# 0.3-0.5 s). Far above a healthy hop (0.1-0.3 ms), below the plant's 20 ms watchdog.
SHED_AGE_NS = 5_000_000


class StampLog:
    """Append-only table of ``n_columns`` int64 values per row (nanoseconds, seqs).

    Keeps the first ``max_rows`` rows; later ones are counted in ``overflow``. Not
    thread-safe: the owning service appends under its own lock.
    """

    def __init__(
        self,
        n_columns: int,
        capacity_rows: int = DEFAULT_CAPACITY_ROWS,
        max_rows: int = DEFAULT_MAX_ROWS,
    ) -> None:
        if n_columns <= 0 or capacity_rows <= 0 or max_rows <= 0:
            raise ValueError("n_columns, capacity_rows and max_rows must be > 0")
        self._table = np.zeros((min(capacity_rows, max_rows), n_columns), dtype=np.int64)
        self._n = 0
        self.max_rows = max_rows
        self.overflow = 0

    def __len__(self) -> int:
        return self._n

    def append(self, row: np.ndarray | Sequence[int]) -> None:
        """Add one row (``n_columns`` integers); only counted once ``max_rows`` are kept."""
        if self._n >= self.max_rows:
            self.overflow += 1
            return
        if self._n == self._table.shape[0]:
            rows = min(2 * self._table.shape[0], self.max_rows)
            grown = np.zeros((rows, self._table.shape[1]), dtype=np.int64)
            grown[: self._n] = self._table
            self._table = grown
        self._table[self._n] = row
        self._n += 1

    @property
    def rows(self) -> np.ndarray:
        """The rows appended so far, shape (n, n_columns) (a view: copy to keep it)."""
        return self._table[: self._n]

    def save(self, path: Path) -> None:
        """Write the rows as a ``.npy`` file, atomically (a reader never sees half a file)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            np.save(f, self.rows)
        os.replace(tmp, path)


class SeqCheck:
    """Losses and reordering of one stream, from the ``seq`` of the records received.

    :meth:`accept` says whether a record is newer than every one before it; gaps in
    ``seq`` count as ``lost``, a record not newer as ``reordered``. Not thread-safe: the
    owning service calls it under its own lock.
    """

    def __init__(self) -> None:
        self.last_seq = -1  # newest seq accepted; -1: none since the (re)start
        self.lost = 0
        self.reordered = 0

    def accept(self, seq: int) -> bool:
        """Count ``seq``; False if it is not newer than the last one accepted."""
        if seq <= self.last_seq:
            self.reordered += 1
            return False
        if self.last_seq >= 0:
            self.lost += seq - self.last_seq - 1
        self.last_seq = seq
        return True

    def restart(self) -> None:
        """The producer starts over (a new run): the next seq is not a gap."""
        self.last_seq = -1


class Inbound:
    """Receiver-side bookkeeping of one realtime input stream, in one place.

    Three checks every realtime receiver makes, in this order: the record is newer than
    every one before it (:class:`SeqCheck`: gaps counted as lost, older ones as
    reordered); it is not older than ``shed_age_ns`` on this host's monotonic clock,
    measured from the stamp its sender wrote at ``tx_stage`` (else it is shed: the
    receiver is behind); and what is shed (here or by the caller, e.g. superseded by a
    newer record) has the HAPTIC_SAMPLE stamp of its loop logged, for the latency
    report's count of loops that never closed. Not thread-safe: the owner calls it
    under its own lock.
    """

    def __init__(
        self, tx_stage: Stage, shed_age_ns: int = SHED_AGE_NS, shed_log: StampLog | None = None
    ) -> None:
        self.tx_stage = tx_stage
        self.shed_age_ns = shed_age_ns
        self.seq = SeqCheck()
        self.shed = 0  # records dropped unanswered: too old, or superseded (see drop)
        # HAPTIC_SAMPLE stamps of the loops dropped here (one log may serve several streams
        # of a service: the latency report counts loops, not streams)
        self.shed_log = shed_log if shed_log is not None else StampLog(1)

    def accept(self, rec: np.ndarray, now_ns: int) -> bool:
        """True if ``rec`` is to be used: newer than the last one and fresh at
        ``now_ns``. A stale record is counted in ``shed`` and logged."""
        if not self.seq.accept(int(rec["seq"])):
            return False
        if self.too_old(rec, now_ns):
            self.drop(rec)
            return False
        return True

    def drop(self, rec: np.ndarray) -> None:
        """``rec`` goes unanswered (too old, or superseded by a newer one): count, log."""
        self.shed += 1
        self.log_dropped(rec)

    def too_old(self, rec: np.ndarray, now_ns: int) -> bool:
        """Whether ``rec`` left its sender more than ``shed_age_ns`` before ``now_ns``."""
        return now_ns - int(rec["trace_ns"][self.tx_stage]) > self.shed_age_ns

    def log_dropped(self, rec: np.ndarray) -> None:
        """Log the HAPTIC_SAMPLE stamp of a record dropped for whatever reason (none
        logged for a record that is not part of a teleoperation loop: stamp 0)."""
        sample_ns = int(rec["trace_ns"][Stage.HAPTIC_SAMPLE])
        if sample_ns > 0:
            self.shed_log.append((sample_ns,))

    def restart(self) -> None:
        """The producer starts over (a new run): its next seq is not a gap."""
        self.seq.restart()

    def save(self, path: Path) -> None:
        """Write the shed log (see :meth:`StampLog.save`)."""
        self.shed_log.save(path)
