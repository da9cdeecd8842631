"""Round trips over Zenoh for the measurements (``teleop latency --across-sites``,
tests/benchmarks/netem_round_trip.py): pings from one session, paced, each timed until
its answer comes back."""

from __future__ import annotations

import struct
import threading
import time

import numpy as np
import zenoh

# Waiting for the path to come up, and for the last answers (s).
TIMEOUT_S = 15.0


def paced_round_trips_ms(
    session: zenoh.Session, ping_key: str, pong_key: str, pings: int, rate_hz: float
) -> np.ndarray:
    """``pings`` pings put on ``ping_key`` at ``rate_hz`` once a first one came back on
    ``pong_key`` (every link and the answerer are up), each a (seq, send ns) pair that the
    answerer sends back as it is; the round trips (ms) of those that came back."""
    done: dict[int, float] = {}
    arrived = threading.Condition()

    def on_answer(sample: zenoh.Sample) -> None:
        seq, sent_ns = struct.unpack("<qq", sample.payload.to_bytes())
        with arrived:
            done[seq] = (time.monotonic_ns() - sent_ns) / 1e6
            arrived.notify_all()

    sub = session.declare_subscriber(pong_key, on_answer)
    pub = session.declare_publisher(ping_key, express=True)
    try:
        with arrived:
            deadline = time.monotonic() + TIMEOUT_S
            while -1 not in done and time.monotonic() < deadline:
                pub.put(struct.pack("<qq", -1, time.monotonic_ns()))
                arrived.wait(0.2)
        if -1 not in done:
            raise RuntimeError(f"no answer on {pong_key} within {TIMEOUT_S:g} s")
        period_s = 1.0 / rate_hz
        start = time.monotonic()
        for seq in range(pings):
            time.sleep(max(0.0, start + seq * period_s - time.monotonic()))
            pub.put(struct.pack("<qq", seq, time.monotonic_ns()))
        with arrived:
            arrived.wait_for(lambda: all(s in done for s in range(pings)), TIMEOUT_S)
    finally:
        sub.undeclare()
        pub.undeclare()
    return np.array([done[s] for s in range(pings) if s in done])
