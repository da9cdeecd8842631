"""Zenoh session factory, typed publishers/subscribers and liveliness helpers.

Topology on one host: every service is a Zenoh *peer*. One service per run listens on
``BusConfig.endpoint``; the others connect to it and also listen on an ephemeral
loopback port, which gossip scouting advertises, so every pair of peers ends up with a
direct link (peers do not forward data for each other). Multicast scouting is off.

Everything on the wire is a :mod:`teleop.bus.messages` record; a subscriber decodes,
validates and counts bad records before the application sees anything.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
import zenoh.ext
from zenoh.shm import ShmProvider

from shm.provider import SHM_THRESHOLD_BYTES, configure_session, put_by_size, took_shm_path
from teleop.bus import graph
from teleop.bus.access import TLS_CONFIG, zenoh_entries
from teleop.bus.messages import (
    PROTOCOL_VERSION,
    DecodeError,
    DropCounter,
    Event,
    FrameSchema,
    Kind,
    Reason,
    Schema,
)
from teleop.bus.stamps import SeqGaps
from teleop.bus.topics import Topics
from teleop.core.config import BusConfig, ConfigError, SiteConfig

logger = logging.getLogger(__name__)

# A connecting peer also listens here (loopback, ephemeral port) so that peers which
# learn of it by gossip can open a direct link to it.
PEER_LISTEN_ENDPOINT = "tcp/127.0.0.1:0"
PEER_LISTEN_ENDPOINT_TLS = "tls/127.0.0.1:0"  # the same in a TLS run (bus.tls)

# connect/timeout_ms: -1 keeps retrying in the background; 0 gives up after one attempt.
CONNECT_RETRY_FOREVER = -1

RecordCallback = Callable[[np.ndarray, int], None]
# (record, pixels (H, W, C), rx_ns, arrived over shared memory)
FrameCallback = Callable[[np.ndarray, np.ndarray, int, bool], None]


def _json(value: Any) -> str:
    return json.dumps(value)


def open_session(
    bus: BusConfig, *, listen: bool, ingress_rate_hz: Mapping[str, float] | None = None
) -> zenoh.Session:
    """Open a peer session configured by :func:`session_config`."""
    return zenoh.open(session_config(bus, listen=listen, ingress_rate_hz=ingress_rate_hz))


def session_config(
    bus: BusConfig, *, listen: bool, ingress_rate_hz: Mapping[str, float] | None = None
) -> zenoh.Config:
    """The Zenoh config of a peer session: ``bus.zenoh_config_path`` plus the run's settings
    (also what a service outside the stack is given: teleop.run.outside).

    ``listen=True``: this process is the run's listener on ``bus.endpoint`` (fails if
    the port is taken). ``listen=False``: connect to ``bus.endpoint``; if nobody listens
    yet, ``open`` still returns and Zenoh keeps retrying in the background (config
    ``connect/retry``), so start order does not matter — wait on liveliness instead.
    Either way it also connects to ``bus.peer_connect_endpoints`` and, when not the
    listener, listens on ``bus.peer_listen_endpoint`` (a launcher's explicit mesh, with
    ``bus.gossip`` off: see BusConfig.gossip).

    ``ingress_rate_hz`` maps key expressions to the most puts per second this session
    takes in (Zenoh's ingress downsampling: the rest are dropped before any Python
    callback runs), for a consumer that needs a fast stream only now and then.

    A credentials file with certificates (a ``bus.tls`` run) makes every link mutual
    TLS: each endpoint must then be a ``tls/`` one (:class:`ConfigError` otherwise, as a
    ``tcp/`` link would bypass the certificates).
    """
    secured = zenoh_entries(Path(bus.credentials_file)) if bus.credentials_file else {}
    tls = any(path.startswith(TLS_CONFIG) for path in secured)
    conf = zenoh.Config.from_file(str(bus.zenoh_config_path))
    conf.insert_json5("mode", _json("peer"))
    conf.insert_json5("scouting/multicast/enabled", _json(False))
    conf.insert_json5("scouting/gossip/enabled", _json(bus.gossip))  # see BusConfig.gossip
    if listen:
        listen_on, connect_to = [bus.endpoint], list(bus.peer_connect_endpoints)
    else:
        default_listen = PEER_LISTEN_ENDPOINT_TLS if tls else PEER_LISTEN_ENDPOINT
        listen_on = [bus.peer_listen_endpoint or default_listen]
        connect_to = [bus.endpoint, *bus.peer_connect_endpoints]
    plain = [endpoint for endpoint in (*listen_on, *connect_to) if not endpoint.startswith("tls/")]
    if tls and plain:
        raise ConfigError(
            f"{bus.credentials_file} holds TLS certificates: bus endpoints must be "
            f"tls/HOST:PORT, not {', '.join(plain)}"
        )
    conf.insert_json5("listen/endpoints", _json(listen_on))
    conf.insert_json5("connect/endpoints", _json(connect_to))
    if connect_to:
        conf.insert_json5("connect/timeout_ms", _json(CONNECT_RETRY_FOREVER))
        conf.insert_json5("connect/exit_on_failure", _json(False))
    if ingress_rate_hz:
        rules = [{"key_expr": key, "freq": rate} for key, rate in ingress_rate_hz.items()]
        conf.insert_json5(
            "downsampling", _json([{"flows": ["ingress"], "messages": ["put"], "rules": rules}])
        )
    configure_session(conf, enabled=bus.shm, lowlatency=bus.lowlatency)  # BusConfig
    for path, value in secured.items():  # a launcher's run: authenticated, access-controlled
        conf.insert_json5(path, _json(value))
    for entry in bus.zenoh_overrides:
        path, _, value = entry.partition("=")
        conf.insert_json5(path.strip(), value.strip())
    return conf


def router_config(bus: BusConfig, site: SiteConfig, *, listen: bool) -> zenoh.Config:
    """The Zenoh config of ``site``'s router (services/router.py): a session in router
    mode with its place in the site's mesh (as :func:`session_config`'s peers), that
    also listens for the other site's router (``site.listen``) or connects to it
    (``site.connect``), mutual TLS either way.

    It takes no shared memory: what crosses between sites goes over the socket, so
    nothing is ever attempted through shared memory across hosts (its links within the
    site go without it too; only the records the other site consumes reach it, each
    under the shared-memory threshold). It keeps the site's transport (the low-latency
    one or not, ``bus.lowlatency``): both ends of a link must agree."""
    conf = session_config(bus, listen=listen)
    conf.insert_json5("mode", _json("router"))
    conf.insert_json5("transport/shared_memory/enabled", _json(False))
    conf.insert_json5("transport/shared_memory/mode", _json("lazy"))
    for key, extra in (("listen/endpoints", site.listen), ("connect/endpoints", site.connect)):
        if extra:
            conf.insert_json5(key, _json([*json.loads(conf.get_json(key)), extra]))
    if site.connect:
        conf.insert_json5("connect/timeout_ms", _json(CONNECT_RETRY_FOREVER))
        conf.insert_json5("connect/exit_on_failure", _json(False))
    return conf


# How long Publisher.undeclare waits for a put under way, s.
UNDECLARE_WAIT_S = 1.0

# Recovery (graph.Stream.recovered, in a lockstep run across sites): zenoh-ext's
# advanced publisher keeps its newest records and says every heartbeat how far it has
# sent; an advanced subscriber that sees a gap in the sequence (or a heartbeat beyond
# its newest record) asks the publisher's cache for what it missed, through whichever
# routers link them then. The cache holds more than a router's restart lets through
# (about 2 s at 100 Hz); the heartbeat finds a lost last record while the loop waits.
RECOVERY_CACHE_RECORDS = 512
RECOVERY_HEARTBEAT_S = 0.25


def _undeclare(entity: Any) -> None:
    try:
        entity.undeclare()
    except zenoh.ZError as exc:  # already undeclared, or its session is gone
        logger.debug("undeclare %r: %s", entity, exc)


def close_session(session: zenoh.Session | None, *entities: Any) -> None:
    """Undeclare ``entities`` (publishers, subscribers, tokens), then close the session.

    Safe to call twice and from a signal handler. Needed because a process with an
    open session (callback subscribers) does not exit on its own.
    """
    for entity in entities:
        if entity is not None:
            _undeclare(entity)
    if session is not None and not session.is_closed():
        session.close()


class Publisher:
    """A typed publisher: ``put(rec)`` encodes a record of one schema.

    QoS defaults are for state and commands: ``express`` (no batching delay),
    ``REAL_TIME`` priority, and ``BLOCK`` congestion control so nothing is lost on
    loopback — lockstep waits for every command, and a dropped one would stall the run.
    A 250-byte record at 1 kHz is far from filling a loopback link, so BLOCK only bites
    if a receiver stops reading; use ``DROP`` for bulky streams only a viewer needs.
    Priority and express apply where the transport has QoS: not on the low-latency
    transport (``BusConfig.lowlatency``, the default with SHM), which sends every put at
    once anyway.
    """

    def __init__(
        self,
        pub: zenoh.Publisher | zenoh.ext.AdvancedPublisher,
        schema: Schema,
        shm: ShmProvider | None,
        block: bool = True,
    ) -> None:
        self._pub = pub
        self.schema = schema
        self._shm = shm
        # A DROP stream never waits for room in the SHM pool: such a record is dropped.
        self._block = block
        self.dropped_pool_full = 0
        # A put and the undeclare never overlap: zenoh-python refuses to undeclare a
        # publisher another thread is putting on ("Already borrowed"), which a service's
        # callback may do while it closes. After undeclare a put sends nothing.
        self._lock = threading.Lock()
        self._undeclared = False

    @classmethod
    def declare(
        cls,
        session: zenoh.Session,
        key: str,
        schema: Schema,
        *,
        shm: ShmProvider | None = None,
        express: bool = True,
        priority: zenoh.Priority = zenoh.Priority.REAL_TIME,
        congestion_control: zenoh.CongestionControl = zenoh.CongestionControl.BLOCK,
        reliability: zenoh.Reliability = zenoh.Reliability.RELIABLE,
        recovery: bool = False,
    ) -> Publisher:
        """A publisher on ``key``; with ``recovery`` zenoh-ext's advanced one (a cache of
        its newest records and a heartbeat, :data:`RECOVERY_CACHE_RECORDS`)."""
        qos: dict[str, Any] = {
            "congestion_control": congestion_control,
            "priority": priority,
            "express": express,
            "reliability": reliability,
        }
        if recovery:
            pub = zenoh.ext.declare_advanced_publisher(
                session,
                key,
                cache=zenoh.ext.CacheConfig(RECOVERY_CACHE_RECORDS),
                sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=RECOVERY_HEARTBEAT_S),
                **qos,
            )
        else:
            pub = session.declare_publisher(key, **qos)
        return cls(pub, schema, shm, congestion_control == zenoh.CongestionControl.BLOCK)

    @classmethod
    def for_stream(
        cls,
        session: zenoh.Session,
        topics: Topics,
        name: str,
        *,
        shm: ShmProvider | None = None,
        recovery: bool = False,
    ) -> Publisher:
        """A publisher of the graph's stream ``name`` (teleop.bus.graph): its key, record
        kind and QoS as the graph describes them; with ``recovery`` (the run's choice:
        lockstep across sites) a stream the graph marks ``recovered`` keeps a cache."""
        stream = graph.stream(name)
        qos = stream.qos
        return cls.declare(
            session,
            getattr(topics, name),
            stream.schema,
            shm=shm,
            express=qos.express,
            priority=getattr(zenoh.Priority, qos.priority),
            congestion_control=getattr(zenoh.CongestionControl, qos.congestion_control),
            reliability=zenoh.Reliability.RELIABLE
            if qos.reliable
            else zenoh.Reliability.BEST_EFFORT,
            recovery=recovery and stream.recovered,
        )

    @property
    def key(self) -> str:
        return str(self._pub.key_expr)

    def put(self, rec: np.ndarray) -> bytes:
        """Encode and send one record (SHM path at or above the threshold); its bytes."""
        data = self.schema.encode(rec)
        self.put_bytes(data)
        return data

    def put_bytes(self, data: bytes) -> bool:
        """Send raw bytes (already encoded) on the path their size calls for; False when
        a DROP stream's record was dropped for a full SHM pool (``dropped_pool_full``)."""
        with self._lock:
            if self._undeclared:
                return False
            sent = put_by_size(self._pub, data, self._shm, block=self._block)
        self.dropped_pool_full += not sent
        return sent

    def wait_matched(self, timeout_s: float) -> bool:
        """Wait until at least one subscriber matches this publisher (event driven; not
        for a publisher with recovery, whose zenoh-ext type has no matching status)."""
        matched = threading.Event()

        def on_status(status: zenoh.MatchingStatus) -> None:
            if status.matching:
                matched.set()

        listener = self._pub.declare_matching_listener(on_status)
        try:
            if self._pub.matching_status.matching:
                return True
            return matched.wait(timeout_s)
        finally:
            _undeclare(listener)

    def undeclare(self) -> None:
        """Undeclare once no put is under way (a put blocked on a full link: after
        :data:`UNDECLARE_WAIT_S`, undeclared anyway)."""
        locked = self._lock.acquire(timeout=UNDECLARE_WAIT_S)
        try:
            self._undeclared = True
            _undeclare(self._pub)
        finally:
            if locked:
                self._lock.release()


