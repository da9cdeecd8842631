"""What the integration tests of access control share: a loopback endpoint on a free
port, and a subscription callback that collects seqs and lets a test wait for them."""

from __future__ import annotations

import threading

import numpy as np

from teleop.core.net import free_loopback_port

TIMEOUT_S = 10.0  # generous bound on any single wait; passing runs take well under 1 s


def free_endpoint(scheme: str = "tcp") -> str:
    """``<scheme>/127.0.0.1:<port>`` on a port the OS just reported free."""
    return f"{scheme}/127.0.0.1:{free_loopback_port()}"


class Seen:
    """Records received on one subscription, by seq."""

    def __init__(self) -> None:
        self.seqs: list[int] = []
        self.cond = threading.Condition()

    def __call__(self, rec: np.ndarray, rx_ns: int) -> None:
        with self.cond:
            self.seqs.append(int(rec["seq"]))
            self.cond.notify_all()

    def wait(self, count: int) -> bool:
        """Whether ``count`` records came within TIMEOUT_S."""
        with self.cond:
            return self.cond.wait_for(lambda: len(self.seqs) >= count, TIMEOUT_S)

    def wait_seq(self, seq: int) -> bool:
        """Whether the record ``seq`` came within TIMEOUT_S."""
        with self.cond:
            return self.cond.wait_for(lambda: seq in self.seqs, TIMEOUT_S)
