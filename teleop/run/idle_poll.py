"""Idle polling: keep each CPU spinning instead of halting while a realtime stack runs.

Why. On a virtual machine (the project's 2-core KVM target) a CPU with nothing to run
executes HLT: the vCPU leaves its host core, which then serves other guests and refills
its caches with their data, and the next wake-up (a message for a loop service) costs an
exit to the hypervisor, an interrupt injection and a host reschedule before our thread
runs, on cold caches. The kernel's cure is to poll when idle (``idle=poll``, or the
``cpuidle-haltpoll`` driver and ``/dev/cpu_dma_latency``), but both need the boot command
line, and this guest runs with no cpuidle driver at all.

What. One process per CPU, pinned to it, spinning at the lowest CPU priority Linux
has. That takes two settings, and the second is the one that matters:

- the process runs under ``SCHED_IDLE`` (weight 3 against nice 0's 1024; any task that
  wakes preempts it at once);
- it first moves itself into a CPU cgroup marked idle (``cpu.idle = 1``, Linux 5.15+),
  so the same holds between groups. A SCHED_IDLE task is idle only within its group:
  left in its session's autogroup it competes at the root as a whole nice-0 group and
  can starve the CPU's kernel threads (ksoftirqd, the per-CPU workqueues) for minutes,
  until TCP loopback stops delivering and ``mprotect`` / ``madvise`` callers hang in D
  state. A poller that cannot join an idle group does not spin: it logs why and sleeps
  until stopped (the stack runs, just without polling).

What it gains is measured by ``tests/benchmarks/latency_stack_variants.py --variants
default,idle_poll_off`` (round trip and the services' own CPU time, as ratios; on a
2-core KVM guest both fall: the services' work runs on warm caches). The cost: the
CPUs read 100 % busy while a realtime stack runs. ``cpu.idle_poll = false`` turns it
off (laptops on battery, hosts shared with other work); lockstep runs never poll.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import signal
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

# prctl(2) option: the signal this process gets when its parent (supervisord) dies.
PR_SET_PDEATHSIG = 1
# The CPU cgroup the pollers share (created on first use, left for the next run).
IDLE_CGROUP_NAME = "teleop-idle-poll"
MOUNTINFO = Path("/proc/self/mountinfo")
# A poller's status (--status-file): spinning, or not (followed by ": <why>").
POLLING = "polling"
NOT_POLLED = "not polled"


class IdlePollUnavailable(RuntimeError):
    """This machine cannot run a poller safely (no idle CPU cgroup); the message says why."""


def cpu_cgroup_root(mountinfo: str) -> tuple[Path, int] | None:
    """Where the CPU controller's hierarchy is mounted, and its cgroup version (1 or 2),
    from the text of ``/proc/self/mountinfo``; None when there is none."""
    v2 = None
    for line in mountinfo.splitlines():
        fields, _, tail = line.partition(" - ")
        parts, super_parts = fields.split(), tail.split()
        if len(parts) < 5 or len(super_parts) < 3:
            continue
        mount_point, fs_type, super_options = Path(parts[4]), super_parts[0], super_parts[2]
        if fs_type == "cgroup" and "cpu" in super_options.split(","):
            return mount_point, 1
        if fs_type == "cgroup2" and v2 is None:
            controllers = mount_point / "cgroup.controllers"
            if controllers.exists() and "cpu" in controllers.read_text().split():
                v2 = mount_point
    return (v2, 2) if v2 is not None else None


def idle_cgroup_writable() -> bool:
    """Whether this process may set up the pollers' idle cgroup (:func:`join_idle_cgroup`):
    write access to the group's files when it exists, else to the hierarchy's root. Root
    may; an ordinary user may not (its stacks report every CPU as not polled)."""
    found = cpu_cgroup_root(MOUNTINFO.read_text())
    if found is None:
        return False
    group = found[0] / IDLE_CGROUP_NAME
    if group.is_dir():
        return all(os.access(group / name, os.W_OK) for name in ("cpu.idle", "cgroup.procs"))
    return os.access(found[0], os.W_OK)


def join_idle_cgroup() -> Path:
    """Move this process into the pollers' CPU cgroup, created with ``cpu.idle = 1``;
    return its directory. Raises :class:`IdlePollUnavailable` when it cannot."""
    found = cpu_cgroup_root(MOUNTINFO.read_text())
    if found is None:
        raise IdlePollUnavailable("no cgroup hierarchy with the cpu controller is mounted")
    root, version = found
    group = root / IDLE_CGROUP_NAME
    try:
        if version == 2 and "cpu" not in (root / "cgroup.subtree_control").read_text().split():
            (root / "cgroup.subtree_control").write_text("+cpu")
        group.mkdir(exist_ok=True)
        (group / "cpu.idle").write_text("1")
        (group / "cgroup.procs").write_text(str(os.getpid()))
    except OSError as exc:
        raise IdlePollUnavailable(f"cannot set up the idle cgroup {group}: {exc}") from exc
    if (group / "cpu.idle").read_text().strip() != "1":
        raise IdlePollUnavailable(f"{group}/cpu.idle did not take the value 1")
    return group


def poll_forever(cpu: int) -> None:
    """Pin this process to ``cpu``, drop to SCHED_IDLE and spin until a signal stops it.
    Call :func:`join_idle_cgroup` first (see the module docstring).

    Raises OSError when ``cpu`` is not one this process may run on.
    """
    os.sched_setaffinity(0, {cpu})
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    while True:
        pass


def _write_status(path: Path | None, status: str) -> None:
    if path is not None:
        path.write_text(status + "\n")


@dataclass(frozen=True)
class IdlePoll:
    """After a run: the CPUs whose poller polled, and why each other one did not (its
    status, :func:`read_status`)."""

    cpus: tuple[int, ...]
    failed: Mapping[int, str]

    def to_json(self) -> dict[str, object]:
        """The summary's ``idle_poll_cpus`` and ``idle_poll_failed``."""
        return {"idle_poll_cpus": list(self.cpus), "idle_poll_failed": dict(self.failed)}


