"""The network emulator (teleop.bench.netem) on real sockets and a real Zenoh link.

What a test of distance relies on: every byte arrives, in order, and no sooner than the
delay asked for. (Wall-clock bounds from above are not asserted: a busy machine only
adds to them.)
"""

from __future__ import annotations

import contextlib
import os
import socket
import struct
import threading
import time

import zenoh

from teleop.bench.netem import LinkCut, LinkImpairment, running_proxy
from teleop.bus import session as bus
from teleop.core.config import BusConfig
from tests.integration.receiving import free_endpoint

TIMEOUT_S = 10.0


class EchoServer:
    """A TCP server on a loopback port that sends back whatever it receives."""

    def __init__(self) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            threading.Thread(target=self._echo, args=(conn,), daemon=True).start()

    @staticmethod
    def _echo(conn: socket.socket) -> None:
        with conn:
            while data := conn.recv(65536):
                conn.sendall(data)

    def close(self) -> None:
        self.sock.close()


def _receive(conn: socket.socket, size: int) -> bytes:
    chunks, got = [], 0
    while got < size:
        chunk = conn.recv(min(65536, size - got))
        assert chunk, "the proxy closed the stream early"
        chunks.append(chunk)
        got += len(chunk)
    return b"".join(chunks)


def test_every_byte_comes_back_in_order_through_jitter_and_loss():
    echo = EchoServer()
    link = LinkImpairment(delay_s=0.002, jitter_s=0.002, loss=0.02, retransmit_s=0.01)
    payload = os.urandom(2_000_000)
    try:
        with running_proxy(("127.0.0.1", echo.port), link, seed=3) as proxy:
            with socket.create_connection(("127.0.0.1", proxy.port), timeout=TIMEOUT_S) as conn:
                sender = threading.Thread(target=conn.sendall, args=(payload,))
                sender.start()
                back = _receive(conn, len(payload))
                sender.join(TIMEOUT_S)
            stats = proxy.stats()
    finally:
        echo.close()
    assert back == payload
    assert stats["forward"]["bytes"] == stats["backward"]["bytes"] == len(payload)
    assert stats["forward"]["lost"] + stats["backward"]["lost"] > 0  # losses were emulated


def test_a_round_trip_takes_at_least_twice_the_one_way_delay():
    echo = EchoServer()
    delay_s = 0.03
    try:
        with running_proxy(("127.0.0.1", echo.port), LinkImpairment(delay_s=delay_s)) as proxy:
            with socket.create_connection(("127.0.0.1", proxy.port), timeout=TIMEOUT_S) as conn:
                trips = []
                for k in range(5):
                    start = time.monotonic()
                    conn.sendall(struct.pack("<I", k))
                    assert struct.unpack("<I", _receive(conn, 4))[0] == k
                    trips.append(time.monotonic() - start)
    finally:
        echo.close()
    assert min(trips) >= 2 * delay_s


def test_a_zenoh_link_through_the_proxy_carries_samples_no_sooner_than_the_delay():
    """Two sessions linked only through the proxy (as two sites' routers would be): a
    sample's one-way time is at least the delay."""
    delay_s = 0.025
    listen = free_endpoint()
    port = int(listen.rsplit(":", 1)[1])
    got: list[float] = []
    arrived = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        sent_ns = struct.unpack("<q", sample.payload.to_bytes())[0]
        got.append((time.monotonic_ns() - sent_ns) / 1e9)
        if len(got) >= 5:
            arrived.set()

    near = bus.open_session(BusConfig(endpoint=listen, shm=False, zenoh_config="local.json5"),
                            listen=True)  # fmt: skip
    try:
        subscriber = near.declare_subscriber("teleop/netem/test", on_sample)
        with running_proxy(("127.0.0.1", port), LinkImpairment(delay_s=delay_s)) as proxy:
            far_endpoint = f"tcp/127.0.0.1:{proxy.port}"
            far = bus.open_session(
                BusConfig(endpoint=far_endpoint, shm=False, zenoh_config="local.json5"),
                listen=False,
            )
            try:
                publisher = far.declare_publisher("teleop/netem/test")
                deadline = time.monotonic() + TIMEOUT_S
                while not arrived.is_set() and time.monotonic() < deadline:
                    publisher.put(struct.pack("<q", time.monotonic_ns()))
                    arrived.wait(0.05)
                publisher.undeclare()
            finally:
                far.close()
            stats = proxy.stats()
        subscriber.undeclare()
    finally:
        near.close()
    assert arrived.is_set(), "no sample crossed the proxy"
    assert min(got) >= delay_s
    assert stats["connections"] >= 1 and stats["forward"]["bytes"] > 0


def test_a_target_that_is_not_there_closes_the_connection_and_is_counted():
    with socket.create_server(("127.0.0.1", 0)) as placeholder:
        port = placeholder.getsockname()[1]  # a port nothing listens on once closed
    with running_proxy(("127.0.0.1", port), LinkImpairment(delay_s=0.001)) as proxy:
        with socket.create_connection(("127.0.0.1", proxy.port), timeout=TIMEOUT_S) as conn:
            assert conn.recv(1) == b""  # closed by the proxy, nothing forwarded
        stats = proxy.stats()
    assert stats["refused"] == 1 and stats["connections"] == 0


def _echoes(port: int) -> bool:
    """Whether a new connection through the proxy on ``port`` echoes a few bytes."""
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT_S) as conn:
            conn.sendall(b"ping")
            return conn.recv(4) == b"ping"
    except OSError:  # reset by the proxy
        return False


def test_a_cut_resets_the_open_link_refuses_new_ones_and_ends():
    echo = EchoServer()
    cut = LinkCut(after_s=0.3, duration_s=1.0)
    try:
        with running_proxy(("127.0.0.1", echo.port), LinkImpairment(), cuts=(cut,)) as proxy:
            with socket.create_connection(("127.0.0.1", proxy.port), timeout=TIMEOUT_S) as conn:
                conn.sendall(b"ping")
                assert conn.recv(4) == b"ping"  # the first connection: the cut's clock starts
                with contextlib.suppress(ConnectionResetError):
                    assert conn.recv(4) == b""  # reset at the cut (or closed)
            cut_seen_ns = time.monotonic_ns()
            assert not _echoes(proxy.port)  # the cut lasts 1 s: a new link is refused
            deadline = time.monotonic() + TIMEOUT_S
            while not _echoes(proxy.port):
                assert time.monotonic() < deadline, "the link did not come back"
                time.sleep(0.05)
            stats = proxy.stats()
    finally:
        echo.close()
    [record] = stats["cuts"]
    assert record["start_ns"] <= cut_seen_ns < record["end_ns"]
    assert record["end_ns"] - record["start_ns"] >= 1e9
    assert record["reset"] == 1 and record["refused"] >= 1
