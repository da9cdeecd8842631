"""Hosts on this machine for tests of a run across hosts: a network namespace each,
joined by veth pairs, with addresses that exist only inside those namespaces. Two hosts
(a robot's and the operator's), or three: a second robot's host too, linked to the
first robot's (the hub every other site's router connects to), and routed through it.

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
# The second robot's host and the first robot's end of their link.
HUB_SIDE_ADDRESS = "10.213.1.1"
SECOND_ROBOT_ADDRESS = "10.213.1.2"
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


def _link(ends: tuple[str, str], hosts: Sequence[tuple[Host, str]]) -> None:
    """A veth pair ``ends``, one end in each of ``hosts``' namespaces at its address."""
    _ip("link", "add", ends[0], "type", "veth", "peer", "name", ends[1])
    for (host, address), end in zip(hosts, ends, strict=True):
        _ip("link", "set", end, "netns", host.netns)
        _ip("-n", host.netns, "addr", "add", f"{address}/{PREFIX_LENGTH}", "dev", end)
        _ip("-n", host.netns, "link", "set", end, "up")


@contextmanager
def two_hosts() -> Iterator[tuple[Host, Host]]:
    """A robot host and an operator host, linked (:data:`ROBOT_ADDRESS`,
    :data:`OPERATOR_ADDRESS`), loopback up in each."""
    with _hosts(second_robot=False) as hosts:
        yield hosts[0], hosts[1]


@contextmanager
def three_hosts() -> Iterator[tuple[Host, Host, Host]]:
    """:func:`two_hosts` and a second robot's host, linked to the first robot's
    (:data:`SECOND_ROBOT_ADDRESS`), which it reaches at :data:`ROBOT_ADDRESS` too."""
    with _hosts(second_robot=True) as hosts:
        yield hosts[0], hosts[1], hosts[2]


@contextmanager
def _hosts(*, second_robot: bool) -> Iterator[list[Host]]:
    if os.geteuid() != 0:
        raise HostsUnavailable("network namespaces need root")
    if shutil.which("ip") is None:
        raise HostsUnavailable("no `ip` command (Debian package iproute2)")
    tag = f"{os.getpid()}"
    robot = Host(f"teleop-r{tag}", ROBOT_ADDRESS)
    operator = Host(f"teleop-o{tag}", OPERATOR_ADDRESS)
    hosts = [robot, operator]
    if second_robot:
        hosts.append(Host(f"teleop-s{tag}", SECOND_ROBOT_ADDRESS))
    pairs = [(f"vr{tag}", f"vo{tag}"), (f"vh{tag}", f"vs{tag}")]
    made: list[str] = []
    try:
        for host in hosts:
            _ip("netns", "add", host.netns)
            made.append(host.netns)
            _ip("-n", host.netns, "link", "set", "lo", "up")
        _link(pairs[0], [(robot, ROBOT_ADDRESS), (operator, OPERATOR_ADDRESS)])
        if second_robot:
            second = hosts[2]
            _link(pairs[1], [(robot, HUB_SIDE_ADDRESS), (second, SECOND_ROBOT_ADDRESS)])
            # The first robot's host owns ROBOT_ADDRESS: no forwarding needed to reach it.
            _ip("-n", second.netns, "route", "add", f"{ROBOT_ADDRESS}/32", "via", HUB_SIDE_ADDRESS)
        yield hosts
    finally:
        for netns in made:
            _remove(netns)
        # Left in this namespace only if moving them failed.
        for ends in pairs:
            subprocess.run(["ip", "link", "del", ends[0]], capture_output=True)
