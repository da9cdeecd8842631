"""Pieces of the service lifecycle that need no bus."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading

import pytest

from teleop.bench.relay import FLOOR_STAND_INS, RELAYS, PlantRelay
from teleop.bus.service import (
    Service,
    ServiceOptions,
    build_service_parser,
    fifo_scheduling,
    pin_to_cpus,
    read_summary,
)
from teleop.core.clock import FINE_SLEEP_MARGIN_NS, MonotonicClock
from teleop.core.config import load_config
from teleop.core.rundir import clear_run_results, incarnation_path, incarnation_paths


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
    # The loops, and the operator whose hand feeds them (not behind them: they can keep
    # both cores busy).
    for name in ("plant", "controller", "haptic", "operator"):
        assert cpu.fifo_priority_for(name, "realtime") == cpu.fifo_priority
        assert cpu.fifo_priority_for(name, "lockstep") == 0
    for name in ("recorder", "eyeview", "hmd"):
        assert cpu.fifo_priority_for(name, "realtime") == 0
    no_fifo = load_config(None, ["cpu.fifo_priority=0"]).cpu
    assert no_fifo.fifo_priority_for("plant", "realtime") == 0
    assert no_fifo.fifo_priority_for("operator", "realtime") == 0


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


class Counting(Service):
    name = "counting"
    count = 0

    def summary(self):
        return {"count": self.count}


def test_a_killed_process_counts_survive_in_its_running_summary(tmp_path):
    """A process killed with SIGKILL never closes: what it wrote while running is taken
    in by the next process's summary at close (and its file removed), oldest first."""
    killed = Counting(load_config(), ServiceOptions(run_dir=tmp_path))
    killed.count = 5
    killed.write_running_summary()
    # Stand in for that process having been another one: its file under another pid.
    own = incarnation_path(tmp_path, "counting", os.getpid())
    written = {**json.loads(own.read_text()), "pid": 123}
    incarnation_path(tmp_path, "counting", 123).write_text(json.dumps(written))
    own.unlink()
    assert read_summary(tmp_path, "counting") == {"count": 5, "pid": 123, "running": True}
    after = Counting(load_config(), ServiceOptions(run_dir=tmp_path))
    after.count = 2
    after.write_running_summary()  # the new one runs: the launcher sees both so far
    seen = read_summary(tmp_path, "counting")
    assert seen["count"] == 2 and seen["earlier_incarnations"][0]["count"] == 5
    after.count = 3
    after.close()  # at close: its summary, the killed one's taken in
    written = read_summary(tmp_path, "counting")
    assert written["count"] == 3 and "running" not in written
    assert written["earlier_incarnations"] == [{"count": 5, "pid": 123, "running": True}]
    assert incarnation_paths(tmp_path, "counting") == []
    # A run in the same directory again starts without them.
    incarnation_path(tmp_path, "counting", 7).write_text("{}")
    assert incarnation_path(tmp_path, "counting", 7) in clear_run_results(tmp_path)


def test_a_running_service_writes_its_summary_so_far_until_it_closes(tmp_path):
    service = Counting(load_config(), ServiceOptions(run_dir=tmp_path))
    service.count = 9
    service.start_running_summaries(period_s=0.001)
    path = incarnation_path(tmp_path, "counting", os.getpid())
    for _ in range(10_000):  # event driven would need a hook in the thread: poll its file
        if path.exists():
            break
        threading.Event().wait(0.001)
    assert read_summary(tmp_path, "counting")["count"] == 9
    service.close()  # joins the writer before the final summary: nothing left behind
    assert not path.exists() and service.running_summaries >= 1
    assert read_summary(tmp_path, "counting") == {"count": 9, "pid": os.getpid()}


class _Linked:
    """A stand-in session whose links are what the test says (Zenoh ids)."""

    def __init__(self, zids: list[str]) -> None:
        self.zids = zids
        self.info = self

    def peers_zid(self) -> list[str]:
        return list(self.zids)

    def is_closed(self) -> bool:
        return False


def test_a_linked_session_that_is_no_participant_is_counted_logged_and_announced_once(caplog):
    announced: list[list[str]] = []

    class Watching(Service):
        name = "plant"

        def on_strangers(self, zids: list[str]) -> None:
            announced.append(zids)

    service = Watching(load_config())
    service._participants = frozenset({"aa01", "bb02"})
    service.session = _Linked(["aa01", "BB02"])  # type: ignore[assignment]
    assert service.check_peers() == [] and announced == []
    service.session.zids.append("cc03")  # type: ignore[attr-defined]
    with caplog.at_level(logging.WARNING):
        assert service.check_peers() == ["cc03"]
        assert service.check_peers() == []  # still linked: not again
    assert announced == [["cc03"]] and service.unknown_peers == ["cc03"]
    assert caplog.text.count("cc03") == 1
    assert service.summary()["unknown_peers"] == ["cc03"]


# A process that takes the stop signal while its main thread holds the lock of the very
# Event the signal sets (the main thread inside ``stop.wait()``, between two bytecodes).
_SIGNAL_IN_WAIT = """
import logging, os, signal, sys, threading, time
from teleop.bus import service
logging.basicConfig(level=logging.INFO, stream=sys.stderr)
service.STOP_AGAIN_DUMP_S = float(sys.argv[1])
# The signals thread takes the second signal once stop.set() gets the lock the block below
# held: wait for its line (the process would otherwise exit first, that thread a daemon).
again = threading.Event()
class Again(logging.Handler):
    def emit(self, record):
        if " again" in record.getMessage():
            again.set()
logging.getLogger("teleop.bus.service").addHandler(Again())
stop = threading.Event()
service.stop_on_signals(stop)
with stop._cond:
    os.kill(os.getpid(), signal.SIGINT)
    time.sleep(0.2)
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(0.2)
print("stopped" if stop.wait(5.0) else "not stopped", flush=True)
again.wait(5.0)
"""


def _signal_in_wait(dump_after_s: float) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", _SIGNAL_IN_WAIT, str(dump_after_s)],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_a_stop_signal_in_the_middle_of_a_wait_stops_the_service():
    done = _signal_in_wait(dump_after_s=60.0)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "stopped"
    assert "signal SIGINT: stopping" in done.stderr
    assert "signal SIGTERM again" in done.stderr and "Thread 0x" not in done.stderr


def test_a_stop_signal_repeated_while_stopping_prints_where_each_thread_is():
    done = _signal_in_wait(dump_after_s=0.0)
    assert done.stdout.strip() == "stopped", done.stderr
    assert "signal SIGTERM again" in done.stderr
    assert "Thread 0x" in done.stderr and "in watch" in done.stderr


def test_hold_at_takes_sim_seconds_and_refuses_anything_else(capsys):
    parser = build_service_parser("plant")
    assert parser.parse_args(["--hold-at", "1.5,4"]).hold_at_ns == (1_500_000_000, 4 * 10**9)
    assert parser.parse_args([]).hold_at_ns == ()
    for bad in ("nan", "-1", "1.5,x", "inf"):
        with pytest.raises(SystemExit):
            parser.parse_args(["--hold-at", bad])
        assert "--hold-at" in capsys.readouterr().err