def subscribe(
    session: zenoh.Session,
    key: str,
    schema: Schema,
    callback: RecordCallback,
    drops: DropCounter,
    *,
    batched: bool = False,
    recovery: bool = False,
) -> zenoh.Subscriber | zenoh.ext.AdvancedSubscriber:
    """Subscribe to records of ``schema``; ``callback(record, rx_ns)`` gets valid ones.

    ``rx_ns`` is ``time.monotonic_ns()`` on arrival, before decoding. Bad records are
    counted in ``drops`` and never reach the callback. Each record is the callback's
    own, writable, in a buffer nothing else holds: keep it or stamp it without a copy
    (a copy per record adds up at the loop's rate). The callback runs on a Zenoh thread:
    keep it short (store into a :class:`Latest`, or a queue).

    ``batched``: the key is a :class:`BatchPublisher`'s, whose messages hold several
    records back to back: the callback runs once per valid record, in order. A message
    that is not a whole number of records is dropped (counted once).

    ``recovery``: zenoh-ext's advanced subscriber, which asks an advanced publisher's
    cache for the records a gap in its sequence says were lost (:data:`RECOVERY_CACHE_RECORDS`).
    """

    def on_sample(sample: zenoh.Sample) -> None:
        rx_ns = time.monotonic_ns()
        deliver(sample.payload.to_bytes(), rx_ns, schema, callback, drops, batched=batched)

    if recovery:
        return zenoh.ext.declare_advanced_subscriber(
            session, key, on_sample, recovery=zenoh.ext.RecoveryConfig(heartbeat=True)
        )
    return session.declare_subscriber(key, on_sample)


