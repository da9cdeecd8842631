"""Receiver-side bookkeeping: sequence checks, shedding stale records, their stamps."""

from __future__ import annotations

import numpy as np
import pytest

from teleop.bus.messages import JOINT_COMMAND, Stage
from teleop.bus.stamps import (
    LINK_CLOCK_WINDOW_NS,
    MAX_SHED_AGE_NS,
    SEQ_WINDOW,
    SHED_AGE_NS,
    Inbound,
    LinkClock,
    SeqCheck,
    SeqGaps,
)


def command(seq: int, tx_ns: int, sample_ns: int = 0):
    rec = JOINT_COMMAND.new()
    rec["seq"] = seq
    rec["trace_ns"][Stage.CONTROLLER_TX] = tx_ns
    rec["trace_ns"][Stage.HAPTIC_SAMPLE] = sample_ns
    return rec


def test_seq_check_counts_gaps_and_reorders_and_restarts():
    check = SeqCheck()
    assert [check.accept(s) for s in (0, 1, 4, 3, 4, 5)] == [True, True, True, False, False, True]
    assert (check.lost, check.reordered) == (2, 2)
    check.restart()
    assert check.accept(0) and check.lost == 2


def test_inbound_drops_older_and_stale_records_and_logs_their_loops():
    inbound = Inbound(Stage.CONTROLLER_TX)
    now_ns = 10 * SHED_AGE_NS
    for seq in (1, 2, 3):  # the link's pace: 1 us on the way at the fastest
        assert inbound.accept(command(seq, now_ns - 1000), now_ns)
    assert not inbound.accept(command(3, now_ns), now_ns)  # not newer
    stale = command(4, now_ns - 1000 - SHED_AGE_NS - 1, sample_ns=777)
    assert not inbound.accept(stale, now_ns)
    assert inbound.shed == 1 and inbound.seq.reordered == 1
    assert inbound.shed_log.rows.tolist() == [[777]]
    # a record of no teleoperation loop (no sample stamp) is shed but leaves no stamp
    assert not inbound.accept(command(5, 0), now_ns)
    assert inbound.shed == 2 and len(inbound.shed_log) == 1


def test_copies_sent_again_a_second_later_teach_the_link_clock_nothing():
    """Lockstep: a plant waiting on an answer gets the controller's commands again, byte
    for byte, a second or more after their stamps, stall after stall. They are copies
    (seqs taken already): rejected by their seq, and the link's clock learns nothing
    from them, so the next fresh command is taken. Learnt from, three of them would set
    the link a second slow and the fresh one would be refused as stamped in the future."""
    inbound = Inbound(Stage.CONTROLLER_TX)
    rx_ns, delivery_ns = 10**12, 200_000
    for seq in range(1, 11):
        rx_ns += 4_000_000
        assert inbound.accept(command(seq, rx_ns - delivery_ns), rx_ns, shed=False)
    sent_ns = {seq: rx_ns - delivery_ns - (10 - seq) * 4_000_000 for seq in (9, 10)}
    for _ in range(3):  # three stalls, the commands in flight sent again each time
        rx_ns += 1_100_000_000
        for seq in (9, 10):
            assert not inbound.accept(command(seq, sent_ns[seq]), rx_ns, shed=False)
    rx_ns += 4_000_000
    assert inbound.accept(command(11, rx_ns - delivery_ns), rx_ns, shed=False)
    assert inbound.future_stamps == 0 and inbound.clock.relearnt == 0
    assert inbound.seq.reordered == 6


def test_a_link_that_spreads_its_records_sheds_later_but_never_past_the_bound():
    """Records of a steady link arrive within a fraction of a ms of its fastest: shed
    beyond SHED_AGE_NS. A link whose delivery spreads them over 0-6 ms (a network's
    jitter) is no backlog: a record 6 ms late is still used; a backlog beyond
    MAX_SHED_AGE_NS is shed whatever the spread."""
    period_ns, ms = 4_000_000, 1_000_000
    steady, jittery = Inbound(Stage.CONTROLLER_TX), Inbound(Stage.CONTROLLER_TX)
    rx_ns = 10**12
    for seq in range(1, 400):
        rx_ns += period_ns
        assert steady.accept(command(seq, rx_ns - 100_000), rx_ns)
        late_ns = (seq * 7 % 13) * ms // 2  # 0 to 6 ms, spread evenly
        jittery.accept(command(seq, rx_ns - 100_000 - late_ns), rx_ns)
    assert steady.shed_after_ns == SHED_AGE_NS
    assert SHED_AGE_NS + 6 * ms < jittery.shed_after_ns <= MAX_SHED_AGE_NS
    rx_ns += period_ns
    assert not steady.accept(command(400, rx_ns - 6 * ms), rx_ns)
    assert jittery.accept(command(400, rx_ns - 6 * ms), rx_ns)
    assert not jittery.accept(command(401, rx_ns - MAX_SHED_AGE_NS - ms), rx_ns)
    assert jittery.counts()["shed_after_ms"] == jittery.shed_after_ns / 1e6


