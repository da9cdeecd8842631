"""Receiver-side bookkeeping: sequence checks, shedding stale records, their stamps."""

from __future__ import annotations

from teleop.bus.messages import JOINT_COMMAND, Stage
from teleop.bus.stamps import SHED_AGE_NS, Inbound, SeqCheck


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
    assert inbound.accept(command(1, now_ns - 1000), now_ns)
    assert not inbound.accept(command(1, now_ns), now_ns)  # not newer
    stale = command(2, now_ns - SHED_AGE_NS - 1, sample_ns=777)
    assert not inbound.accept(stale, now_ns)
    assert inbound.shed == 1 and inbound.seq.reordered == 1
    assert inbound.shed_log.rows.tolist() == [[777]]
    # a record of no teleoperation loop (no sample stamp) is shed but leaves no stamp
    assert not inbound.accept(command(3, 0), now_ns)
    assert inbound.shed == 2 and len(inbound.shed_log) == 1