class NewestSubscriber:
    """A subscription whose callback sees only the newest record: what a realtime consumer
    takes (``Stream.newest_for`` in :mod:`teleop.bus.graph`).

    Zenoh keeps one sample in a ring (``RingChannel(1)``: a newer sample overwrites one
    not yet taken) and a thread of this object takes it, decodes it like :func:`subscribe`
    and calls back. A callback that takes longer than the stream's period, or a thread
    that is not scheduled for a while, therefore never leaves a backlog: the next record
    it gets is the newest. The records it never saw show as gaps in their ``seq``:
    ``skipped`` counts them by the bus layer's one rule (:class:`teleop.bus.stamps.SeqGaps`;
    with any the bus lost: on loopback it loses none).

    The hand-off is the one Zenoh's own Python callbacks make (a Rust thread queues the
    sample, a Python thread runs the callback), with a ring of one instead of an unbounded
    queue. :meth:`undeclare` closes the ring, which ends the thread, and joins it.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        schema: Schema,
        callback: RecordCallback,
        drops: DropCounter,
    ) -> None:
        self.key = key
        self.taken = 0  # records handed to the callback
        self._gaps = SeqGaps()
        self._schema, self._callback, self._drops = schema, callback, drops
        self._sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(1))
        # recv() on the handler, not the subscriber: undeclare() must not wait for it
        self._ring = self._sub.handler
        self._failed_once = False
        self._thread = threading.Thread(target=self._take, name=f"newest {key}", daemon=True)
        self._thread.start()

    @property
    def skipped(self) -> int:
        """Records overwritten before this subscriber took them (gaps in their seq)."""
        return self._gaps.missing

    def _count(self, rec: np.ndarray, rx_ns: int) -> None:
        self._gaps.add(int(rec["seq"]))
        self.taken += 1
        self._callback(rec, rx_ns)

    def _take(self) -> None:
        while True:
            try:
                sample = self._ring.recv()
            except zenoh.ZError:
                return  # undeclared: the ring is closed and empty
            rx_ns = time.monotonic_ns()
            try:
                deliver(sample.payload.to_bytes(), rx_ns, self._schema, self._count, self._drops)
            except Exception:
                if not self._failed_once:  # a bug in the callback: say it, keep taking
                    self._failed_once = True
                    logger.exception("callback of %s failed (further failures not logged)",
                                     self.key)  # fmt: skip

    def undeclare(self) -> None:
        _undeclare(self._sub)
        if threading.current_thread() is not self._thread:
            self._thread.join()


def subscribe_stream(
    session: zenoh.Session,
    topics: Topics,
    stream_name: str,
    callback: RecordCallback,
    drops: DropCounter,
    *,
    consumer: str,
    mode: str,
    scenario: str,
    recovery: bool = False,
) -> zenoh.Subscriber | zenoh.ext.AdvancedSubscriber | NewestSubscriber:
    """Subscribe ``consumer`` to the graph's stream ``stream_name`` (its key and record
    kind) as the graph says it takes it in a run of ``mode`` and ``scenario``
    (``Stream.takes_newest``): a :class:`NewestSubscriber`, or :func:`subscribe` (every
    record, in order; with ``recovery``, the run's choice, a stream the graph marks
    ``recovered`` with recovery). The choice is made here, once per subscription."""
    stream = graph.stream(stream_name)
    key = getattr(topics, stream_name)
    if stream.takes_newest(consumer, mode, scenario):
        return NewestSubscriber(session, key, stream.schema, callback, drops)
    recovered = recovery and stream.recovered
    return subscribe(session, key, stream.schema, callback, drops, recovery=recovered)


def owned_events(stream_name: str, callback: RecordCallback, drops: DropCounter) -> RecordCallback:
    """``callback`` behind a check that each RUN_EVENT is one the service of
    ``stream_name`` owns (:data:`graph.EVENT_STREAM`); any other is counted in ``drops``
    (reason ``source``) and dropped."""

    def owned(rec: np.ndarray, rx_ns: int) -> None:
        event = int(rec["event"])
        if graph.event_on_own_stream(stream_name, event):
            callback(rec, rx_ns)
        else:
            detail = f"{Event(event).name} on {stream_name}"
            drops.record(DecodeError(Kind.RUN_EVENT, Reason.SOURCE, detail))

    return owned


def subscribe_events(
    session: zenoh.Session,
    topics: Topics,
    stream_name: str,
    callback: RecordCallback,
    drops: DropCounter,
    *,
    recovery: bool = False,
) -> zenoh.Subscriber | zenoh.ext.AdvancedSubscriber:
    """Subscribe to one service's RUN_EVENT stream (``plant_events``, ``operator_events``):
    ``callback`` gets only the events that service owns (:func:`owned_events`); with
    ``recovery`` (the run's choice) as :func:`subscribe_stream` says."""
    key = getattr(topics, stream_name)
    stream = graph.stream(stream_name)
    owned = owned_events(stream_name, callback, drops)
    return subscribe(
        session, key, stream.schema, owned, drops, recovery=recovery and stream.recovered
    )


def deliver(
    payload: bytes,
    rx_ns: int,
    schema: Schema,
    callback: RecordCallback,
    drops: DropCounter,
    *,
    batched: bool = False,
) -> None:
    """What :func:`subscribe` does with a payload received at ``rx_ns``: decode it into
    records the callback owns (writable), count bad ones in ``drops``, call back."""
    data = bytearray(payload)
    size = schema.size
    count = len(data) // size if batched and data and len(data) % size == 0 else 1
    for offset in range(0, count * size, size):
        try:
            rec = schema.decode(data if count == 1 else data[offset : offset + size])
        except DecodeError as err:
            drops.record(err)
            continue
        callback(rec, rx_ns)


def batch_records(record_bytes: int, requested: int) -> int:
    """Records per observer message: ``requested``, fewer if needed to keep a message
    below :data:`SHM_THRESHOLD_BYTES` (never fewer than one).

    Observer batches go over the socket: through Zenoh's implicit shared-memory transport
    pool (what a put above the threshold takes without a provider of ours), a recorder
    starved on a busy machine received some records of 4830 B plant-state batches zeroed
    (version 0: 49 and 228 of about 2000 messages in two realtime grasps under a full
    test suite's load), while the 2010 B and 2880 B batches of the same run arrived whole.
    """
    if record_bytes < 1 or requested < 1:
        raise ValueError(
            f"record_bytes and requested must be >= 1, got {record_bytes}, {requested}"
        )
    return max(1, min(requested, (SHM_THRESHOLD_BYTES - 1) // record_bytes))


class BatchPublisher:
    """Observers' copy of a fast stream: records sent ``records_per_message`` at a time.

    Every Zenoh message costs the receiving process a wake-up (tens of microseconds of
    CPU, whatever the payload: docs/realtime.md), so an observer that needs every record
    but none of them at once (the recorder, the eye view) listens here instead of to the
    1 kHz stream. ``add`` keeps an encoded record; the message goes out when it holds
    ``records_per_message`` records, or at :meth:`flush` (the producer calls it when its
    run ends, and :meth:`undeclare` does, so a producer stopped before its observer
    loses nothing: supervisord stops the recorder last).
    """

    def __init__(self, publisher: Publisher, records_per_message: int) -> None:
        if records_per_message < 1:
            raise ValueError(f"records_per_message must be >= 1, got {records_per_message}")
        self._publisher = publisher
        self.records_per_message = records_per_message
        self._pending: list[bytes] = []

    @classmethod
    def for_stream(
        cls, session: zenoh.Session, topics: Topics, name: str, records_per_message: int
    ) -> BatchPublisher:
        """The batched copy ``name`` of a stream (its ``batch_of`` in teleop.bus.graph)."""
        stream = graph.stream(name)
        if not stream.batch_of:
            raise ValueError(f"{name} is not a batched stream of the graph")
        records = batch_records(stream.schema.size, records_per_message)
        return cls(Publisher.for_stream(session, topics, name), records)

    def add(self, data: bytes) -> None:
        """Keep one encoded record; send the message once it is full."""
        self._pending.append(data)
        if len(self._pending) >= self.records_per_message:
            self.flush()

    def flush(self) -> None:
        """Send the records kept so far (nothing if none)."""
        if self._pending:
            data = b"".join(self._pending)
            self._pending = []
            self._publisher.put_bytes(data)

    def undeclare(self) -> None:
        self.flush()
        self._publisher.undeclare()


def subscribe_frames(
    session: zenoh.Session,
    key: str,
    schema: FrameSchema,
    callback: FrameCallback,
    drops: DropCounter,
) -> zenoh.Subscriber:
    """Subscribe to image frames; ``callback(record, pixels, rx_ns, via_shm)``.

    Like :func:`subscribe`, for a :class:`FrameSchema`: the pixels are a read-only
    (H, W, C) view of the received bytes, and ``via_shm`` tells whether the sample
    came through shared memory (:func:`shm.took_shm_path`).
    """

    def on_sample(sample: zenoh.Sample) -> None:
        rx_ns = time.monotonic_ns()
        via_shm = took_shm_path(sample)
        try:
            rec, pixels = schema.decode_frame(sample.payload.to_bytes())
        except DecodeError as err:
            drops.record(err)
            return
        callback(rec, pixels, rx_ns, via_shm)

    return session.declare_subscriber(key, on_sample)


class Latest:
    """Thread-safe holder of the newest record of a stream, with event-driven waits.

    Use an instance as the ``callback`` of :func:`subscribe`; a control loop then calls
    :meth:`wait_newer` with the last ``seq`` it handled and sleeps on a condition
    variable until a newer record arrives (no polling).
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._rec: np.ndarray | None = None
        self._rx_ns = 0
        self._seq = -1  # header seq of the stored record; -1 = nothing yet
        self._count = 0

    def __call__(self, rec: np.ndarray, rx_ns: int) -> None:
        with self._cond:
            self._rec = rec
            self._rx_ns = rx_ns
            self._seq = int(rec["seq"])
            self._count += 1
            self._cond.notify_all()

    @property
    def count(self) -> int:
        """Records stored since creation."""
        with self._cond:
            return self._count

    def get(self) -> tuple[np.ndarray, int] | None:
        """(record, rx_ns) of the newest record, or None before the first one."""
        with self._cond:
            return None if self._rec is None else (self._rec, self._rx_ns)

    def wait_newer(self, seq: int, timeout_s: float) -> tuple[np.ndarray, int] | None:
        """Wait until the stored record's ``seq`` exceeds ``seq``; None on timeout.

        Pass -1 to wait for the first record. A producer that restarts from seq 0 is
        not "newer": the caller sees a timeout and decides (e.g. resets its ``seq``).
        """
        with self._cond:
            if not self._cond.wait_for(lambda: self._seq > seq, timeout_s):
                return None
            assert self._rec is not None
            return self._rec, self._rx_ns


def declare_alive(
    session: zenoh.Session, topics: Topics, service: str, *, ready: bool = False
) -> zenoh.LivelinessToken:
    """Announce ``service`` as up (``ready``: as ready, see :meth:`Topics.alive`); the
    token disappears when undeclared or the session dies."""
    return session.liveliness().declare_token(topics.alive(service, ready=ready))


def declare_protocol(session: zenoh.Session, topics: Topics) -> zenoh.LivelinessToken:
    """Announce the protocol version this process speaks (``PROTOCOL_VERSION``) under
    ``topics``' robot: what a client reads before its first record."""
    return session.liveliness().declare_token(topics.protocol(PROTOCOL_VERSION))


class ServicesMissing(TimeoutError):
    """:func:`wait_alive` timed out; ``missing``: the services whose tokens were not seen."""

    def __init__(self, message: str, missing: tuple[str, ...]) -> None:
        super().__init__(message)
        self.missing = missing


def wait_alive(
    session: zenoh.Session,
    topics: Topics,
    services: Iterable[str],
    timeout_s: float,
    *,
    ready: bool = False,
) -> None:
    """Block until every named service's liveliness token (``ready``: its ready token)
    is present.

    Event driven: a liveliness subscriber with history reports the tokens already
    present and every later change. Raises :class:`ServicesMissing` (a TimeoutError)
    naming the missing services.

    Peers do not forward for each other, so a token seen here came over this session's
    own link to that service, after the declarations made before it (its subscribers):
    from then on what this session publishes reaches that service.
    """
    wanted = set(services)
    present: set[str] = set()
    cond = threading.Condition()

    def on_token(sample: zenoh.Sample) -> None:
        name = topics.service_of(str(sample.key_expr))
        with cond:
            if sample.kind == zenoh.SampleKind.PUT:
                present.add(name)
            else:
                present.discard(name)
            cond.notify_all()

    key = topics.ready_all if ready else topics.alive_all
    sub = session.liveliness().declare_subscriber(key, on_token, history=True)
    try:
        with cond:
            if not cond.wait_for(lambda: wanted <= present, timeout_s):
                missing = tuple(sorted(wanted - present))
                state = "ready" if ready else "alive"
                raise ServicesMissing(
                    f"services not {state} after {timeout_s:g} s: {', '.join(missing)}", missing
                )
    finally:
        _undeclare(sub)
