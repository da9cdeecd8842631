"""Bus layer over real Zenoh sessions in real processes (no mocks).

Each test gets its own free loopback port (multicast scouting is off in every session),
so concurrent runs cannot see each other. Child processes are spawned (not forked: the
parent may already run Zenoh threads) and report through a multiprocessing queue.
Nothing waits on a fixed sleep: liveliness tokens, matching status and first samples.
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import queue
import socket
import threading
import time
from collections.abc import Callable

import numpy as np
import pytest
import zenoh

from shm.provider import SHM_THRESHOLD_BYTES, get_provider, memlock_budget_bytes, took_shm_path
from teleop.bus import messages as m
from teleop.bus import session as bus
from teleop.bus.topics import Topics
from teleop.core.config import BusConfig, load_config
from teleop.core.net import LoopbackPorts
from teleop.run.stack import peer_mesh
from tests.integration.receiving import free_endpoint

TIMEOUT_S = 10.0  # generous bound on any single wait; passing runs take well under 1 s
ROBOT = "testarm"
BIG_BYTES = 64 * 1024
SMALL_BYTES = 64
RAW_KEY = f"teleop/{ROBOT}/test/raw"  # a test-only stream, not part of the registry

SPAWN = mp.get_context("spawn")


def _bus(endpoint: str, shm: bool = True) -> BusConfig:
    return BusConfig(endpoint=endpoint, shm=shm, zenoh_config="local.json5")


def _child(fn: Callable[..., None], *args: object) -> None:
    """Run ``fn(*args)`` in a child, forwarding any exception to the report queue."""
    report = args[-1]
    try:
        fn(*args)
    except BaseException as exc:  # the parent must see child failures
        report.put(("error", repr(exc)))
        raise


def _start(fn: Callable[..., None], *args: object) -> mp.process.BaseProcess:
    proc = SPAWN.Process(target=_child, args=(fn, *args), daemon=True)
    proc.start()
    return proc


def _get(report: mp.Queue, tag: str) -> tuple:
    """The next report with ``tag``; fails on a child error or after TIMEOUT_S."""
    item = report.get(timeout=TIMEOUT_S)
    assert item[0] != "error", f"child failed: {item[1]}"
    assert item[0] == tag, item
    return item


def _join(*procs: mp.process.BaseProcess) -> None:
    for proc in procs:
        proc.join(TIMEOUT_S)
        assert proc.exitcode == 0, f"{proc.name} exit code {proc.exitcode}"


# --- child process bodies ------------------------------------------------------------------


def state_producer(endpoint: str, stop: mp.Event, report: mp.Queue) -> None:
    """Connect, wait for the consumer, send one bad record and one good PLANT_STATE."""
    topics = Topics(ROBOT)
    session = bus.open_session(_bus(endpoint), listen=False)
    pub = bus.Publisher.declare(session, topics.plant_state, m.PLANT_STATE)
    token = bus.declare_alive(session, topics, "producer")
    try:
        bus.wait_alive(session, topics, ["consumer"], TIMEOUT_S)
        assert pub.wait_matched(TIMEOUT_S)
        bad = m.PLANT_STATE.new()
        bad["q_rad"][0] = np.nan
        pub.put_bytes(bad.tobytes())
        rec = m.PLANT_STATE.new()
        rec["seq"] = 42
        rec["n_joints"] = 6
        rec["q_rad"][:6] = np.arange(6) * 0.1
        rec["t_source_ns"] = time.monotonic_ns()
        pub.put(rec)
        report.put(("sent", int(rec["t_source_ns"])))
        stop.wait(TIMEOUT_S)
    finally:
        bus.close_session(session, pub, token)


def peer_b_or_c(config: BusConfig, role: str, stop: mp.Event, report: mp.Queue) -> None:
    """Peer B publishes to peer C (each connects to the listener A, and to whatever
    else ``config`` says)."""
    topics = Topics(ROBOT)
    session = bus.open_session(config, listen=False)
    entities: list = []
    try:
        if role == "C":
            got = threading.Event()
            received: list[int] = []

            def on_cmd(rec: np.ndarray, rx_ns: int) -> None:
                received.append(int(rec["seq"]))
                got.set()

            drops = m.DropCounter()
            entities.append(
                bus.subscribe(session, topics.joint_command, m.JOINT_COMMAND, on_cmd, drops)
            )
            entities.append(bus.declare_alive(session, topics, "C"))
            assert got.wait(TIMEOUT_S), "C got nothing from B"
            peers = sorted(str(z) for z in session.info.peers_zid())
            report.put(("C", received[0], str(session.info.zid()), peers))
        else:
            pub = bus.Publisher.declare(session, topics.joint_command, m.JOINT_COMMAND)
            entities.append(pub)
            entities.append(bus.declare_alive(session, topics, "B"))
            bus.wait_alive(session, topics, ["C"], TIMEOUT_S)
            assert pub.wait_matched(TIMEOUT_S)
            rec = m.JOINT_COMMAND.new()
            rec["seq"] = 7
            pub.put(rec)
            report.put(("B", str(session.info.zid())))
        stop.wait(TIMEOUT_S)
    finally:
        bus.close_session(session, *entities)


def early_connector(endpoint: str, stop: mp.Event, report: mp.Queue) -> None:
    """Start before any listener exists; must keep retrying, then announce itself."""
    topics = Topics(ROBOT)
    t0 = time.monotonic()
    session = bus.open_session(_bus(endpoint), listen=False)
    token = bus.declare_alive(session, topics, "early")
    report.put(("opened", time.monotonic() - t0))
    try:
        stop.wait(TIMEOUT_S)
    finally:
        bus.close_session(session, token)


def raw_sink(endpoint: str, shm: bool, n_expected: int, report: mp.Queue) -> None:
    """Report (size, took_shm_path) of each raw sample on the test key."""
    topics = Topics(ROBOT)
    session = bus.open_session(_bus(endpoint, shm=shm), listen=False)
    samples: queue.Queue = queue.Queue()
    sub = session.declare_subscriber(RAW_KEY, samples.put)
    token = bus.declare_alive(session, topics, "sink")
    try:
        for _ in range(n_expected):
            sample = samples.get(timeout=TIMEOUT_S)
            report.put(("sample", len(sample.payload), took_shm_path(sample)))
    finally:
        bus.close_session(session, sub, token)


# --- tests ---------------------------------------------------------------------------------


def test_record_crosses_processes_and_bad_record_is_dropped():
    endpoint = free_endpoint()
    topics = Topics(ROBOT)
    session = bus.open_session(_bus(endpoint), listen=True)
    latest = bus.Latest()
    drops = m.DropCounter()
    sub = bus.subscribe(session, topics.plant_state, m.PLANT_STATE, latest, drops)
    token = bus.declare_alive(session, topics, "consumer")
    stop, report = SPAWN.Event(), SPAWN.Queue()
    proc = _start(state_producer, endpoint, stop, report)
    try:
        got = latest.wait_newer(-1, TIMEOUT_S)
        assert got is not None
        rec, rx_ns = got
        assert int(rec["seq"]) == 42 and int(rec["n_joints"]) == 6
        np.testing.assert_allclose(rec["q_rad"][:6], np.arange(6) * 0.1)
        _, t_source_ns = _get(report, "sent")
        assert rx_ns >= t_source_ns  # one host, one monotonic clock
        assert drops.counts() == {(int(m.Kind.PLANT_STATE), m.Reason.NON_FINITE.value): 1}
        assert latest.wait_newer(42, 0.0) is None
    finally:
        stop.set()
        _join(proc)
        bus.close_session(session, sub, token)
        bus.close_session(session, sub, token)  # twice is fine
    assert session.is_closed()


def _b_reaches_c_directly(a: zenoh.Session, config_b: BusConfig, config_c: BusConfig) -> None:
    """B (a child process) sends C (another) a command: C must get it over a B-C link."""
    stop, report = SPAWN.Event(), SPAWN.Queue()
    c = _start(peer_b_or_c, config_c, "C", stop, report)
    b = _start(peer_b_or_c, config_b, "B", stop, report)
    try:
        results = {}
        for _ in range(2):
            item = report.get(timeout=TIMEOUT_S)
            assert item[0] != "error", item
            results[item[0]] = item
        _, seq, c_zid, c_peers = results["C"]
        _, b_zid = results["B"]
        assert seq == 7
        assert b_zid in c_peers, "C has no direct link to B"
        assert str(a.info.zid()) in c_peers
    finally:
        stop.set()
        _join(b, c)


def test_peers_connecting_to_one_listener_reach_each_other_directly():
    """Gossip: A listens; B and C only connect to A, and link to each other."""
    endpoint = free_endpoint()
    a = bus.open_session(_bus(endpoint), listen=True)
    try:
        _b_reaches_c_directly(a, _bus(endpoint), _bus(endpoint))
    finally:
        bus.close_session(a)


def test_the_launchers_mesh_links_peers_with_gossip_off():
    """The launcher's explicit mesh (stack.peer_mesh, through the same --set overrides the
    services get): gossip off, B listens on a port of its own and C connects to it. With
    gossip off and peers not routing for each other, only the mesh can link B and C."""
    endpoint = free_endpoint()
    with LoopbackPorts() as ports:
        mesh = peer_mesh(["B", "C"], None, ports)
    configs = {
        name: load_config(None, [f'bus.endpoint="{endpoint}"', *overrides]).bus
        for name, overrides in mesh.items()
    }
    assert not configs["B"].gossip and not configs["C"].gossip
    assert configs["B"].peer_connect_endpoints == ()
    assert configs["C"].peer_connect_endpoints == (configs["B"].peer_listen_endpoint,)
    a = bus.open_session(dataclasses.replace(configs["B"], peer_connect_endpoints=()), listen=True)
    try:
        _b_reaches_c_directly(a, configs["B"], configs["C"])
    finally:
        bus.close_session(a)


def test_peer_mesh_links_every_pair_once_and_the_listener_by_its_endpoint():
    with LoopbackPorts() as ports:
        mesh = peer_mesh(["plant", "controller", "haptic", "recorder"], "plant", ports)
    configs = {name: load_config(None, overrides).bus for name, overrides in mesh.items()}
    assert configs["plant"].peer_listen_endpoint == ""  # it listens on bus.endpoint
    own = {name: c.peer_listen_endpoint for name, c in configs.items() if name != "plant"}
    assert len(set(own.values())) == 3
    links = [
        frozenset((name, peer))
        for name, c in configs.items()
        for peer, endpoint in own.items()
        if endpoint in c.peer_connect_endpoints
    ]
    assert len(links) == len(set(links)) == 3  # the non-listeners' pairs, once each


def test_connecting_peer_started_before_listener_keeps_retrying():
    endpoint = free_endpoint()
    topics = Topics(ROBOT)
    stop, report = SPAWN.Event(), SPAWN.Queue()
    proc = _start(early_connector, endpoint, stop, report)
    _get(report, "opened")  # its session is open and nobody listens yet
    session = bus.open_session(_bus(endpoint), listen=True)
    try:
        bus.wait_alive(session, topics, ["early"], TIMEOUT_S)
    finally:
        stop.set()
        _join(proc)
        bus.close_session(session)


def test_wait_alive_names_missing_services():
    endpoint = free_endpoint()
    topics = Topics(ROBOT)
    session = bus.open_session(_bus(endpoint), listen=True)
    token = bus.declare_alive(session, topics, "plant")
    try:
        bus.wait_alive(session, topics, ["plant"], TIMEOUT_S)
        with pytest.raises(TimeoutError, match="controller, haptic"):
            bus.wait_alive(session, topics, ["plant", "haptic", "controller"], 0.05)
    finally:
        bus.close_session(session, token)


@pytest.mark.parametrize("shm", [True, False], ids=["shm", "noshm"])
def test_payload_path_shm_above_threshold_inline_below(shm: bool):
    assert SMALL_BYTES < SHM_THRESHOLD_BYTES <= BIG_BYTES
    if memlock_budget_bytes() is not None:
        # An ordinary user: this process's sessions have used up its locked memory, so its
        # sessions go over the socket (the eye view's e2e run covers SHM within the limit).
        pytest.skip("needs an unbounded locked-memory limit (root or CAP_IPC_LOCK)")
    endpoint = free_endpoint()
    topics = Topics(ROBOT)
    config = _bus(endpoint, shm=shm)
    session = bus.open_session(config, listen=True)
    report = SPAWN.Queue()
    proc = _start(raw_sink, endpoint, shm, 2, report)
    # The publisher always offers SHM buffers for big payloads; the session config decides.
    provider = get_provider(config.shm_pool_bytes)
    pub = bus.Publisher.declare(session, RAW_KEY, m.PLANT_STATE, shm=provider)
    try:
        bus.wait_alive(session, topics, ["sink"], TIMEOUT_S)
        assert pub.wait_matched(TIMEOUT_S)
        pub.put_bytes(bytes(range(256)) * (BIG_BYTES // 256))
        pub.put_bytes(b"\x01" * SMALL_BYTES)
        got = [_get(report, "sample")[1:] for _ in range(2)]
        assert got == [(BIG_BYTES, shm), (SMALL_BYTES, False)]
    finally:
        _join(proc)
        bus.close_session(session, pub)


def test_close_session_is_idempotent_and_tolerates_none():
    session = bus.open_session(_bus(free_endpoint()), listen=True)
    pub = session.declare_publisher("teleop/testarm/x")
    bus.close_session(session, pub, None)
    bus.close_session(session, pub, None)
    bus.close_session(None)
    assert session.is_closed()
    assert isinstance(session, zenoh.Session)


def test_batch_publisher_delivers_every_record_in_order_and_drops_bad_batches():
    """Observers' copy: records go out N per message (and the rest at flush), arrive one
    callback per record, in order; a message that is not whole records is dropped."""
    endpoint = free_endpoint()
    topics = Topics(ROBOT)
    listener = bus.open_session(_bus(endpoint), listen=True)
    session = bus.open_session(_bus(endpoint), listen=False)
    got: list[int] = []
    done = threading.Event()
    drops = m.DropCounter()

    def on_record(rec: np.ndarray, rx_ns: int) -> None:
        got.append(int(rec["seq"]))
        if len(got) == 7:
            done.set()

    sub = bus.subscribe(
        listener, topics.plant_state_batch, m.PLANT_STATE, on_record, drops, batched=True
    )
    batch = bus.BatchPublisher.for_stream(session, topics, "plant_state_batch", 3)
    raw = bus.Publisher.declare(session, topics.plant_state_batch, m.PLANT_STATE)
    try:
        assert raw.wait_matched(TIMEOUT_S)
        raw.put_bytes(b"\x00" * (m.PLANT_STATE.size + 5))  # not whole records: dropped
        for seq in range(7):
            rec = m.PLANT_STATE.new()
            rec["seq"] = seq
            batch.add(m.PLANT_STATE.encode(rec))
        assert batch.records_per_message == 3
        # The configured 10 would make 4830 B messages: cut to stay off the implicit SHM
        # path (teleop.bus.session.batch_records).
        assert bus.batch_records(m.PLANT_STATE.size, 10) == 6
        assert bus.batch_records(m.PLANT_STATE.size, 2) == 2
        assert bus.batch_records(10_000, 10) == 1
        assert 6 * m.PLANT_STATE.size < SHM_THRESHOLD_BYTES <= 7 * m.PLANT_STATE.size
        batch.flush()  # the seventh record goes out alone
        assert done.wait(TIMEOUT_S)
        assert got == list(range(7))
        assert drops.total == 1
    finally:
        batch.undeclare()
        bus.close_session(session, raw)
        bus.close_session(listener, sub)


def test_a_zenoh_listener_opens_on_a_port_the_launcher_holds():
    """The stack hands each service a port it keeps bound until the service listens
    (teleop.core.net.LoopbackPorts): Zenoh's listener must bind beside that hold."""
    with LoopbackPorts() as ports:
        port = ports.take()
        endpoint = f"tcp/127.0.0.1:{port}"
        session = bus.open_session(BusConfig(endpoint=endpoint, gossip=False), listen=True)
        try:
            # Zenoh accepts on it (the hold itself never listens).
            with socket.create_connection(("127.0.0.1", port), timeout=2.0):
                pass
        finally:
            bus.close_session(session)


