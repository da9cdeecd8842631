"""Sim-tick schedules and the tick barrier that keeps lockstep deterministic."""

from __future__ import annotations

import numpy as np

from teleop.core.ticks import TickBarrier, TickedInputs, expected_valid_from, is_sample_tick

TIMESTEP_S = 0.001


def test_sample_ticks_of_slower_producers():
    ticks_100hz = [k for k in range(100) if is_sample_tick(k, 100.0, TIMESTEP_S)]
    assert ticks_100hz == list(range(0, 100, 10))
    ticks_90hz = [k for k in range(1001) if is_sample_tick(k, 90.0, TIMESTEP_S)]
    assert len(ticks_90hz) == 91  # 0 plus one per 1/90 s over one second
    assert max(np.diff(ticks_90hz)) == 12 and min(np.diff(ticks_90hz)) == 11


def test_expected_valid_from_points_at_the_latest_published_record():
    assert expected_valid_from(5, 100.0, TIMESTEP_S, lead_ticks=10) is None
    assert expected_valid_from(10, 100.0, TIMESTEP_S, lead_ticks=10) == 10
    assert expected_valid_from(19, 100.0, TIMESTEP_S, lead_ticks=10) == 10
    assert expected_valid_from(20, 100.0, TIMESTEP_S, lead_ticks=10) == 20


def test_ticked_inputs_latest_and_wait():
    inputs = TickedInputs()
    inputs.put(10, np.array(1))
    inputs.put(20, np.array(2))
    assert int(inputs.latest_at(15)) == 1 and int(inputs.latest_at(25)) == 2
    assert inputs.latest_at(5) is None
    assert int(inputs.wait_for(20, 0.0)) == 2
    assert inputs.wait_for(30, 0.01) is None


def test_barrier_fires_once_per_complete_tick_in_any_arrival_order():
    fired: list[tuple[int, dict]] = []
    barrier = TickBarrier(("state", "haptic"), lambda tick, recs: fired.append((tick, recs)))
    barrier.put("haptic", 0, np.array(0))
    assert fired == []
    barrier.put("state", 0, np.array(0))
    barrier.put("state", 1, np.array(1))
    barrier.put("haptic", 1, np.array(1))
    barrier.put("haptic", 1, np.array(9))  # a duplicate of a completed tick is dropped
    assert [tick for tick, _ in fired] == [0, 1]
    assert barrier.dropped == 1
    barrier.reset()
    barrier.put("state", 0, np.array(0))
    barrier.put("haptic", 0, np.array(0))
    assert [tick for tick, _ in fired] == [0, 1, 0]


def test_ticked_inputs_latest_at_matches_a_scan_whatever_the_arrival_order():
    rng = np.random.default_rng(3)
    inputs = TickedInputs(keep=16)
    kept: dict[int, int] = {}
    for tick in rng.permutation(200)[:80]:
        rec = np.array(int(tick))
        inputs.put(int(tick), rec)
        kept[int(tick)] = int(tick)
        for old in sorted(kept)[: max(0, len(kept) - 16)]:
            del kept[old]
        for query in (int(tick) - 1, int(tick), int(tick) + 7, 250):
            eligible = [t for t in kept if t <= query]
            found = inputs.latest_at(query)
            assert (None if found is None else int(found)) == (max(eligible) if eligible else None)
    inputs.clear()
    assert inputs.latest_at(1000) is None
