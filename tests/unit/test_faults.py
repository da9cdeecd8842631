"""Fault injection without processes: the --kill / --freeze parsing, the measurements on
recorded state arrays, the injector on a fake clock, and the failure watch's expected
restarts."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from teleop.bus.messages import PLANT_STATE, Flag, Stage
from teleop.core.summary import FaultOutcome
from teleop.run.failure import ProgramWatch, ServiceFailed
from teleop.run.faults import (
    FREEZE,
    KILL,
    FaultInjector,
    FaultRecord,
    FaultSpec,
    FaultSpecError,
    InjectorHooks,
    StateLog,
    fault_report,
    parse_fault,
    parse_faults,
    world_reset,
)

SERVICES = ("plant", "controller", "recorder", "operator", "haptic", "hmd", "eyeview")
MS = 1_000_000
S = 1_000_000_000


# -- parsing -------------------------------------------------------------------------------


def test_kill_and_freeze_arguments_parse_into_sorted_faults():
    faults = parse_faults(["plant@7.5", "controller@2"], ["haptic@3:0.5"], SERVICES, 60.0)
    assert faults == [
        FaultSpec("controller", KILL, 2.0),
        FaultSpec("haptic", FREEZE, 3.0, 0.5),
        FaultSpec("plant", KILL, 7.5),
    ]
    assert faults[1].text() == "--freeze haptic@3:0.5"


@pytest.mark.parametrize(
    ("text", "kind", "message"),
    [
        ("controller", KILL, "expected SERVICE@T"),
        ("controller@", KILL, "expected SERVICE@T"),
        ("controller@-1", KILL, "expected SERVICE@T"),
        ("controller@1:2", KILL, "expected SERVICE@T"),
        ("controller@1", FREEZE, "expected SERVICE@T:SECONDS"),
        ("controller@1:0", FREEZE, "more than 0"),
        ("controler@1", KILL, "did you mean controller?"),
        ("zzz@1", KILL, "it runs plant, controller"),
    ],
)
def test_bad_fault_arguments_say_what_is_wrong(text, kind, message):
    with pytest.raises(FaultSpecError, match=message):
        parse_fault(text, kind, SERVICES)


def test_a_fault_after_the_run_ends_is_refused():
    with pytest.raises(FaultSpecError, match="ends at 10 s"):
        parse_faults(["controller@10"], [], SERVICES, 10.0)


# -- measurements --------------------------------------------------------------------------


def _log(rows: list[dict]) -> dict[str, np.ndarray]:
    """A StateLog filled from rows of (t_ns, step, braking, controller_tx_ns,
    haptic_sample_ns, speed as qd of joint 0)."""
    log = StateLog(n_joints=1, capacity=2)  # grows while filling
    for row in rows:
        rec = PLANT_STATE.new()
        rec["t_source_ns"] = row["t"]
        rec["step"] = row.get("step", 0)
        rec["sim_time_ns"] = row.get("step", 0) * MS
        rec["flags"] = Flag.BRAKING if row.get("braking") else Flag.NONE
        rec["trace_ns"][Stage.CONTROLLER_TX] = row.get("tx", 0)
        rec["trace_ns"][Stage.HAPTIC_SAMPLE] = row.get("sample", 0)
        rec["qd_rad_s"][0] = row.get("speed", 0.0)
        rec["n_joints"] = 1
        log.add(rec)
    return log.arrays()


def _speed(arrays):
    return lambda i: abs(float(arrays["qd_rad_s"][i][0]))  # the tool speed, m/s


def test_a_killed_controller_brake_restart_and_resume_are_measured_from_the_states():
    inject = 100 * MS
    rows = [{"t": t * MS, "speed": 0.05, "tx": t * MS - 1} for t in range(90, 100)]
    # killed at 100 ms: the plant brakes at 120 ms, the arm is still at 150 ms
    rows += [{"t": t * MS, "speed": 0.05, "tx": 99 * MS} for t in range(100, 120)]
    rows += [{"t": t * MS, "speed": 0.05 * (150 - t) / 30, "braking": True, "tx": 99 * MS}
             for t in range(120, 400)]  # fmt: skip
    # new controller ready at 400 ms; its first command applied at 450 ms
    rows += [{"t": t * MS, "tx": 99 * MS, "braking": True} for t in range(400, 450)]
    rows += [{"t": t * MS, "tx": t * MS - 1, "speed": 0.01} for t in range(450, 500)]
    arrays = _log(rows)
    record = FaultRecord(FaultSpec("controller", KILL, 5.0), t_s=5.0, inject_ns=inject,
                         ready_ns=400 * MS)  # fmt: skip
    report = fault_report(record, arrays, _speed(arrays), success=True)
    assert report.brake_ms == pytest.approx(50.0, abs=1.01)  # below 1 mm/s at ~150 ms
    assert report.restart_s == pytest.approx(0.3)
    assert report.resumed_s == pytest.approx(0.35)
    assert report.success is True and report.kind == KILL


def test_a_frozen_haptic_device_resumes_with_its_first_new_sample():
    rows = [{"t": t * MS, "step": t, "sample": min(t, 100) * MS, "speed": 0.0}
            for t in range(90, 300)]  # fmt: skip
    rows += [{"t": t * MS, "step": t, "sample": (t - 5) * MS, "speed": 0.02}
             for t in range(300, 320)]  # fmt: skip
    arrays = _log(rows)
    record = FaultRecord(FaultSpec("haptic", FREEZE, 1.0, 0.15), t_s=1.0, inject_ns=100 * MS,
                         thaw_ns=250 * MS)  # fmt: skip
    report = fault_report(record, arrays, _speed(arrays), success=False)
    assert report.brake_ms == 0.0  # already still when frozen
    assert report.restart_s is None  # a freeze has no restart
    assert report.t_s == 0.1  # the plant's sim time at the injection, from its states
    assert report.frozen_s == pytest.approx(0.15)
    # the first state after the thaw carrying a sample taken after it: at 300 ms (sample 295)
    assert report.resumed_s == pytest.approx(0.2)


def test_a_service_off_the_command_path_resumes_when_back_and_need_not_brake():
    rows = [{"t": t * MS, "speed": 0.05, "tx": t * MS} for t in range(0, 1000)]
    arrays = _log(rows)
    record = FaultRecord(FaultSpec("recorder", KILL, 0.1), t_s=0.1, inject_ns=100 * MS,
                         ready_ns=700 * MS)  # fmt: skip
    report = fault_report(record, arrays, _speed(arrays), success=True)
    assert report.brake_ms is None  # the arm never stopped
    assert report.restart_s == pytest.approx(0.6)
    assert report.resumed_s == pytest.approx(0.6)


def test_a_fault_that_could_not_be_injected_reports_its_error():
    record = FaultRecord(FaultSpec("hmd", KILL, 1.0), error="SIGKILL failed: not running")
    report = fault_report(record, _log([{"t": 1}]), lambda i: 0.0, success=None)
    assert report.error.startswith("SIGKILL failed")
    assert report.brake_ms is None and report.resumed_s is None
    assert report.to_json()["error"] == report.error  # written only when there is one
    assert "error" not in FaultOutcome("hmd", KILL).to_json()
    assert FaultOutcome.from_json(report.to_json()) == report


def test_a_plant_that_comes_back_at_step_0_reset_the_world():
    rows = [{"t": t * MS, "step": t} for t in range(1, 100)]
    killed = FaultRecord(FaultSpec("plant", KILL, 0.099), t_s=0.099, step=99,
                         inject_ns=99 * MS + 1)  # fmt: skip
    assert not world_reset(killed, _log(rows))  # nothing from the new one yet
    assert world_reset(killed, _log([*rows, {"t": 500 * MS, "step": 0}]))
    assert not world_reset(killed, _log([*rows, {"t": 500 * MS, "step": 90}]))  # resumed


# -- the injector --------------------------------------------------------------------------


def _wait_until(condition: Callable[[], bool], timeout_s: float = 5.0) -> None:
    """Wait for another thread's work (a bound against a hang, not a measurement)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "not reached"
        time.sleep(0.001)


