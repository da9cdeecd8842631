"""Loopback ports for the processes of one run (bus endpoints, a web viewer's ports)."""

from __future__ import annotations

import socket

LOOPBACK = "127.0.0.1"


def free_loopback_port() -> int:
    """A TCP port on 127.0.0.1 that is free now (the OS picks it).

    The port stays unbound until the process given it listens there, seconds later, while
    a stack's peers open connections. Those cannot take it: Linux gives bind() to port
    0 odd ports and connect() even ones first (checked on this machine, kernel 6.18: 50
    of 50 each way), so only another bind() to port 0 could, with odds of about one in
    14000 per bind."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((LOOPBACK, 0))
        return int(s.getsockname()[1])
