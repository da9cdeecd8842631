"""The transport floor: a bare Zenoh relay chain with the bilateral loop's shape.

The teleoperation round trip crosses four legs between three processes:
haptic -> controller -> plant -> controller -> haptic. The floor chain has the same legs
between the same number of Python processes, with the same Zenoh config, QoS and
payload size, and does no work: each relay stamps the time a payload arrives and the
time it forwards it, into the slots of :class:`teleop.bus.messages.Stage` the real service
would stamp, so the floor and the stack are split into the same hops
(:data:`teleop.bench.loop_stats.HOPS`) and compared hop by hop.

Payload layout (little-endian): ``seq`` u8, then ``trace_ns`` i8[N_STAGES] (the header's
stamps, same indices), then zero padding up to the payload size. A relay forwards the
payload at the size it came with (a copy in, stamps, a copy out: what a Python service
costs at the least).

``origin`` (the haptic's place) runs in the ``teleop latency`` process itself:
:class:`FloorOrigin` sends paced at the device rate, or back to back, and keeps the
completed traces.
"""

from __future__ import annotations

import logging
import struct
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import zenoh

import shm
from teleop.bus.messages import N_STAGES, Stage
from teleop.bus.service import Service, service_main
from teleop.bus.stamps import StampLog
from teleop.bus.topics import ROOT, Topics
from teleop.core.clock import LoopTimer, MonotonicClock
from teleop.core.config import BusConfig

# Payload prefix: seq (u8) and the trace stamps (i8 each), same indices as the header's.
SEQ_FORMAT = struct.Struct("<Q")
STAMP_FORMAT = struct.Struct("<q")
TRACE_OFFSET = SEQ_FORMAT.size
FLOOR_PREFIX_BYTES = TRACE_OFFSET + N_STAGES * STAMP_FORMAT.size
# SHM pools one process of the chain holds or maps at once: relay_controller has its
# own and maps the origin's (haptic leg) and relay_plant's (state leg). Every pool of the
# chain is sized for that, within the locked-memory limit (shm.open_provider).
FLOOR_POOLS_PER_PROCESS = 3
# Payloads one pool must hold at once for a size to be measured: relay_controller's pool
# carries a command and a feedback payload, and a buffer is free again only once its
# receiver has copied it out.
FLOOR_PAYLOADS_PER_POOL = 2

logger = logging.getLogger(__name__)

# Legs of the chain, in loop order (each a key of floor_key).
LEG_HAPTIC = "haptic"
LEG_COMMAND = "command"
LEG_STATE = "state"
LEG_FEEDBACK = "feedback"


def stamp(buf: bytearray, stage: Stage, t_ns: int) -> None:
    """Write one stamp into a floor payload."""
    STAMP_FORMAT.pack_into(buf, TRACE_OFFSET + int(stage) * STAMP_FORMAT.size, t_ns)


def read_trace(buf: bytes | bytearray) -> tuple[int, np.ndarray]:
    """(seq, trace_ns (N_STAGES,)) of a floor payload."""
    (seq,) = SEQ_FORMAT.unpack_from(buf, 0)
    return seq, np.frombuffer(buf, "<i8", N_STAGES, TRACE_OFFSET).astype(np.int64)


def subscribe_raw(
    session: zenoh.Session, key: str, callback: Callable[[bytes, int], None]
) -> zenoh.Subscriber:
    """Subscribe to raw payloads: ``callback(bytes, rx_ns)``, ``rx_ns`` stamped first."""

    def on_sample(sample: zenoh.Sample) -> None:
        rx_ns = time.monotonic_ns()
        callback(sample.payload.to_bytes(), rx_ns)

    return session.declare_subscriber(key, on_sample)


@dataclass(frozen=True)
class Route:
    """One leg a relay forwards: stamps ``rx_stages`` on arrival, ``tx_stage`` on send."""

    in_leg: str
    out_leg: str
    rx_stages: tuple[Stage, ...]
    tx_stage: Stage


def floor_provider(bus: BusConfig) -> tuple[shm.ShmProvider | None, shm.PoolReport | None]:
    """The floor's SHM provider and how its pool came out: the stack's pool size, or a
    smaller one that fits the locked-memory limit :data:`FLOOR_POOLS_PER_PROCESS` times
    (shm.open_provider, reason logged); (None, None) when shared memory is off. The
    launcher (teleop.bench.latency.run_floor) gives the relays the pool size its own
    provider came out with, so that every process of the chain holds the same."""
    if not bus.shm:
        return None, None
    provider, report = shm.open_provider(
        bus.shm_pool_bytes, shm.POOL_GRANULE_BYTES, pools_per_process=FLOOR_POOLS_PER_PROCESS
    )
    if report.reason:
        logger.warning("shared memory: %s", report.reason)
    return provider, report