class FakeClock:
    def __init__(self) -> None:
        self.t_ns = 0

    def now_ns(self) -> int:
        return self.t_ns


def test_the_injector_kills_and_freezes_on_sim_time_and_thaws_on_close():
    sent: list[tuple[str, int]] = []
    expected: list[str] = []
    clock = FakeClock()
    done = threading.Event()

    pids = {"controller": 10, "haptic": 20}
    names = {pid: name for name, pid in pids.items()}

    def signal_group(pid: int, signum: int) -> None:
        sent.append((names[pid], signum))
        done.set()

    faults = [FaultSpec("controller", KILL, 1.0), FaultSpec("haptic", FREEZE, 2.0, 3600.0)]
    released: list[float] = []
    hooks = InjectorHooks(pids.__getitem__, signal_group, expected.append, clock.now_ns,
                          released.append)  # fmt: skip
    injector = FaultInjector(faults, hooks)
    injector.start()
    try:
        injector.on_state(int(0.5 * S), 500)
        assert not done.wait(0.05)  # not due yet
        clock.t_ns = 7 * S
        injector.on_state(1 * S, 1000)
        assert done.wait(5)
        done.clear()
        assert sent == [("controller", signal.SIGKILL)] and expected == ["controller"]
        _wait_until(lambda: released == [1.0])  # the held plant steps on once injected
        injector.on_ready("controller", 8 * S)
        injector.on_state(int(2.001 * S), 2001)
        assert done.wait(5)
    finally:
        injector.close()
    assert sent[1:] == [("haptic", signal.SIGSTOP), ("haptic", signal.SIGCONT)]
    assert released == [1.0, 2.0]
    kill, freeze = injector.records
    assert (kill.t_s, kill.step, kill.inject_ns, kill.ready_ns) == (1.0, 1000, 7 * S, 8 * S)
    assert freeze.t_s == pytest.approx(2.001) and freeze.thaw_ns == 7 * S


