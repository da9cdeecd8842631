"""Idle polling: keep each CPU spinning instead of halting while a realtime stack runs.

Why. On a virtual machine (the project's 2-core KVM target) a CPU with nothing to run
executes HLT: the vCPU leaves its host core, which then serves other guests and refills
its caches with their data, and the next wake-up (a message for a loop service) costs an
exit to the hypervisor, an interrupt injection and a host reschedule before our thread
runs, on cold caches. The kernel's cure is to poll when idle (``idle=poll``, or the
``cpuidle-haltpoll`` driver and ``/dev/cpu_dma_latency``), but both need the boot command
line, and this guest runs with no cpuidle driver at all.

What. One process per CPU, pinned to it, under ``SCHED_IDLE``, spinning. ``SCHED_IDLE``
runs only when nothing else wants that CPU: a SCHED_FIFO loop service or a normally
scheduled service that wakes preempts it at once, and against busy normal tasks it gets
a weight of 3 against nice 0's 1024. So it never delays or starves a service; it only
fills the time the CPU would have halted, and the vCPU stays on its core.

Measured (2026-11-22, this machine, ``teleop latency`` stack, 3 alternating rounds of
15 s): round trip p50 761 -> 558 us (0.73x), p99 1233 -> 1103 us (0.89x), every hop
lower, and the services' own CPU time 1.5 -> 1.1 cores (their work runs on warm caches).
The bare relay chain (the floor), paced at 1 kHz: p50 0.30 -> 0.20 ms, p99 0.62 -> 0.36
ms. Back to back (no idle time to fill) it does not change. The cost: the CPUs read 100 %
busy while a realtime stack runs. ``cpu.idle_poll = false`` turns it off (laptops on
battery, hosts shared with other work); lockstep runs never poll.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import signal
import sys

# prctl(2) option: the signal this process gets when its parent (supervisord) dies.
PR_SET_PDEATHSIG = 1


def poll_forever(cpu: int) -> None:
    """Pin this process to ``cpu``, drop to SCHED_IDLE and spin until a signal stops it.

    Raises OSError when ``cpu`` is not one this process may run on.
    """
    os.sched_setaffinity(0, {cpu})
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    while True:
        pass


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
        "(SCHED_IDLE: any service that wakes preempts it). Started by the stack under "
        "supervisord when cpu.idle_poll is true; see teleop/idle_poll.py for why.",
    )
    parser.add_argument("--cpu", type=int, required=True, help="the CPU to keep polling")
    args = parser.parse_args(argv)
    parent_pid = os.getppid()
    _exit_with_parent()
    if os.getppid() != parent_pid:  # the parent died before the request took effect
        return 0
    allowed = sorted(os.sched_getaffinity(0))
    if args.cpu not in allowed:
        print(f"idle_poll: CPU {args.cpu} is not available here (have {allowed})", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    print(f"idle_poll: CPU {args.cpu} polling (SCHED_IDLE)", file=sys.stderr, flush=True)
    try:
        poll_forever(args.cpu)
    except KeyboardInterrupt:  # supervisord's stop signal (SIGINT), or SIGTERM
        pass
    return 0
