"""The idle poller (teleop/run/idle_poll.py) as a real process: pinned, SCHED_IDLE in the
idle cgroup, leaves its CPU to any other process, stops on supervisord's signal, exits
with its parent, refuses a CPU it may not use; and which stacks get one per CPU."""

import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pytest

from teleop.core.config import load_config
from teleop.core.rundir import idle_poll_status_path
from teleop.run.assemble import idle_poll_report
from teleop.run.idle_poll import (
    IDLE_CGROUP_NAME,
    POLLING,
    cpu_cgroup_root,
    idle_cgroup_writable,
    read_status,
)
from teleop.run.stack import (
    IDLE_POLL_PRIORITY,
    PRIORITY,
    idle_poll_cpus,
    idle_poll_programs,
)

# Waits poll with a deadline; the deadline only bounds a failure.
WAIT_TIMEOUT_S = 10.0
POLL_S = 0.02
POLLER = [sys.executable, "-m", "services.idle_poll"]


needs_idle_cgroup = pytest.mark.skipif(
    not idle_cgroup_writable(),
    reason="the idle cgroup needs write access to the CPU cgroup (root): no poller runs",
)


def _wait_for(predicate, what: str) -> None:
    deadline = time.monotonic() + WAIT_TIMEOUT_S
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(POLL_S)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def _user_ticks(pid: int) -> int:
    """CPU time (clock ticks) ``pid`` has spent in user space."""
    with open(f"/proc/{pid}/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[11])


def _is_polling(pid: int) -> bool:
    return os.sched_getscheduler(pid) == os.SCHED_IDLE


@needs_idle_cgroup
def test_poller_spins_pinned_at_sched_idle_and_stops_on_sigint(tmp_path):
    cpu = max(os.sched_getaffinity(0))
    status = idle_poll_status_path(tmp_path, cpu)
    proc = subprocess.Popen(
        [*POLLER, "--cpu", str(cpu), "--status-file", str(status)],
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        _wait_for(lambda: _is_polling(proc.pid), "the poller to drop to SCHED_IDLE")
        assert os.sched_getaffinity(proc.pid) == {cpu}
        with open(f"/proc/{proc.pid}/cgroup") as f:
            assert f"/{IDLE_CGROUP_NAME}\n" in f.read()
        _wait_for(lambda: _user_ticks(proc.pid) > 0, "the poller to spin in user space")
        assert read_status(status) == POLLING
        report = idle_poll_report([cpu], tmp_path)
        assert report.to_json() == {"idle_poll_cpus": [cpu], "idle_poll_failed": {}}
        proc.send_signal(signal.SIGINT)
        assert proc.wait(WAIT_TIMEOUT_S) == 0
        assert f"CPU {cpu} polling (SCHED_IDLE, cgroup" in proc.stderr.read()
    finally:
        proc.kill()
        proc.wait()


@needs_idle_cgroup
def test_poller_sits_in_a_cgroup_marked_idle_so_any_other_process_preempts_it():
    # SCHED_IDLE alone is not enough: a spinner left in its session's autogroup competes
    # at the root as a nice-0 group (another session's CPU-bound process got half the CPU)
    # and starves the CPU's kernel threads. Inside a cgroup with cpu.idle = 1 the whole
    # group yields to any other work. How much of the CPU another process gets is a
    # measurement: tests/benchmarks/idle_poll_share.py prints it as a ratio.
    cpu = max(os.sched_getaffinity(0))
    poller = subprocess.Popen([*POLLER, "--cpu", str(cpu)], stderr=subprocess.DEVNULL)
    try:
        _wait_for(lambda: _is_polling(poller.pid), "the poller to start")
        with open(f"/proc/{poller.pid}/cgroup") as f:
            groups = [line.rsplit(":", 1)[1] for line in f.read().splitlines()]
        assert f"/{IDLE_CGROUP_NAME}" in groups
        found = cpu_cgroup_root(Path("/proc/self/mountinfo").read_text())
        assert found is not None
        assert (found[0] / IDLE_CGROUP_NAME / "cpu.idle").read_text().strip() == "1"
    finally:
        poller.send_signal(signal.SIGINT)
        poller.wait(WAIT_TIMEOUT_S)


@needs_idle_cgroup
def test_poller_exits_when_its_parent_dies():
    # The parent starts a poller, prints its pid and sleeps; SIGKILL on the parent must not
    # leave an orphan spinning (PR_SET_PDEATHSIG).
    script = (
        "import subprocess, sys, time; "
        f"p = subprocess.Popen({POLLER!r} + ['--cpu', '{min(os.sched_getaffinity(0))}']); "
        "print(p.pid, flush=True); time.sleep(60)"
    )
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    poller_pid = int(parent.stdout.readline())
    try:
        _wait_for(lambda: _is_polling(poller_pid), "the poller to start")
        parent.kill()
        parent.wait()
        _wait_for(lambda: not _alive(poller_pid), "the orphaned poller to exit")
    finally:
        if _alive(poller_pid):
            os.kill(poller_pid, signal.SIGKILL)


def test_poller_refuses_a_cpu_it_may_not_use():
    missing = max(os.sched_getaffinity(0)) + 64
    proc = subprocess.run(
        [*POLLER, "--cpu", str(missing)], capture_output=True, text=True, timeout=30
    )
    assert proc.returncode == 2
    assert f"CPU {missing} is not available" in proc.stderr


def _programs(config, run_dir=Path("/nonexistent")):
    """The pollers a stack run with ``config`` gets (as the stack builds them)."""
    return idle_poll_programs(idle_poll_cpus(config), run_dir)


def test_realtime_stacks_get_one_poller_per_cpu_started_first(tmp_path):
    config = load_config(None, ['run.mode="realtime"'])
    cpus = sorted(os.sched_getaffinity(0))
    stale = idle_poll_status_path(tmp_path, cpus[0])
    stale.write_text(POLLING)  # a previous run's
    programs = _programs(config, tmp_path)
    assert not stale.exists()
    assert [p.name for p in programs] == [f"idle_poll_cpu{c}" for c in cpus]
    for program, cpu in zip(programs, cpus, strict=True):
        status = str(idle_poll_status_path(tmp_path, cpu))
        assert program.command[-4:] == ["--cpu", str(cpu), "--status-file", status]
        assert program.priority == IDLE_POLL_PRIORITY < min(PRIORITY.values())


def test_the_report_names_only_cpus_whose_poller_polled(tmp_path):
    """A poller that could not join the idle cgroup says so in its status file, and one
    that never wrote its status did not poll either."""
    idle_poll_status_path(tmp_path, 0).write_text(POLLING + "\n")
    idle_poll_status_path(tmp_path, 1).write_text("not polled: no CPU cgroup hierarchy\n")
    report = idle_poll_report([0, 1, 2], tmp_path)
    assert report.cpus == (0,)
    assert report.failed[1] == "not polled: no CPU cgroup hierarchy"
    assert report.failed[2].startswith("not polled: no status")


def test_lockstep_and_disabled_stacks_get_no_poller():
    config = load_config(None, ['run.mode="lockstep"'])
    assert _programs(config) == []
    realtime = load_config(None, ['run.mode="realtime"'])
    assert _programs(replace(realtime, cpu=replace(realtime.cpu, idle_poll=False))) == []
    assert _programs(load_config(None, ["cpu.idle_poll=false"])) == []


def test_cpu_cgroup_root_finds_the_cpu_hierarchy_v1_first(tmp_path):
    v1 = (
        "31 23 0:28 / /sys/fs/cgroup rw,relatime - tmpfs tmpfs rw,mode=755\n"
        "33 31 0:30 / /sys/fs/cgroup/cpuacct rw,relatime - cgroup cgroup rw,cpuacct\n"
        "32 31 0:29 / /sys/fs/cgroup/cpu rw,relatime - cgroup cgroup rw,cpu\n"
    )
    assert cpu_cgroup_root(v1) == (Path("/sys/fs/cgroup/cpu"), 1)
    unified = tmp_path / "unified"
    unified.mkdir()
    (unified / "cgroup.controllers").write_text("cpuset cpu io memory pids\n")
    v2 = f"40 23 0:31 / {unified} rw,nosuid - cgroup2 cgroup2 rw\n"
    assert cpu_cgroup_root(v2) == (unified, 2)
    (unified / "cgroup.controllers").write_text("memory pids\n")
    assert cpu_cgroup_root(v2) is None
    assert cpu_cgroup_root("") is None


def test_idle_poll_cpus_narrow_the_polled_cpus_to_those_available():
    cpus = sorted(os.sched_getaffinity(0))
    config = load_config(None, ['run.mode="realtime"', f"cpu.idle_poll_cpus=[{cpus[-1]}, 999]"])
    assert [p.name for p in _programs(config)] == [f"idle_poll_cpu{cpus[-1]}"]