def test_in_realtime_a_fault_is_due_on_the_clock_from_the_plants_start():
    """Realtime: due ``at_s`` after the plant's STARTED stamp, whether or not this process
    has received the states of that instant yet."""
    clock, done = FakeClock(), threading.Event()
    hooks = InjectorHooks(lambda name: 10, lambda pid, signum: done.set(), lambda n: None,
                          clock.now_ns, lambda at_s: None)  # fmt: skip
    injector = FaultInjector([FaultSpec("controller", KILL, 1.0)], hooks, realtime=True)
    injector.start()
    try:
        injector.on_started(5 * S)
        clock.t_ns = 5 * S + S // 2
        assert not done.wait(0.05)
        clock.t_ns = 6 * S  # no state came: the clock alone makes it due
        assert done.wait(5)
    finally:
        injector.close()
    assert injector.records[0].inject_ns == 6 * S


def test_the_pid_of_a_service_not_running_at_start_is_known_before_its_fault_is_due():
    """Lockstep races ahead while a supervisor answers: the pid of a service that was not
    running when the injector started is looked up again once its ready token comes (or
    a retry later), not at the fault's instant."""
    running = threading.Event()
    found = threading.Event()
    asked: list[str] = []

    def pid_of(name: str) -> int:
        asked.append(name)
        if not running.is_set():
            raise RuntimeError("controller: no such process yet")
        found.set()
        return os.getpgrp()  # a process group that exists, as a running service's

    killed = threading.Event()
    hooks = InjectorHooks(pid_of, lambda pid, signum: killed.set(), lambda n: None, int,
                          lambda at_s: None)  # fmt: skip
    injector = FaultInjector([FaultSpec("controller", KILL, 1.0)], hooks)
    injector.start()
    try:
        injector.on_state(0, 0)
        running.set()
        injector.on_ready("controller", 1)
        assert found.wait(5)  # looked up ahead, on the ready token
        calls = len(asked)
        injector.on_state(1 * S, 1000)
        assert killed.wait(5)
    finally:
        injector.close()
    assert len(asked) == calls  # nothing asked at the instant
    assert injector.records[0].pid == os.getpgrp() and injector.records[0].t_s == 1.0


def test_a_fault_on_a_service_that_is_not_running_is_reported_not_injected():
    asked = threading.Semaphore(0)

    def pid_of(name: str) -> int:
        asked.release()
        return 0  # supervisord's pid of a program that is not running

    released = threading.Event()
    hooks = InjectorHooks(pid_of, lambda pid, signum: None, lambda name: None, int,
                          lambda at_s: released.set())  # fmt: skip
    injector = FaultInjector([FaultSpec("hmd", KILL, 0.0)], hooks)
    injector.start()
    injector.on_state(0, 0)
    assert asked.acquire(timeout=5) and asked.acquire(timeout=5)  # ahead, then at the instant
    assert released.wait(5)  # a held lockstep run goes on without the fault
    injector.close()
    (record,) = injector.records
    assert record.error.startswith("no process") and record.inject_ns == 0


# -- the failure watch ---------------------------------------------------------------------


def _infos(pid: int, state: str = "RUNNING") -> list[dict]:
    return [{"name": "controller", "statename": state, "pid": pid, "exitstatus": 0}]


def test_an_expected_kill_and_its_one_restart_pass_the_watch_but_a_second_one_fails():
    watch = ProgramWatch(lambda name: Path(f"/logs/{name}.log"), lambda path: "boom")
    watch.check(_infos(10))
    watch.expect_restart("controller")
    watch.check(_infos(0, "EXITED"))  # killed, not yet restarted
    watch.check(_infos(11, "STARTING"))
    watch.check(_infos(11))
    with pytest.raises(ServiceFailed, match="restarted"):
        watch.check(_infos(12))
