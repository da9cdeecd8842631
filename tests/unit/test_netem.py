"""The network emulator's schedule (teleop.bench.netem): pure, seeded, no sockets."""

from __future__ import annotations

import random

import pytest

from teleop.bench.netem import DeliverySchedule, LinkCut, LinkImpairment


def schedule(**impairment: float) -> DeliverySchedule:
    return DeliverySchedule(LinkImpairment(**impairment), random.Random(7))


def test_a_delay_alone_shifts_every_chunk_by_it():
    link = schedule(delay_s=0.05)
    assert [link.due_s(t) for t in (0.0, 0.001, 0.5)] == pytest.approx([0.05, 0.051, 0.55])
    assert link.lost == 0 and link.chunks == 3


def test_jitter_stays_within_its_bounds_and_never_reorders_the_stream():
    link = schedule(delay_s=0.02, jitter_s=0.01)
    received = [k * 0.001 for k in range(5000)]  # a chunk a millisecond: jitter > spacing
    due = [link.due_s(t) for t in received]
    assert due == sorted(due)  # a TCP stream keeps its order
    assert all(t + 0.01 - 1e-12 <= d for t, d in zip(received, due, strict=True))
    assert max(d - t for t, d in zip(received, due, strict=True)) <= 0.03 + 1e-12
    spread = {round(d - t, 4) for t, d in zip(received, due, strict=True)}
    assert len(spread) > 100  # jittered, not one value


def test_a_loss_costs_one_retransmission_at_about_its_rate():
    link = schedule(delay_s=0.01, loss=0.05, retransmit_s=0.2)
    due = [link.due_s(t) for t in (k * 1.0 for k in range(4000))]  # far apart: no queueing
    late = sum(1 for k, d in enumerate(due) if d - k > 0.1)
    assert late == link.lost and 150 < link.lost < 250  # 5 % of 4000, seeded
    assert {round(d - k, 6) for k, d in enumerate(due)} == {0.01, 0.21}


def test_the_same_seed_gives_the_same_schedule():
    first, second = schedule(jitter_s=0.01, loss=0.1), schedule(jitter_s=0.01, loss=0.1)
    assert [first.due_s(k * 0.01) for k in range(100)] == [
        second.due_s(k * 0.01) for k in range(100)
    ]


@pytest.mark.parametrize(
    "bad", [{"delay_s": -1.0}, {"jitter_s": -0.1}, {"loss": 1.0}, {"loss": -0.1}]
)
def test_impossible_impairments_are_refused(bad):
    with pytest.raises(ValueError):
        LinkImpairment(**bad)


def test_a_cut_is_read_from_after_and_duration():
    assert LinkCut.parse("20:0.5") == LinkCut(after_s=20.0, duration_s=0.5)


@pytest.mark.parametrize("bad", ["20", "a:1", "20:0", "-1:2", "20:-0.5", ""])
def test_a_cut_that_is_not_after_and_duration_is_refused_saying_how(bad):
    with pytest.raises(ValueError, match="AFTER_S:DURATION_S"):
        LinkCut.parse(bad)
