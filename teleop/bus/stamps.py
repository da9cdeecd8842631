"""Raw latency stamps kept by a service during a run and written to its run dir at exit.

The latency report (:mod:`teleop.bench.latency`) is computed from these raw samples, never
from summaries of them, so every percentile it prints can be recomputed from the files.
A :class:`StampLog` is a ring of ``int64`` rows (:class:`teleop.core.ring.Ring`): appending
a row costs a slice assignment, cheap enough for a 1 kHz loop, and its memory is the same
at the end of an hour as at the start.
"""

from __future__ import annotations

import collections
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
# A link's own delivery spreads its records' ages (a network's jitter, a router's batches):
# a record late by that is the newest there is, not a backlog. So the shed age grows by
# SPREAD_FACTOR times the link's mean age (an average, gain SPREAD_GAIN, of the ages of
# the records not too old: a backlog does not widen it), as TCP's retransmission timeout
# grows with the round trip's variation, up to MAX_SHED_AGE_NS, below the plant's
# command watchdog (20 ms).
SPREAD_FACTOR = 4
SPREAD_GAIN = 1 / 16
MAX_SHED_AGE_NS = 15_000_000


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
# A link's fastest delivery is learnt over this much of the receiver's time: long enough
# that a backlog lasting seconds still shows as age, short enough that clocks drifting
# apart (tens of ppm) move it by well under a shed age.
LINK_CLOCK_WINDOW_NS = 10_000_000_000
# ... in this many slices, each keeping its fastest record (the window slides by one).
LINK_CLOCK_SLICES = 10
# A record that arrived this much faster than the link's fastest delivery is stamped in
# the future of the clock learnt: refused. Faster by less, it is learnt at once (a link
# faster than its first records showed, after a busy start, loses nothing).
FUTURE_STAMP_TOLERANCE_NS = 100_000_000
# A record this much slower than the link's fastest delivery is far behind the clock
# learnt (judged old). RESYNC_RECORDS records in a row off the clock learnt, either way,
# are a sender's new clock (a restart on another host): the link learns it afresh.
CLOCK_STEP_LIMIT_NS = 1_000_000_000
# Records taken whose seq and send stamp a receiver keeps, to know a copy sent again (a
# lockstep re-send: the states in flight, a few).
TAKEN_KEPT = 8