def test_a_newest_only_subscriber_that_falls_behind_takes_the_newest_and_counts_the_rest():
    """A realtime consumer slower than its stream (here: 20 ms per record, records every
    millisecond) never works through a backlog: each record it takes is the newest sent
    by then, the last one it takes is the last one sent, and what it never saw is counted
    as skipped. A FIFO subscriber beside it takes every record, late."""
    endpoint = free_endpoint()
    topics = Topics(ROBOT)
    listener = bus.open_session(_bus(endpoint), listen=True)
    session = bus.open_session(_bus(endpoint), listen=False)
    drops = m.DropCounter()
    newest_got: list[tuple[int, int]] = []  # (seq taken, newest seq sent by then)
    every_got: list[int] = []
    sent = [-1]
    last = 199
    newest_done, every_done = threading.Event(), threading.Event()

    def slow(rec: np.ndarray, rx_ns: int) -> None:
        newest_got.append((int(rec["seq"]), sent[0]))
        time.sleep(0.02)
        if int(rec["seq"]) == last:
            newest_done.set()

    def every(rec: np.ndarray, rx_ns: int) -> None:
        every_got.append(int(rec["seq"]))
        if int(rec["seq"]) == last:
            every_done.set()

    newest = bus.NewestSubscriber(listener, topics.plant_state, m.PLANT_STATE, slow, drops)
    fifo = bus.subscribe(listener, topics.plant_state, m.PLANT_STATE, every, drops)
    pub = bus.Publisher.declare(session, topics.plant_state, m.PLANT_STATE)
    try:
        assert pub.wait_matched(TIMEOUT_S)
        rec = m.PLANT_STATE.new()
        start_s = time.monotonic()
        for seq in range(last + 1):
            rec["seq"] = seq
            sent[0] = seq
            pub.put(rec)
            time.sleep(0.001)
        sending_s = time.monotonic() - start_s
        assert newest_done.wait(TIMEOUT_S) and every_done.wait(TIMEOUT_S)
        assert every_got == list(range(last + 1))
        taken = [seq for seq, _ in newest_got]
        assert taken == sorted(taken) and taken[-1] == last
        # One record per 20 ms callback while they came, and the last: no backlog.
        assert len(taken) <= sending_s / 0.02 + 2, (len(taken), sending_s)
        # Each record taken after the first was fresh when taken (a FIFO's lag would grow
        # to the whole backlog: about 190 records here).
        assert all(sent_then - seq <= 25 for seq, sent_then in newest_got[1:]), newest_got
        assert newest.taken == len(taken)
        assert newest.skipped == taken[-1] - taken[0] - (len(taken) - 1)
    finally:
        bus.close_session(session, pub)
        bus.close_session(listener, fifo, newest)
    assert not newest._thread.is_alive()  # undeclare ended and joined its thread


def test_a_publisher_undeclared_while_another_thread_puts_closes_cleanly():
    """A service closes while a callback still publishes (the HMD did at shutdown): the
    undeclare waits for the put under way instead of failing ("Already borrowed"), and a
    put after it sends nothing."""
    session = bus.open_session(_bus(free_endpoint()), listen=False)
    errors: list[str] = []
    data = m.TOOL_POSE.encode(m.TOOL_POSE.new())
    try:
        for _ in range(50):
            pub = bus.Publisher.declare(session, "teleop/test/undeclare", m.TOOL_POSE)
            done = threading.Event()

            def spam(pub: bus.Publisher = pub, done: threading.Event = done) -> None:
                try:
                    while not done.is_set():
                        pub.put_bytes(data)
                except Exception as exc:  # what the close must never cause
                    errors.append(repr(exc))

            thread = threading.Thread(target=spam)
            thread.start()
            time.sleep(0.001)
            try:
                pub.undeclare()
            except Exception as exc:
                errors.append(f"undeclare: {exc!r}")
            assert pub.put_bytes(data) is False
            done.set()
            thread.join()
    finally:
        bus.close_session(session)
    assert errors == []