def read_status(path: Path) -> str:
    """A poller's status file: POLLING, "not polled: <why>", or why there is none."""
    try:
        return path.read_text().strip() or f"{NOT_POLLED}: empty status file {path}"
    except OSError as exc:
        return f"{NOT_POLLED}: no status ({exc.strerror}: {path})"


def _exit_with_parent() -> None:
    """Ask the kernel for SIGTERM when the parent dies: an orphaned spinner would keep a
    CPU busy for ever (supervisord itself gets the same from the process that runs it)."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="teleop-idle-poll",
        description="Keep one CPU polling instead of halting while a realtime stack runs "
        "(SCHED_IDLE, in a CPU cgroup marked idle: anything else that wants the CPU gets "
        "it at once). Started by the stack under supervisord when cpu.idle_poll is true; "
        "see teleop/run/idle_poll.py for why.",
    )
    parser.add_argument("--cpu", type=int, required=True, help="the CPU to keep polling")
    parser.add_argument(
        "--status-file",
        type=Path,
        help="write here whether the CPU is polled: 'polling' or 'not polled: <why>' "
        "(the run's summary reads it)",
    )
    args = parser.parse_args(argv)
    parent_pid = os.getppid()
    _exit_with_parent()
    if os.getppid() != parent_pid:  # the parent died before the request took effect
        return 0
    allowed = sorted(os.sched_getaffinity(0))
    if args.cpu not in allowed:
        print(f"idle_poll: CPU {args.cpu} is not available here (have {allowed})", file=sys.stderr)
        return 2
    for stop_signal in (signal.SIGINT, signal.SIGTERM):  # SIGINT may come in ignored
        signal.signal(stop_signal, signal.default_int_handler)
    try:
        try:
            group = join_idle_cgroup()
        except IdlePollUnavailable as exc:
            print(f"idle_poll: CPU {args.cpu} not polled: {exc}", file=sys.stderr, flush=True)
            _write_status(args.status_file, f"{NOT_POLLED}: {exc}")
            signal.pause()  # stay up (supervisord would restart an exit) until stopped
            return 0
        print(
            f"idle_poll: CPU {args.cpu} polling (SCHED_IDLE, cgroup {group})",
            file=sys.stderr,
            flush=True,
        )
        _write_status(args.status_file, POLLING)
        poll_forever(args.cpu)
    except KeyboardInterrupt:  # supervisord's stop signal (SIGINT), or SIGTERM
        pass
    return 0