class LinkClock:
    """A sender's clock as one receiver sees it: how long a record has been on its way.

    Sender and receiver each stamp with their own monotonic clock (two hosts, or two time
    namespaces, never share one), so a stamp alone says nothing on this host. What does:
    ``delay = arrival - send stamp`` is the clocks' offset plus the record's time on its
    way, and its least over :data:`LINK_CLOCK_WINDOW_NS` (as NTP's clock filter keeps its
    best samples) is the offset plus the link's fastest delivery: ``offset_ns``.
    :meth:`age_ns` is a record's time beyond that fastest delivery, on this host's clock:
    the queueing a receiver that is behind adds, never the link's own latency.

    The first :data:`RESYNC_RECORDS` records set ``offset_ns`` by their median (their
    ages are 0 meanwhile), so that no single record does. After that a record that
    arrived faster than ``offset_ns`` allows (by more than
    :data:`FUTURE_STAMP_TOLERANCE_NS`) is stamped in the sender's future and refused;
    one slower by more than :data:`CLOCK_STEP_LIMIT_NS` is old, as its age says; and
    :data:`RESYNC_RECORDS` records in a row off the clock either way are learnt afresh
    from (``relearnt``): the sender's new clock (a restart on another host), or a link
    faster than its first records showed (they came through a busy start). So a
    single record, whatever its stamp, neither makes the sender's next records look old
    nor an old one fresh. Not thread-safe: its owner calls it under its own lock;
    ``offset_ns`` may be read from any thread.
    """

    def __init__(
        self, window_ns: int = LINK_CLOCK_WINDOW_NS, step_limit_ns: int = CLOCK_STEP_LIMIT_NS
    ) -> None:
        self.slice_ns = max(1, window_ns // LINK_CLOCK_SLICES)
        self.step_limit_ns = step_limit_ns
        self._slices: collections.deque[list[int]] = collections.deque()  # [index, least]
        self._first: list[int] = []  # delays of the records off the clock learnt (or before)
        self._offset_ns: int | None = None  # kept apart: any thread may read it
        self.refused = 0  # records stamped in the sender's future
        self.relearnt = 0  # times the link learnt its clock afresh

    @property
    def offset_ns(self) -> int | None:
        """The clocks' offset plus the link's fastest delivery: the least (arrival - send
        stamp) in the window (None: not learnt yet)."""
        return self._offset_ns

    def observe(self, stamp_ns: int, rx_ns: int) -> bool:
        """Learn from a record sent at ``stamp_ns`` (sender's clock) that arrived at
        ``rx_ns`` (this host's); False if it is refused, stamped in the sender's future.
        An unset stamp (0) teaches nothing (its age is the sender's uptime)."""
        if stamp_ns == 0:
            return True
        delay_ns = rx_ns - stamp_ns
        offset_ns = self._offset_ns
        faster = offset_ns is not None and offset_ns - delay_ns > FUTURE_STAMP_TOLERANCE_NS
        if offset_ns is None or faster or delay_ns - offset_ns > self.step_limit_ns:
            self._first.append(delay_ns)
            if len(self._first) < RESYNC_RECORDS:
                if faster:
                    self.refused += 1
                    return False
                return True  # old (its age says so), or while the clock is not learnt
            if offset_ns is not None:
                self.relearnt += 1
            self._slices.clear()
            delay_ns = sorted(self._first)[len(self._first) // 2]
        self._first.clear()
        self._learn(delay_ns, rx_ns // self.slice_ns)
        return True

    def _learn(self, delay_ns: int, index: int) -> None:
        slices = self._slices
        if slices and slices[-1][0] == index:
            slices[-1][1] = min(slices[-1][1], delay_ns)
        else:  # a new slice: the oldest leave the window
            slices.append([index, delay_ns])
            while slices[0][0] <= index - LINK_CLOCK_SLICES:
                slices.popleft()
        self._offset_ns = min(least for _, least in slices)

    def age_ns(self, stamp_ns: int, now_ns: int) -> int:
        """How much longer than the link's fastest delivery the record sent at
        ``stamp_ns`` has been on its way at ``now_ns`` (0 while the clock is not learnt)."""
        offset_ns = self._offset_ns
        return 0 if offset_ns is None else now_ns - stamp_ns - offset_ns

    def local_ns(self, stamp_ns: int) -> int:
        """``stamp_ns`` of the sender's clock on this host's clock, as the link's fastest
        delivery would have brought it (``stamp_ns`` itself while not learnt)."""
        offset_ns = self._offset_ns
        return stamp_ns if offset_ns is None else stamp_ns + offset_ns

    def reset(self) -> None:
        """Forget the sender's clock (it started over, perhaps on another host)."""
        self._slices.clear()
        self._first.clear()
        self._offset_ns = None


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

    Why a run of records and not one: every record may be hostile or from a restarted
    peer, and the robot's commands pass this check. Were one record going back taken as
    a restart at once, a single stale or forged record would rewind the check and the
    old commands after it would be taken as new; were one far ahead taken, it would turn
    every real record after it into a reordered one. Only a producer that keeps sending
    in order moves the check, so no single record of a sender steers it; the price is
    that a restarted producer's first ``RESYNC_RECORDS - 1`` records go unused. Observers
    count by the same rule (:class:`SeqGaps`), so their gaps and restarts are the ones
    the robot's path saw.
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
        length = self._join_run(seq)
        if length < RESYNC_RECORDS:
            self._runs[seq] = length
            return False
        self.restarts += 1  # the run's records were counted as rejected: not as lost
        self.last_seq = seq
        self._runs.clear()
        return True

    def refused(self, seq: int) -> None:
        """A record refused before this check (for its stamp), which this check would
        have rejected too, joins the runs of rejected records, uncounted here and never
        taken: a producer whose records look wrong after one hostile record (a seq and a
        clock it set) is taken up as soon as it would be for its seqs alone."""
        if not self.last_seq < seq <= self.last_seq + SEQ_WINDOW:
            self._runs[seq] = self._join_run(seq)

    def _join_run(self, seq: int) -> int:
        """The length of the run of rejected records ``seq`` extends (1: a new run, the
        shortest dropped if too many), taken out of the runs."""
        extends = [last for last in self._runs if last < seq <= last + SEQ_WINDOW]
        if extends:
            return self._runs.pop(max(extends)) + 1
        if len(self._runs) >= MAX_RESYNC_RUNS:
            del self._runs[min(self._runs, key=self._runs.__getitem__)]  # shortest, oldest
        return 1

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
    (taken at ``tx_stage`` on the sender's monotonic clock) is not in the sender's future
    as this link has seen its clock (:class:`LinkClock`; ``future_stamp``: rejected, the
    seq check untouched); its seq is in order (:class:`SeqCheck`: gaps counted as lost,
    older ones as reordered, jumps beyond the window rejected, a restarted producer taken
    up); and it is not older than ``shed_age_ns`` (plus the link's own spread, see
    SPREAD_FACTOR) beyond the link's fastest delivery, on this host's clock (else it is
    shed: the receiver is behind; it did arrive, so the next record is no gap). A copy
    of a record taken already (the same seq and send stamp: a lockstep re-send) is judged
    by its seq alone and teaches the link's clock nothing. What is shed (here or by the
    caller, e.g. superseded by a newer record) has the HAPTIC_SAMPLE stamp of its loop
    logged, for the latency report's count of loops that never closed.
    The first rejection of each reason is logged. Not thread-safe: the owner calls it
    under its own lock.
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
        self.clock = LinkClock()
        self.shed = 0  # records dropped unanswered: too old, or superseded (see drop)
        self.future_stamps = 0
        self.mean_age_ns = 0.0  # the link's spread: its records' mean age on arrival
        # HAPTIC_SAMPLE stamps of the loops dropped here (one log may serve several streams
        # of a service: the latency report counts loops, not streams)
        self.shed_log = shed_log if shed_log is not None else StampLog(1)
        self._logged: set[str] = set()
        self._taken: dict[int, int] = {}  # seq -> send stamp of the newest records taken

    def accept(self, rec: np.ndarray, now_ns: int, *, shed: bool = True) -> bool:
        """True if ``rec`` is to be used: not stamped in the future, in order and (with
        ``shed``) not older than the shed age at ``now_ns``. A stale record is counted in
        ``shed`` and logged."""
        seq, stamp_ns = int(rec["seq"]), int(rec["trace_ns"][self.tx_stage])
        if self._taken.get(seq) == stamp_ns:
            # A copy of a record taken already (a lockstep re-send, byte for byte): its
            # seq alone judges it. It tells nothing new of the sender's clock, and a copy
            # sent again a second later would teach the link a delivery a second slow
            # (three such: its clock learnt afresh, the next fresh record refused as
            # stamped in the future).
            return self.accept_seq(seq)
        if not self.arrived(rec, now_ns):
            self.seq.refused(seq)
            return False
        if not self.accept_seq(seq):
            return False
        self._taken[seq] = stamp_ns
        if len(self._taken) > TAKEN_KEPT:
            del self._taken[next(iter(self._taken))]  # the oldest taken
        if self.too_old(rec, now_ns):
            if shed:
                self.drop(rec)  # arrived, in order, too late: shed, not lost
                return False
        else:  # the link's own spread, from the records it delivers in time
            age_ns = max(0, self.age_ns(rec, now_ns))
            self.mean_age_ns += SPREAD_GAIN * (age_ns - self.mean_age_ns)
        return True

    def arrived(self, rec: np.ndarray, rx_ns: int) -> bool:
        """The clock check alone: fold the record's send stamp into the link's clock;
        False (counted, logged once) if it is stamped in the sender's future."""
        stamp_ns = int(rec["trace_ns"][self.tx_stage])
        if self.clock.observe(stamp_ns, rx_ns):
            return True
        self.future_stamps += 1
        self._log_once("future_stamp", self.clock.local_ns(stamp_ns) - rx_ns)
        return False

    def age_ns(self, rec: np.ndarray, now_ns: int) -> int:
        """How long ``rec`` has been on its way at ``now_ns`` beyond the link's fastest
        delivery (this host's clock; :class:`LinkClock`)."""
        return self.clock.age_ns(int(rec["trace_ns"][self.tx_stage]), now_ns)

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

    @property
    def shed_after_ns(self) -> int:
        """The age beyond which a record is shed: ``shed_age_ns`` plus the link's spread,
        at most MAX_SHED_AGE_NS (or ``shed_age_ns`` if that is more)."""
        spread_ns = round(SPREAD_FACTOR * self.mean_age_ns)
        return max(self.shed_age_ns, min(self.shed_age_ns + spread_ns, MAX_SHED_AGE_NS))

    def too_old(self, rec: np.ndarray, now_ns: int) -> bool:
        """Whether ``rec`` has been on its way longer than :attr:`shed_after_ns` beyond the
        link's fastest delivery at ``now_ns``."""
        return self.age_ns(rec, now_ns) > self.shed_after_ns

    def log_dropped(self, rec: np.ndarray) -> None:
        """Log the HAPTIC_SAMPLE stamp of a record dropped for whatever reason (none
        logged for a record that is not part of a teleoperation loop: stamp 0)."""
        sample_ns = int(rec["trace_ns"][Stage.HAPTIC_SAMPLE])
        if sample_ns > 0:
            self.shed_log.append((sample_ns,))

    def restart(self) -> None:
        """The producer starts over (a new run, perhaps on another host): its next seq is
        not a gap, its clock is learnt afresh."""
        self.seq.restart()
        self.clock.reset()
        self._taken.clear()

    def counts(self) -> dict[str, int]:
        """Every counter of the stream, by name (for a summary)."""
        return {
            **self.seq.counts(),
            "shed": self.shed,
            "future_stamps": self.future_stamps,
            "shed_after_ms": self.shed_after_ns / 1e6,  # its last value
        }

    def save(self, path: Path) -> None:
        """Write the shed log (see :meth:`StampLog.save`)."""
        self.shed_log.save(path)
