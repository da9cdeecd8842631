"""Raw latency stamps kept by a service during a run and written to its run dir at exit.

The latency report (:mod:`teleop.bench.latency`) is computed from these raw samples, never
from summaries of them, so every percentile it prints can be recomputed from the files.
A :class:`StampLog` is a ring of ``int64`` rows (:class:`teleop.core.ring.Ring`): appending
a row costs a slice assignment, cheap enough for a 1 kHz loop, and its memory is the same
at the end of an hour as at the start.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from teleop.bus.messages import Stage
from teleop.core.ring import Ring

logger = logging.getLogger(__name__)

# Rows a stamp log keeps, the newest: 65 s of a 1 kHz stream, 4.4 min at 250 Hz (5 MB for
# a trace log of 10 stamps a row); older rows are only counted.
STAMP_LOG_ROWS = 65_536
# Realtime teleoperation: an input of the loop (haptic sample, state, feedback) older than
# this when its callback runs (its producer's stamp to now) is shed, not answered: the
# service is behind (a CPU stall), its answer would be late anyway, and answering every
# queued input in order would keep it behind for as long as the backlog lasts. Many times a
# healthy hop (a fraction of a ms), well below the plant's command watchdog.
SHED_AGE_NS = 5_000_000


class StampLog(Ring):
    """The newest ``max_rows`` rows of ``n_columns`` int64 stamps (ns, seqs); ``dropped``
    counts the older rows no longer kept."""

    def __init__(self, n_columns: int, max_rows: int = STAMP_LOG_ROWS) -> None:
        super().__init__(max_rows, n_columns, np.int64)


# Sequence window: a record more than this many seqs ahead of the newest accepted one is
# suspicious (a poisoned counter, or a producer that started over), not a gap: at 1 kHz
# about 65 s of consecutive losses. A sender can therefore move a receiver's counters by
# at most this much per record, never to the end of the u64 range.
SEQ_WINDOW = 1 << 16
# A producer that started over (or one a receiver joins late) is taken up after this many
# rejected records in order among themselves (other records may come between): one
# poisoned record cannot lock out the stream's real producer, whose next record (in the
# window) is taken, or whose run of records re-anchors the check.
RESYNC_RECORDS = 3
# Runs of rejected records in order tracked at once: junk between a restarted producer's
# records starts runs of its own, which evict the shortest, never a longer one.
MAX_RESYNC_RUNS = 4
# A record stamped more than this far in this host's future did not come from a clock of
# this host: rejected (it would otherwise never be judged stale).
FUTURE_STAMP_TOLERANCE_NS = 1_000_000


class SeqCheck:
    """Losses, reordering and restarts of one stream, from the ``seq`` of its records.

    :meth:`accept` takes a record that is newer than the last one accepted by at most
    :data:`SEQ_WINDOW`; gaps count as ``lost``. A record not newer is ``reordered``, one
    too far ahead is a ``jump``: both rejected, and neither moves the check. Rejected
    records in order among themselves form runs; one that reaches
    :data:`RESYNC_RECORDS` records means the producer started over (or this receiver
    joined late): the check re-anchors on it (``restarts``). The first record of a
    stream is taken when its seq is within the window of zero (a producer's first
    records), else it starts such a run. Not thread-safe: the owning service calls it
    under its own lock.
    """

    def __init__(self) -> None:
        self.last_seq = -1  # newest seq accepted; -1: none since the (re)start
        self.lost = 0
        self.reordered = 0
        self.jumps = 0
        self.restarts = 0
        self._runs: dict[int, int] = {}  # newest seq of a run of rejected records -> length

    def accept(self, seq: int) -> bool:
        """Count ``seq``; True if the record is to be used."""
        if self.last_seq < seq <= self.last_seq + SEQ_WINDOW:
            if self.last_seq >= 0:
                self.lost += seq - self.last_seq - 1
            self.last_seq = seq
            self._runs.clear()
            return True
        if seq <= self.last_seq:
            self.reordered += 1
        else:
            self.jumps += 1
        extends = [last for last in self._runs if last < seq <= last + SEQ_WINDOW]
        length = 1
        if extends:
            newest = max(extends)
            length = self._runs.pop(newest) + 1
        elif len(self._runs) >= MAX_RESYNC_RUNS:
            del self._runs[min(self._runs, key=self._runs.__getitem__)]  # shortest, oldest
        if length < RESYNC_RECORDS:
            self._runs[seq] = length
            return False
        self.restarts += 1  # the run's records were counted as rejected: not as lost
        self.last_seq = seq
        self._runs.clear()
        return True

    def restart(self) -> None:
        """The producer starts over (a new run): the next seq is not a gap."""
        self.last_seq = -1
        self._runs.clear()

    def counts(self) -> dict[str, int]:
        """The counters, by name (for a summary)."""
        return {
            "lost": self.lost,
            "reordered": self.reordered,
            "jumps": self.jumps,
            "restarts": self.restarts,
        }


class SeqGaps:
    """:class:`SeqCheck`'s rule for a receiver that keeps every record anyway (an
    observer: the recorder, a newest-only subscription): it only counts. ``missing`` are
    the gaps (records lost on the way, or skipped by a newest-only consumer that was
    behind), ``restarts`` the producer starting over, ``out_of_order`` the records the
    rule would not have used (behind the newest, or too far ahead: a producer starting
    over until its run re-anchors the check, or a counter nobody can trust). Record by
    record (:meth:`add`) or batch by batch (:meth:`add_batch`): the same counts either
    way. Not thread-safe: its owner calls it from one thread.
    """

    def __init__(self) -> None:
        self.check = SeqCheck()
        self.previous: int | None = None  # the newest seq seen; None: none yet

    @property
    def missing(self) -> int:
        return self.check.lost

    @property
    def restarts(self) -> int:
        return self.check.restarts

    @property
    def out_of_order(self) -> int:
        return self.check.reordered + self.check.jumps - self.check.restarts

    def add(self, seq: int) -> int:
        """One record's seq; the records missing before it."""
        lost = self.check.lost
        self.check.accept(seq)
        self.previous = seq
        return self.check.lost - lost

    def add_batch(self, seqs: np.ndarray) -> tuple[int, int]:
        """Seqs of several records in arrival order; (missing, restarts) among them."""
        lost, restarts = self.check.lost, self.check.restarts
        for seq in np.asarray(seqs, dtype=np.int64).tolist():
            self.add(seq)
        return self.check.lost - lost, self.check.restarts - restarts


