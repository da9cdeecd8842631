"""Two hosts on this machine for tests of a run across hosts: a network namespace each,
joined by a veth pair, with addresses that exist only inside those two namespaces.

Needs root (``ip netns``, from iproute2); :func:`two_hosts` raises HostsUnavailable,
saying why, where it cannot make them. Namespaces are named after this process, so test
sessions running at once do not meet; everything is removed on exit, the processes
started inside first.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

# A /30 of the private range: inside the two namespaces only, never on the machine's own
# interfaces (each pair of namespaces has its own network stack).
ROBOT_ADDRESS = "10.213.0.1"
OPERATOR_ADDRESS = "10.213.0.2"
PREFIX_LENGTH = 30


class HostsUnavailable(RuntimeError):
    """This machine cannot make test hosts (not root, no iproute2, no namespaces)."""


@dataclass(frozen=True)
class Host:
    """A network namespace standing for a host."""

    netns: str
    address: str

    def argv(self, command: Sequence[str]) -> list[str]:
        """``command`` run inside this host's namespace."""
        return ["ip", "netns", "exec", self.netns, *command]


def _ip(*args: str) -> None:
    result = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)
    if result.returncode != 0:
        raise HostsUnavailable(f"ip {' '.join(args)}: {result.stderr.strip()}")


def _remove(netns: str) -> None:
    """Kill what runs in ``netns``, then remove it (its veth end goes with it)."""
    pids = subprocess.run(["ip", "netns", "pids", netns], capture_output=True, text=True)
    for pid in pids.stdout.split():
        try:
            os.kill(int(pid), signal.SIGKILL)
        except ProcessLookupError:
            pass
    subprocess.run(["ip", "netns", "del", netns], capture_output=True)


@contextmanager
def two_hosts() -> Iterator[tuple[Host, Host]]:
    """A robot host and an operator host, linked (:data:`ROBOT_ADDRESS`,
    :data:`OPERATOR_ADDRESS`), loopback up in each."""
    if os.geteuid() != 0:
        raise HostsUnavailable("network namespaces need root")
    if shutil.which("ip") is None:
        raise HostsUnavailable("no `ip` command (Debian package iproute2)")
    tag = f"{os.getpid()}"
    robot = Host(f"teleop-r{tag}", ROBOT_ADDRESS)
    operator = Host(f"teleop-o{tag}", OPERATOR_ADDRESS)
    ends = (f"vr{tag}", f"vo{tag}")
    made: list[str] = []
    try:
        for host in (robot, operator):
            _ip("netns", "add", host.netns)
            made.append(host.netns)
        _ip("link", "add", ends[0], "type", "veth", "peer", "name", ends[1])
        for host, end in zip((robot, operator), ends, strict=True):
            _ip("link", "set", end, "netns", host.netns)
            _ip("-n", host.netns, "addr", "add", f"{host.address}/{PREFIX_LENGTH}", "dev", end)
            _ip("-n", host.netns, "link", "set", end, "up")
            _ip("-n", host.netns, "link", "set", "lo", "up")
        yield robot, operator
    finally:
        for netns in made:
            _remove(netns)
        # Left in this namespace only if moving it failed.
        subprocess.run(["ip", "link", "del", ends[0]], capture_output=True)
