"""A network in between: a user-space TCP proxy that delays, jitters and loses.

The kernel's ``tc netem`` is not available on these machines, so a link between two
Zenoh sessions (two sites' routers, a service and its peer) goes through this proxy
when a test or a benchmark wants distance: everything one side sends reaches the other
``delay_s`` later, give or take ``jitter_s``, in order. Test and benchmark tooling, not
the product's data path.

TCP cannot lose bytes without breaking the stream, so loss is what TCP makes of it: a
chunk "lost" on the way arrives one retransmission later (``retransmit_s``, Linux's
minimum RTO by default), holding back everything behind it, as a real loss holds back
a TCP stream. Per direction, each chunk read is due at

    max(received + delay + U(-jitter, +jitter) [+ retransmit if lost], previous due)

(order preserved; a seeded generator, so a run is repeatable).

A **cut** (:class:`LinkCut`) breaks the link for a while, as a pulled cable or a
failed route whose endpoints notice: ``after_s`` past the first connection forwarded,
every open connection is reset (both sides at once) and new ones are refused (reset as
they come) for ``duration_s``; then connections are forwarded again, and the
connecting side's retries find the link back. Run it by hand::

    python -m teleop.bench.netem --listen 127.0.0.1:7448 --target 127.0.0.1:7447 \\
        --delay-ms 50 --jitter-ms 5 --loss 0.01 --cut 20:0.5

and point the connecting side at the listen address.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import random
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# Linux's minimum TCP retransmission timeout (TCP_RTO_MIN): what one loss costs.
DEFAULT_RETRANSMIT_S = 0.2
READ_BYTES = 64 * 1024  # largest chunk read at once


@dataclass(frozen=True)
class LinkImpairment:
    """One direction's (or both's) delay, jitter and loss."""

    delay_s: float = 0.0  # one way
    jitter_s: float = 0.0  # uniform in [-jitter_s, +jitter_s] around the delay
    loss: float = 0.0  # probability that a chunk is lost (and resent by TCP)
    retransmit_s: float = DEFAULT_RETRANSMIT_S  # what a loss adds

    def __post_init__(self) -> None:
        if self.delay_s < 0 or self.jitter_s < 0 or self.retransmit_s < 0:
            raise ValueError("delay, jitter and retransmission time must be >= 0")
        if not 0.0 <= self.loss < 1.0:
            raise ValueError(f"loss {self.loss}: a probability in [0, 1)")

    def describe(self) -> str:
        return (
            f"delay {self.delay_s * 1e3:g} ms, jitter +-{self.jitter_s * 1e3:g} ms, "
            f"loss {self.loss:.1%} (a loss costs {self.retransmit_s * 1e3:g} ms)"
        )


@dataclass(frozen=True)
class LinkCut:
    """The link broken for ``duration_s``, ``after_s`` after the first connection the
    proxy forwarded (so a cut falls at the same point of a run whatever its start-up
    took)."""

    after_s: float
    duration_s: float

    def __post_init__(self) -> None:
        if not (self.after_s >= 0 and self.duration_s > 0):
            raise ValueError(f"a cut needs after_s >= 0 and duration_s > 0, got {self}")

    @classmethod
    def parse(cls, text: str) -> LinkCut:
        """``AFTER_S:DURATION_S``, e.g. ``20:0.5``."""
        after, sep, duration = text.partition(":")
        try:
            if not sep:
                raise ValueError(text)
            return cls(float(after), float(duration))
        except ValueError as exc:
            raise ValueError(
                f"{text!r}: AFTER_S:DURATION_S (s after the first connection, s cut), e.g. 20:0.5"
            ) from exc


@dataclass
class CutRecord:
    """One cut as it happened: monotonic ns of this host, the connections it reset and
    those refused while it lasted."""

    start_ns: int
    end_ns: int = 0
    reset: int = 0
    refused: int = 0


@dataclass
class DeliverySchedule:
    """When each chunk of one direction is delivered (pure: seconds in, seconds out)."""

    impairment: LinkImpairment
    rng: random.Random
    chunks: int = 0
    lost: int = 0
    _last_due_s: float = field(default=float("-inf"), repr=False)

    def due_s(self, received_s: float) -> float:
        """The time a chunk received at ``received_s`` is passed on: never before one
        received earlier (a TCP stream keeps its order)."""
        link = self.impairment
        extra_s = link.delay_s
        if link.jitter_s:
            extra_s += self.rng.uniform(-link.jitter_s, link.jitter_s)
        if link.loss and self.rng.random() < link.loss:
            extra_s += link.retransmit_s
            self.lost += 1
        self.chunks += 1
        due = max(received_s + max(extra_s, 0.0), self._last_due_s)
        self._last_due_s = due
        return due


@dataclass
class DirectionStats:
    """What one direction of all connections forwarded."""

    bytes: int = 0
    chunks: int = 0
    lost: int = 0


class ImpairedProxy:
    """Accepts TCP connections on a port and forwards each to ``target`` through a
    :class:`DeliverySchedule` per direction. Runs on an asyncio loop."""

    def __init__(
        self,
        target: tuple[str, int],
        impairment: LinkImpairment,
        *,
        seed: int = 0,
        listen: tuple[str, int] = ("127.0.0.1", 0),
        cuts: tuple[LinkCut, ...] = (),
    ) -> None:
        self.target = target
        self.impairment = impairment
        self.listen = listen
        self.cuts = cuts
        self._rng = random.Random(seed)
        self._server: asyncio.Server | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._open: set[asyncio.StreamWriter] = set()  # both ends of every forwarded link
        self._cut: CutRecord | None = None  # the cut under way
        self.cut_log: list[CutRecord] = []
        self.connections = 0
        self.refused = 0  # connections closed at once: nothing listened on the target
        self.forward = DirectionStats()  # listen side -> target
        self.backward = DirectionStats()  # target -> listen side

    @property
    def port(self) -> int:
        """The port it listens on (chosen by the kernel when ``listen`` asked for 0)."""
        assert self._server is not None, "not started"
        return int(self._server.sockets[0].getsockname()[1])

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._accept, *self.listen)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)

    def stats(self) -> dict[str, Any]:
        return {
            "impairment": self.impairment.describe(),
            "connections": self.connections,
            "refused": self.refused,
            "forward": vars(self.forward).copy(),
            "backward": vars(self.backward).copy(),
            "cuts": [vars(cut).copy() for cut in self.cut_log],
        }

    def _schedule_cuts(self) -> None:
        loop = asyncio.get_running_loop()
        for cut in self.cuts:
            loop.call_later(cut.after_s, self._begin_cut, cut.duration_s)

    def _begin_cut(self, duration_s: float) -> None:
        """Reset every open connection and refuse new ones for ``duration_s``."""
        record = CutRecord(start_ns=time.monotonic_ns(), reset=len(self._open) // 2)
        self._cut = record
        self.cut_log.append(record)
        for writer in list(self._open):
            writer.transport.abort()  # a reset, not an orderly close: the link failed
        print(f"netem: link cut for {duration_s:g} s ({record.reset} connection(s) reset)",
              file=sys.stderr, flush=True)  # fmt: skip
        asyncio.get_running_loop().call_later(duration_s, self._end_cut, record)

    def _end_cut(self, record: CutRecord) -> None:
        record.end_ns = time.monotonic_ns()
        self._cut = None
        print(f"netem: link back ({record.refused} connection(s) refused meanwhile)",
              file=sys.stderr, flush=True)  # fmt: skip

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._cut is not None:
            self._cut.refused += 1
            writer.transport.abort()
            return
        try:
            target_reader, target_writer = await asyncio.open_connection(*self.target)
        except OSError as exc:
            writer.close()  # nothing to forward to: the connecting side sees it closed
            if not self.refused:
                print(f"netem: cannot reach {self.target[0]}:{self.target[1]} ({exc}): "
                      "connections are closed until it listens", file=sys.stderr)  # fmt: skip
            self.refused += 1
            return
        if not self.connections:
            self._schedule_cuts()
        self.connections += 1
        self._open.update((writer, target_writer))
        pumps = [
            self._pump(reader, target_writer, self.forward),
            self._pump(target_reader, writer, self.backward),
        ]
        tasks = [asyncio.create_task(pump) for pump in pumps]
        self._tasks.update(tasks)
        try:  # until both sides are done (a half-closed side may still receive)
            await asyncio.gather(*tasks, return_exceptions=True)
        finally:
            for task in tasks:
                task.cancel()
                self._tasks.discard(task)
            for w in (writer, target_writer):
                self._open.discard(w)
                w.close()

    async def _pump(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, stats: DirectionStats
    ) -> None:
        """Read chunks as they come and hand each on at its due time, in order."""
        loop = asyncio.get_running_loop()
        schedule = DeliverySchedule(self.impairment, random.Random(self._rng.random()))
        due: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue()

        async def deliver() -> None:
            while True:
                at_s, data = await due.get()
                wait_s = at_s - loop.time()
                if wait_s > 0:
                    await asyncio.sleep(wait_s)
                if not data:  # the sender closed: close after what came before
                    if writer.can_write_eof():
                        writer.write_eof()
                    else:
                        writer.close()
                    return
                writer.write(data)
                await writer.drain()

        delivering = asyncio.create_task(deliver())
        try:
            while True:
                data = await reader.read(READ_BYTES)
                lost = schedule.lost
                due.put_nowait((schedule.due_s(loop.time()), data))
                if not data:
                    break
                stats.bytes += len(data)
                stats.chunks += 1
                stats.lost += schedule.lost - lost
            await delivering
        finally:
            delivering.cancel()


@contextlib.contextmanager
def running_proxy(
    target: tuple[str, int],
    impairment: LinkImpairment,
    *,
    seed: int = 0,
    cuts: tuple[LinkCut, ...] = (),
) -> Iterator[ImpairedProxy]:
    """An :class:`ImpairedProxy` on a loopback port of its own, on a thread of its own
    (for tests and benchmarks); stopped on leaving."""
    loop = asyncio.new_event_loop()
    proxy = ImpairedProxy(target, impairment, seed=seed, cuts=cuts)
    thread = threading.Thread(target=loop.run_forever, name="netem", daemon=True)
    thread.start()
    try:
        asyncio.run_coroutine_threadsafe(proxy.start(), loop).result(timeout=10)
        yield proxy
    finally:
        asyncio.run_coroutine_threadsafe(proxy.close(), loop).result(timeout=10)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout=10)
        loop.close()


def _address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit():
        raise argparse.ArgumentTypeError(f"{text!r}: HOST:PORT, e.g. 127.0.0.1:7448")
    return host, int(port)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m teleop.bench.netem", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--listen", type=_address, required=True, help="HOST:PORT to accept on")
    parser.add_argument("--target", type=_address, required=True, help="HOST:PORT to forward to")
    parser.add_argument("--delay-ms", type=float, default=0.0, help="one-way delay (ms)")
    parser.add_argument("--jitter-ms", type=float, default=0.0, help="+- uniform jitter (ms)")
    parser.add_argument("--loss", type=float, default=0.0, help="chunk loss probability")
    parser.add_argument(
        "--retransmit-ms", type=float, default=DEFAULT_RETRANSMIT_S * 1e3,
        help="what one loss delays the stream by (ms; TCP's minimum RTO by default)",
    )  # fmt: skip
    parser.add_argument("--seed", type=int, default=0, help="random seed (jitter, loss)")
    parser.add_argument(
        "--cut", action="append", default=[], metavar="AFTER_S:DURATION_S",
        help="break the link for DURATION_S, AFTER_S after the first connection forwarded: "
        "open connections reset, new ones refused meanwhile (repeatable)",
    )  # fmt: skip
    parser.add_argument(
        "--report", type=Path, default=None,
        help="on exit, write what was forwarded and each cut (monotonic ns) here as JSON",
    )  # fmt: skip
    args = parser.parse_args(argv)
    try:
        impairment = LinkImpairment(
            args.delay_ms / 1e3, args.jitter_ms / 1e3, args.loss, args.retransmit_ms / 1e3
        )
        cuts = tuple(LinkCut.parse(text) for text in args.cut)
    except ValueError as exc:
        parser.error(str(exc))

    async def serve() -> ImpairedProxy:
        proxy = ImpairedProxy(
            args.target, impairment, seed=args.seed, listen=args.listen, cuts=cuts
        )
        try:
            await proxy.start()
        except OSError as exc:
            parser.exit(2, f"netem: cannot listen on {args.listen[0]}:{args.listen[1]}: {exc}\n")
        print(
            f"netem: {args.listen[0]}:{proxy.port} -> {args.target[0]}:{args.target[1]}, "
            f"{impairment.describe()}; Ctrl-C stops",
            file=sys.stderr,
            flush=True,
        )
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for signum in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(signum, stop.set)
        await stop.wait()
        await proxy.close()
        return proxy

    proxy = asyncio.run(serve())
    print(f"netem: {proxy.stats()}", file=sys.stderr)
    if args.report is not None:
        args.report.write_text(json.dumps(proxy.stats(), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