class Inbound:
    """Receiver-side bookkeeping of one realtime input stream, in one place.

    The checks every realtime receiver makes, in this order: the record's send stamp
    (taken at ``tx_stage`` on this host's monotonic clock) is not in this host's future
    (``future_stamp``: rejected, the seq check untouched); its seq is in order
    (:class:`SeqCheck`: gaps counted as lost, older ones as reordered, jumps beyond the
    window rejected, a restarted producer taken up); and it is not older than
    ``shed_age_ns`` (else it is shed: the receiver is behind; it did arrive, so the next
    record is no gap). What is shed (here or by the caller, e.g.
    superseded by a newer record) has the HAPTIC_SAMPLE stamp of its loop logged, for the
    latency report's count of loops that never closed. The first rejection of each
    reason is logged. Not thread-safe: the owner calls it under its own lock.
    """

    def __init__(
        self,
        tx_stage: Stage,
        shed_age_ns: int = SHED_AGE_NS,
        shed_log: StampLog | None = None,
        name: str = "",
    ) -> None:
        self.tx_stage = tx_stage
        self.shed_age_ns = shed_age_ns
        self.name = name or tx_stage.name  # for the log lines
        self.seq = SeqCheck()
        self.shed = 0  # records dropped unanswered: too old, or superseded (see drop)
        self.future_stamps = 0
        # HAPTIC_SAMPLE stamps of the loops dropped here (one log may serve several streams
        # of a service: the latency report counts loops, not streams)
        self.shed_log = shed_log if shed_log is not None else StampLog(1)
        self._logged: set[str] = set()

    def accept(self, rec: np.ndarray, now_ns: int, *, shed: bool = True) -> bool:
        """True if ``rec`` is to be used: not stamped in the future, in order and (with
        ``shed``) not older than the shed age at ``now_ns``. A stale record is counted in
        ``shed`` and logged."""
        stamp_ns = int(rec["trace_ns"][self.tx_stage])
        if stamp_ns > now_ns + FUTURE_STAMP_TOLERANCE_NS:
            self.future_stamps += 1
            self._log_once("future_stamp", stamp_ns - now_ns)
            return False
        if not self.accept_seq(int(rec["seq"])):
            return False
        if shed and now_ns - stamp_ns > self.shed_age_ns:
            self.drop(rec)  # arrived, in order, too late: shed, not lost
            return False
        return True

    def accept_seq(self, seq: int) -> bool:
        """The sequence check alone (:class:`SeqCheck`), its first rejection of each kind
        and every restart logged."""
        counts = (self.seq.reordered, self.seq.jumps, self.seq.restarts)
        if self.seq.accept(seq):
            if self.seq.restarts != counts[2]:
                logger.warning("%s: the producer started over (seq %d): taken up", self.name, seq)
            return True
        if self.seq.jumps != counts[1]:
            self._log_once("jump", seq)
        else:
            self._log_once("reordered", seq)
        return False

    def _log_once(self, reason: str, value: int) -> None:
        if reason not in self._logged:
            self._logged.add(reason)
            logger.warning(
                "%s: rejected a record (%s: %d); further ones are only counted",
                self.name,
                reason,
                value,
            )

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

    def counts(self) -> dict[str, int]:
        """Every counter of the stream, by name (for a summary)."""
        return {**self.seq.counts(), "shed": self.shed, "future_stamps": self.future_stamps}

    def save(self, path: Path) -> None:
        """Write the shed log (see :meth:`StampLog.save`)."""
        self.shed_log.save(path)
