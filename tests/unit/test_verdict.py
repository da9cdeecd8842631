"""The run's verdict on its own real time and the machine section (pure functions)."""

from __future__ import annotations

from teleop.bus.messages import PROTOCOL_VERSION
from teleop.core.service_summaries import Drops
from teleop.run.assemble import service_records
from teleop.run.idle_poll import IdlePoll
from teleop.run.verdict import (
    CLEAN,
    DEGRADED,
    LOST,
    Privilege,
    drop_lines,
    machine_section,
    realtime_health,
    refused_privileges,
)

QUIET = {
    "overrun_fraction": 0.0002,
    "realtime_factor": 0.999,
    "watchdog_brakes": 0,
    "braked_steps": 0,
    "steps": 20_000,
    "drops": [],
    "unlinked_peers": {},
}


def test_a_quiet_realtime_run_is_clean():
    health = realtime_health("realtime", **QUIET)
    assert health.verdict == CLEAN and health.problems == ()


def test_a_few_short_brakes_degrade_a_run_and_say_how_many():
    health = realtime_health("realtime", **{**QUIET, "watchdog_brakes": 7, "braked_steps": 87})
    assert health.verdict == DEGRADED
    assert "7 time(s), 87 steps" in health.problems[0]


def test_a_starved_run_is_lost_with_every_bound_it_missed():
    starved = {
        **QUIET,
        "overrun_fraction": 0.08,
        "realtime_factor": 0.7,
        "watchdog_brakes": 40,
        "braked_steps": 1500,
    }
    health = realtime_health("realtime", **starved)
    assert health.verdict == LOST
    assert len(health.problems) == 3
    assert any("8.00%" in p for p in health.problems)
    assert any("0.700 x real time" in p for p in health.problems)


def test_lockstep_has_no_real_time_to_lose():
    slow = {**QUIET, "overrun_fraction": 0.5, "realtime_factor": 0.1}
    assert realtime_health("lockstep", **slow).verdict == CLEAN


def test_services_that_never_linked_degrade_a_run_as_missing_data_not_lost_real_time():
    unlinked = {**QUIET, "unlinked_peers": {"plant": ["recorder"], "hmd": ["recorder"]}}
    for mode in ("lockstep", "realtime"):
        health = realtime_health(mode, **unlinked)
        assert health.verdict == DEGRADED
        (problem,) = health.problems
        assert "plant never saw recorder; hmd never saw recorder" in problem
        assert "missing from the run" in problem
    # With a loop that lost real time as well, the verdict is the loop's.
    starved = {**unlinked, "realtime_factor": 0.7}
    health = realtime_health("realtime", **starved)
    assert health.verdict == LOST and len(health.problems) == 2
    assert "x real time" in health.problems[0]


def test_a_dropped_record_of_another_version_names_its_sender_and_both_versions():
    dropped = {
        "plant": Drops(
            counts={"JOINT_COMMAND:version": 5001},
            first={"JOINT_COMMAND:version": "5, expected 8"},
        ),
        "haptic": Drops(counts={"FORCE_FEEDBACK:range": 2}, first={}),
    }
    lines = drop_lines(dropped)
    assert lines[0] == (
        "plant dropped 5001 JOINT_COMMAND record(s) from controller: protocol version 5, "
        f"this stack speaks {PROTOCOL_VERSION}"
    )
    assert lines[1] == "haptic dropped 2 FORCE_FEEDBACK record(s) from controller: range"
    health = realtime_health("lockstep", **{**QUIET, "drops": lines})
    assert health.verdict == DEGRADED and list(health.problems) == lines


def test_the_machine_section_says_which_privileges_were_granted_and_refused():
    summaries = {
        "plant": {"privileges": {"sched_fifo": "refused: EPERM", "cpu_pinning": "granted [0]"}},
        "recorder": {"privileges": {"sched_fifo": "not requested", "cpu_pinning": "granted [1]"}},
        "eyeview": {"privileges": {}, "shm_pool": {"pool_bytes": 2 << 20, "reason": "ulimit"}},
    }
    idle = IdlePoll(cpus=(), failed={0: "not polled: EACCES"})
    machine = machine_section(service_records(summaries), [0], idle)
    assert machine.sched_fifo == Privilege(granted={}, refused={"plant": "refused: EPERM"})
    assert set(machine.cpu_pinning.granted) == {"plant", "recorder"}
    assert machine.to_json()["idle_cgroup"]["refused"] == {"0": "not polled: EACCES"}
    lines = refused_privileges(machine)
    assert len(lines) == 3
    assert lines[0].startswith("SCHED_FIFO refused for plant")
    assert "ulimit" in lines[2]