def test_a_link_clock_learns_the_senders_clock_and_no_single_stamp_moves_it():
    """Hours between the clocks: ages are the time beyond the fastest delivery; one record
    stamped anywhere neither ages the next nor freshens an old one; a sender's new clock
    is learnt from its third record."""
    hours_ns = 5 * 3600 * 10**9
    clock = LinkClock()
    rx_ns = 10**12
    for delay_ns in (400_000, 0, 900_000):  # stamps of a clock hours ahead
        assert clock.offset_ns is None and clock.age_ns(0, 10**18) == 0  # not learnt yet
        assert clock.observe(rx_ns + hours_ns - delay_ns, rx_ns)
        rx_ns += 4_000_000
    assert clock.offset_ns == -hours_ns + 400_000  # the median of the first three
    assert clock.observe(rx_ns + hours_ns - 300_000, rx_ns)  # faster still: learnt
    assert clock.offset_ns == -hours_ns + 300_000
    # Stamped in the future: refused, and nothing moves; stamped long ago: old.
    assert not clock.observe(rx_ns + hours_ns + 10**9, rx_ns) and clock.refused == 1
    assert clock.observe(rx_ns, rx_ns) and clock.offset_ns == -hours_ns + 300_000
    stamp_ns = rx_ns + hours_ns - 300_000 - SHED_AGE_NS
    assert clock.age_ns(stamp_ns, rx_ns) == SHED_AGE_NS
    assert clock.local_ns(stamp_ns) == rx_ns - SHED_AGE_NS
    assert clock.observe(rx_ns + hours_ns - 300_000, rx_ns)  # on the clock again
    # A sender restarted on a clock hours behind: its third record re-learns the link.
    for k in range(3):
        rx_ns += 4_000_000
        assert clock.observe(rx_ns - 100_000, rx_ns)
        assert clock.relearnt == (1 if k == 2 else 0)
    assert clock.offset_ns == 100_000 and clock.age_ns(rx_ns - 100_000, rx_ns) == 0
    # The fastest delivery is forgotten after the window: a slower link is learnt.
    rx_ns += LINK_CLOCK_WINDOW_NS + 1
    for _ in range(3):
        rx_ns += 4_000_000
        clock.observe(rx_ns - 700_000, rx_ns)
    assert clock.offset_ns == 700_000


SEQ_RUNS = [
    [0, 1, 2, 3],  # in order: nothing missing
    [5, 6, 9, 10, 20],  # gaps: 2 + 9 missing
    [7, 8, 3, 4, 6],  # went back: a new run, taken up at its third record
    [1, 2, 2, 3],  # a repeat: out of order, the stream goes on
    [1, 1 + SEQ_WINDOW + 1, 1 + SEQ_WINDOW + 2],  # too far ahead: no gap of 65536
]


@pytest.mark.parametrize("seqs", SEQ_RUNS)
def test_seq_gaps_count_the_same_record_by_record_and_in_batches(seqs):
    one = SeqGaps()
    for seq in seqs:
        one.add(seq)
    batched = SeqGaps()
    for part in (seqs[:2], seqs[2:3], seqs[3:]):  # batches of a recorder's flushes
        batched.add_batch(np.array(part, dtype=np.int64))
    assert (one.missing, one.restarts) == (batched.missing, batched.restarts)
    assert one.previous == batched.previous == seqs[-1]


def test_seq_gaps_of_each_case():
    # (missing, restarts, out of order): SeqCheck's counts, the one rule of the bus layer
    expected = [(0, 0, 0), (11, 0, 0), (0, 1, 2), (0, 0, 1), (0, 0, 2)]
    for seqs, (missing, restarts, out_of_order) in zip(SEQ_RUNS, expected, strict=True):
        gaps, check = SeqGaps(), SeqCheck()
        assert gaps.add_batch(np.array(seqs)) == (missing, restarts)
        assert (gaps.missing, gaps.restarts, gaps.out_of_order) == (missing, restarts, out_of_order)
        for seq in seqs:
            check.accept(seq)
        assert (check.lost, check.restarts) == (missing, restarts)
    gaps = SeqGaps()
    assert gaps.add(4) == 0 and gaps.add(7) == 2 and gaps.add_batch(np.zeros(0)) == (0, 0)
