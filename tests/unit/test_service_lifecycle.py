"""Pieces of the service lifecycle that need no bus."""

from __future__ import annotations

import json
import logging
import os

from teleop.bench.relay import FLOOR_STAND_INS, RELAYS, PlantRelay
from teleop.bus.service import Service, ServiceOptions, fifo_scheduling, pin_to_cpus
from teleop.core.clock import FINE_SLEEP_MARGIN_NS, MonotonicClock
from teleop.core.config import load_config


def test_pin_to_cpus_uses_existing_cpus_and_ignores_others(caplog):
    original = os.sched_getaffinity(0)
    try:
        first = min(original)
        assert pin_to_cpus((first, 10_000)) == f"granted [{first}]"
        assert os.sched_getaffinity(0) == {first}
        os.sched_setaffinity(0, original)
        with caplog.at_level(logging.WARNING):
            outcome = pin_to_cpus((10_000,))
        assert outcome.startswith("refused") and os.sched_getaffinity(0) == original
        assert "no such CPU" in caplog.text
        assert pin_to_cpus(()) == "not requested"
        assert os.sched_getaffinity(0) == original
    finally:
        os.sched_setaffinity(0, original)


def test_fifo_scheduling_applies_inside_the_block_and_restores_after(caplog):
    before = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority
    with fifo_scheduling(0) as outcome:  # 0: normal scheduling, nothing to do
        assert outcome == "not requested" and os.sched_getscheduler(0) == before[0]
    with caplog.at_level(logging.INFO), fifo_scheduling(7) as outcome:
        if outcome.startswith("granted"):  # CAP_SYS_NICE (root): the kernel accepted it
            assert os.sched_getscheduler(0) == os.SCHED_FIFO
            assert os.sched_getparam(0).sched_priority == 7
            # A clock built now sleeps in one go: no timer slack under a realtime policy.
            assert MonotonicClock().fine_margin_ns == 0
        else:  # refused: said once, the thread keeps its policy
            assert outcome.startswith("refused") and "refused" in caplog.text
            assert os.sched_getscheduler(0) == before[0]
    assert (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority) == before
    assert MonotonicClock().fine_margin_ns == FINE_SLEEP_MARGIN_NS


def test_fifo_priority_goes_to_the_loop_services_in_realtime_only():
    cpu = load_config(None, []).cpu
    assert cpu.fifo_priority > 0
    for name in ("plant", "controller", "haptic"):
        assert cpu.fifo_priority_for(name, "realtime") == cpu.fifo_priority
        assert cpu.fifo_priority_for(name, "lockstep") == 0
    for name in ("recorder", "eyeview", "hmd", "operator"):
        assert cpu.fifo_priority_for(name, "realtime") == 0
    assert (
        load_config(None, ["cpu.fifo_priority=0"]).cpu.fifo_priority_for("plant", "realtime") == 0
    )


def test_the_floor_relays_run_where_the_services_they_stand_in_for_run():
    assert FLOOR_STAND_INS == {"relay_controller": "controller", "relay_plant": "plant"}
    assert {relay.name: relay.scheduling_as for relay in RELAYS} == FLOOR_STAND_INS
    assert PlantRelay.scheduling_as == "plant" and Service.scheduling_as == ""


def test_a_restarted_services_summary_keeps_its_earlier_processes(tmp_path):
    class Counting(Service):
        name = "counting"
        count = 0

        def summary(self):
            return {"count": self.count}

    path = tmp_path / "counting.summary.json"
    path.write_text(json.dumps({"count": 7, "pid": -1}))  # a process before this one
    service = Counting(load_config(), ServiceOptions(run_dir=tmp_path))
    service.count = 3
    service.write_summary()
    service.count = 4
    service.write_summary()  # the same process again: replaces its own, keeps the earlier
    written = json.loads(path.read_text())
    assert written["count"] == 4 and written["pid"] == os.getpid()
    assert written["earlier_incarnations"] == [{"count": 7, "pid": -1}]
