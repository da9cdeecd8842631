"""Loopback ports for the processes of one run (bus endpoints, a web viewer's ports), and
the address of a Zenoh endpoint."""

from __future__ import annotations

import socket
from contextlib import ExitStack

LOOPBACK = "127.0.0.1"


class LoopbackPorts(ExitStack):
    """Free TCP ports on 127.0.0.1 for the processes of one run, each held by this
    process until :meth:`close`.

    A port is handed out seconds before the process given it listens there. Meanwhile
    it stays bound here (with SO_REUSEADDR, not listening), so nothing else binds it:
    not the next port taken here (every port taken is distinct), not another launcher's
    pick, not any program's bind to port 0 (the kernel skips a bound port). Released at
    once, the picks of one stack could repeat (the kernel draws each from its ephemeral
    range, so 8 picks among its ports meet about 28 / ports of the time), and one of the
    run's services then could not listen. The process given the port can still listen
    on it: Zenoh's listeners and Rust's set SO_REUSEADDR too. Close once the processes
    listen, or when the run ends (an :class:`~contextlib.ExitStack` of the held sockets).
    """

    def take(self) -> int:
        """A free port, distinct from every other taken here and held until close()."""
        held = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.enter_context(held)
        held.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        held.bind((LOOPBACK, 0))
        return int(held.getsockname()[1])


def free_loopback_port() -> int:
    """One TCP port on 127.0.0.1 that is free now, released at once: for a test's or
    a tool's single listener. Several ports for one run: :class:`LoopbackPorts`."""
    with LoopbackPorts() as ports:
        return ports.take()


def endpoint_address(endpoint: str) -> tuple[str, str]:
    """The host and port of a Zenoh endpoint ``proto/HOST:PORT`` (an IPv6 host without
    its brackets; both empty where the endpoint has none)."""
    host, _, port = endpoint.partition("/")[2].rpartition(":")
    return host.strip("[]"), port