def unmeasurable_reason(size_bytes: int, bus: BusConfig, pool: shm.PoolReport | None) -> str:
    """Why the floor chain cannot carry payloads of ``size_bytes`` (empty: it can).

    Over the socket (shared memory off) and inline (below the SHM threshold) any size
    goes. At or above the threshold, with shared memory on, a payload must go through a
    pool holding :data:`FLOOR_PAYLOADS_PER_POOL` of them: with the low-latency transport a
    put that finds no room is lost without an error, so such a size is not sent at all.
    """
    if not bus.shm or size_bytes < shm.SHM_THRESHOLD_BYTES:
        return ""
    pool_bytes = pool.pool_bytes if pool is not None else 0
    if pool_bytes >= FLOOR_PAYLOADS_PER_POOL * size_bytes:
        return ""
    why = f": {pool.reason}" if pool is not None and pool.reason else ""
    return (
        f"the floor's SHM pool of {pool_bytes} B holds fewer than "
        f"{FLOOR_PAYLOADS_PER_POOL} payloads of {size_bytes} B{why}"
    )


class RawPublisher:
    """A publisher of raw bytes with the QoS of :class:`teleop.bus.session.Publisher` (state and
    commands: express, real-time priority, blocking, reliable); SHM at the threshold."""

    def __init__(self, session: zenoh.Session, key: str, provider: shm.ShmProvider | None) -> None:
        self._pub = session.declare_publisher(
            key,
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.REAL_TIME,
            express=True,
            reliability=zenoh.Reliability.RELIABLE,
        )
        self._shm = provider

    def put(self, data: bytes | bytearray) -> None:
        shm.put_by_size(self._pub, data, self._shm)

    def undeclare(self) -> None:
        self._pub.undeclare()


class RelayService(Service):
    """A relay of the floor chain: forwards each payload of its routes at once, stamped."""

    ROUTES: ClassVar[tuple[Route, ...]] = ()

    def open(self) -> None:
        super().open()
        assert self.session is not None
        bus = self.config.bus
        self.forwarded = 0
        self._lock = threading.Lock()
        provider, _ = floor_provider(bus)
        for route in self.ROUTES:
            out = self.keep(
                RawPublisher(self.session, floor_key(self.topics.robot_id, route.out_leg), provider)
            )
            self.keep(
                subscribe_raw(
                    self.session,
                    floor_key(self.topics.robot_id, route.in_leg),
                    self._forward(route, out),
                )
            )
        self.announce()

    def _forward(self, route: Route, out: RawPublisher) -> Any:
        def on_payload(data: bytes, rx_ns: int) -> None:
            if len(data) < FLOOR_PREFIX_BYTES:
                return
            buf = bytearray(data)
            for stage in route.rx_stages:
                stamp(buf, stage, rx_ns)
            stamp(buf, route.tx_stage, time.monotonic_ns())
            out.put(buf)
            with self._lock:
                self.forwarded += 1

        return on_payload

    def run(self, stop: threading.Event) -> None:
        stop.wait()  # everything happens in the callbacks

    def summary(self) -> dict[str, Any]:
        return {**super().summary(), "forwarded": getattr(self, "forwarded", 0)}


class ControllerRelay(RelayService):
    """The controller's place: haptic -> command, and state -> feedback."""

    name = "relay_controller"
    scheduling_as = "controller"
    ROUTES = (
        Route(LEG_HAPTIC, LEG_COMMAND, (Stage.CONTROLLER_RX,), Stage.CONTROLLER_TX),
        Route(LEG_STATE, LEG_FEEDBACK, (Stage.CONTROLLER_STATE_RX,), Stage.FEEDBACK_TX),
    )


class PlantRelay(RelayService):
    """The plant's place: command -> state (applied the moment it arrives: no step)."""

    name = "relay_plant"
    scheduling_as = "plant"
    ROUTES = (
        Route(LEG_COMMAND, LEG_STATE, (Stage.PLANT_RX, Stage.PLANT_APPLIED), Stage.PLANT_STATE_TX),
    )


RELAYS: tuple[type[RelayService], ...] = (ControllerRelay, PlantRelay)
# Each relay and the service whose place (CPUs, scheduling) it takes in the loop.
FLOOR_STAND_INS: Mapping[str, str] = {relay.name: relay.scheduling_as for relay in RELAYS}


def floor_key(robot_id: str, leg: str) -> str:
    """Key of one leg of the floor's relay chain, e.g. ``teleop/arm0/floor/command``:
    under the robot's keys (same session config and QoS), apart from its real streams."""
    if not leg or any(c in leg for c in "/*$?#"):
        raise ValueError(f"leg name {leg!r}: non-empty, one key chunk")
    return f"{ROOT}/{robot_id}/floor/{leg}"


class FloorOrigin:
    """The haptic's place in the floor chain: sends payloads, keeps the returned traces.

    ``session`` is the caller's (the run's listener). Completed traces are rows of
    ``trace_log`` (stamps by Stage; FEEDBACK_RX = FEEDBACK_RENDERED = arrival).
    """

    def __init__(
        self, session: zenoh.Session, topics: Topics, provider: shm.ShmProvider | None
    ) -> None:
        self._pub = RawPublisher(session, floor_key(topics.robot_id, LEG_HAPTIC), provider)
        self._cond = threading.Condition()
        self._last_seq = -1
        self.trace_log = StampLog(N_STAGES)
        self.sent = 0
        self.received = 0
        self.reordered = 0
        self._recording = True
        self._sub = subscribe_raw(
            session, floor_key(topics.robot_id, LEG_FEEDBACK), self._on_return
        )

    def _on_return(self, data: bytes, rx_ns: int) -> None:
        if len(data) < FLOOR_PREFIX_BYTES:
            return
        seq, trace = read_trace(data)
        trace[Stage.FEEDBACK_RX] = rx_ns
        trace[Stage.FEEDBACK_RENDERED] = rx_ns
        with self._cond:
            if seq <= self._last_seq:
                self.reordered += 1
            else:
                self._last_seq = seq
            self.received += 1
            if self._recording:
                self.trace_log.append(trace)
            self._cond.notify_all()

    def _send(self, seq: int, size_bytes: int) -> None:
        buf = bytearray(max(size_bytes, FLOOR_PREFIX_BYTES))
        SEQ_FORMAT.pack_into(buf, 0, seq)
        stamp(buf, Stage.HAPTIC_SAMPLE, time.monotonic_ns())
        self._pub.put(buf)
        self.sent += 1

    def reset(self) -> None:
        """Forget the traces and counters of earlier rounds (a new measurement)."""
        with self._cond:
            self.trace_log = StampLog(N_STAGES)
            self.sent = self.received = self.reordered = 0

    def wait_returned(self, seq: int, timeout_s: float) -> bool:
        """Wait until the payload ``seq`` (or a later one) came back."""
        with self._cond:
            return self._cond.wait_for(lambda: self._last_seq >= seq, timeout_s)

    def paced(self, period_ns: int, duration_s: float, size_bytes: int, first_seq: int) -> int:
        """Send one payload per period for ``duration_s`` (absolute deadlines); next seq."""
        timer = LoopTimer(period_ns, MonotonicClock())
        seq = first_seq
        end_ns = time.monotonic_ns() + round(duration_s * 1e9)
        while time.monotonic_ns() < end_ns:
            timer.wait()
            self._send(seq, size_bytes)
            seq += 1
        return seq

    def back_to_back(
        self, count: int, size_bytes: int, first_seq: int, timeout_s: float, budget_s: float
    ) -> int:
        """Send ``count`` payloads, each as soon as the previous one came back; next seq.

        Stops early when ``budget_s`` is spent or a payload does not come back within
        ``timeout_s`` (counted as lost: sent minus received).
        """
        seq = first_seq
        end_ns = time.monotonic_ns() + round(budget_s * 1e9)
        for _ in range(count):
            self._send(seq, size_bytes)
            if not self.wait_returned(seq, timeout_s):
                break
            seq += 1
            if time.monotonic_ns() > end_ns:
                break
        return seq + 1

    def close(self) -> None:
        self._sub.undeclare()
        self._pub.undeclare()


def main(argv: list[str] | None = None) -> int:
    """``python -m teleop.bench.relay RELAY [service options]``: one relay process."""
    args = sys.argv[1:] if argv is None else argv
    relays = {relay.name: relay for relay in RELAYS}
    if not args or args[0] not in relays:
        print(f"usage: python -m teleop.bench.relay {{{','.join(relays)}}} [options]")
        return 2
    return service_main(relays[args[0]], args[1:])


if __name__ == "__main__":
    sys.exit(main())
