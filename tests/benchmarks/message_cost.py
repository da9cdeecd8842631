"""Benchmark: the CPU one message costs at each end, the stack's 1 kHz streams against a
bare zenoh-python publisher/subscriber pair (the floor), measured in the same run.

Each variant runs in two fresh processes (a sender and a receiver, the run's Zenoh
config: ``deploy/zenoh/local.json5`` with shared memory and the low-latency transport, a
loopback endpoint of its own) for ``--seconds`` at 1 kHz, the sender on absolute 1 ms
deadlines. Each end reports its process CPU time (every thread, Zenoh's included) from
its first message to its last, over the messages it handled: microseconds of CPU per
message. Variants, rounds alternating:

- ``floor``: ``Publisher.put(bytes)`` of a payload of the stream's size, and a default
  Python callback that takes the payload's bytes (zenoh-python's own path, nothing of
  ours);
- ``floor_ring``: the same sender, the receiver on a ``RingChannel(1)`` drained by a
  thread (what a newest-only consumer does), for the hand-off's own cost;
- ``floor_direct``: the floor's callback on Zenoh's own receiving thread
  (``Callback(..., indirect=False)``: no hand-off to a Python thread);
- ``<stream>`` for each 1 kHz stream of the stack (``plant_state``, ``joint_command``,
  ``haptic_state``, ``force_feedback``): the stack's path for that stream's record, the
  typed :class:`teleop.bus.session.Publisher` (encode, put) and the subscription its
  consumer takes in a realtime run (:meth:`teleop.bus.graph.Stream.takes_newest`:
  decode, validate, call back).

Prints per variant the median over rounds of each end's CPU per message and its ratio to
the floor's; writes JSON (``--json``).

    .venv/bin/python tests/benchmarks/message_cost.py --seconds 10 --rounds 3
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import Any

# The stack's 1 kHz streams and the consumer whose subscription each one takes.
STREAM_CONSUMERS = {
    "plant_state": "controller",
    "joint_command": "plant",
    "haptic_state": "controller",
    "force_feedback": "haptic",
}
# The scenario whose realtime subscriptions are measured (its 1 kHz loop).
SCENARIO = "grasp"
PERIOD_NS = 1_000_000  # 1 kHz
# The receiver's first messages pay one-off costs (imports, first allocations): CPU is
# counted from this many messages on.
WARMUP_MESSAGES = 200
SPAWN = mp.get_context("spawn")


def _bus(endpoint: str) -> Any:
    from teleop.core.config import load_config

    config = load_config(None, ())
    from dataclasses import replace

    return replace(config.bus, endpoint=endpoint, gossip=False)


def receiver(variant: str, endpoint: str, messages: int, report: Any) -> None:
    """Subscribe as ``variant`` says; report (CPU s, messages) from message WARMUP on."""
    import zenoh

    from teleop.bus import session as bus
    from teleop.bus.messages import DropCounter
    from teleop.bus.topics import Topics

    session = bus.open_session(_bus(endpoint), listen=True)
    count = [0]
    start = [0.0]
    done = threading.Event()

    def tick() -> None:
        count[0] += 1
        if count[0] == WARMUP_MESSAGES:
            start[0] = time.process_time()
        elif count[0] == messages:
            done.set()

    key = "bench/raw"
    if variant == "floor":
        sub = session.declare_subscriber(key, lambda sample: (sample.payload.to_bytes(), tick()))
    elif variant == "floor_direct":
        sub = session.declare_subscriber(
            key,
            zenoh.handlers.Callback(
                lambda sample: (sample.payload.to_bytes(), tick()), indirect=False
            ),  # fmt: skip
        )
    elif variant == "floor_ring":
        sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(1))
        ring = sub.handler

        def drain() -> None:
            while True:
                try:
                    ring.recv().payload.to_bytes()
                except zenoh.ZError:
                    return
                tick()

        threading.Thread(target=drain, daemon=True).start()
    else:
        sub = bus.subscribe_stream(
            session, Topics("bench"), variant, lambda rec, rx_ns: tick(), DropCounter(),
            consumer=STREAM_CONSUMERS[variant], mode="realtime", scenario=SCENARIO,
        )  # fmt: skip
    report.put(("ready", variant))
    done.wait(60 + messages / 1000)
    cpu_s = time.process_time() - start[0]
    report.put(("receiver", cpu_s, count[0] - WARMUP_MESSAGES))
    bus.close_session(session, sub)


def sender(variant: str, endpoint: str, messages: int, size: int, report: Any) -> None:
    """Publish ``messages`` at 1 kHz; report (CPU s, messages) from message WARMUP on."""
    from teleop.bus import graph
    from teleop.bus import session as bus
    from teleop.bus.topics import Topics

    session = bus.open_session(_bus(endpoint), listen=False)
    if variant.startswith("floor"):
        pub = session.declare_publisher("bench/raw", express=True)
        payload = bytes(size)

        def put(seq: int) -> None:
            pub.put(payload)

    else:
        stream = graph.stream(variant)
        typed = bus.Publisher.for_stream(session, Topics("bench"), variant)
        pub = typed
        rec = stream.schema.new()

        def put(seq: int) -> None:
            rec["seq"] = seq
            rec["t_source_ns"] = time.monotonic_ns()
            typed.put(rec)

    # Wait for the receiver's subscription (event driven), then pace on deadlines.
    matched = threading.Event()
    zpub = pub if variant.startswith("floor") else pub._pub
    listener = zpub.declare_matching_listener(lambda s: s.matching and matched.set())
    if not zpub.matching_status.matching:
        matched.wait(30)
    listener.undeclare()
    deadline = time.monotonic_ns()
    start = 0.0
    for seq in range(messages + 50):  # a few more: a ring may skip the very last ones
        if seq == WARMUP_MESSAGES:
            start = time.process_time()
        put(seq)
        deadline += PERIOD_NS
        delay = deadline - time.monotonic_ns()
        if delay > 0:
            time.sleep(delay / 1e9)
    report.put(("sender", time.process_time() - start, messages + 50 - WARMUP_MESSAGES))
    bus.close_session(session, pub)


def run_variant(variant: str, seconds: float, size: int) -> dict[str, float]:
    from teleop.core.net import free_loopback_port

    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    messages = int(seconds * 1000)
    report: Any = SPAWN.Queue()
    rx = SPAWN.Process(target=receiver, args=(variant, endpoint, messages, report))
    rx.start()
    assert report.get(timeout=60)[0] == "ready"
    tx = SPAWN.Process(target=sender, args=(variant, endpoint, messages, size, report))
    tx.start()
    results = {}
    for _ in range(2):
        tag, cpu_s, count = report.get(timeout=120 + seconds)
        results[tag] = cpu_s / max(count, 1) * 1e6
    tx.join(30)
    rx.join(30)
    return {"sender_us": results["sender"], "receiver_us": results["receiver"]}


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=10.0, help="per variant and round")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--json", type=Path, default=Path("runs/bench/message_cost.json"))
    args = parser.parse_args()
    if args.rounds < 1 or args.seconds * 1000 <= 2 * WARMUP_MESSAGES:
        parser.error("--rounds >= 1 and --seconds > 0.4")
    from teleop.bus import graph

    size = graph.stream("plant_state").schema.size  # the largest 1 kHz record
    variants = ["floor", "floor_ring", "floor_direct", *STREAM_CONSUMERS]
    loadavg_before = os.getloadavg()
    rounds: list[dict[str, dict[str, float]]] = []
    for index in range(args.rounds):
        order = variants if index % 2 == 0 else list(reversed(variants))
        measured = {variant: run_variant(variant, args.seconds, size) for variant in order}
        rounds.append(measured)
        print(
            f"round {index + 1}/{args.rounds}: "
            + ", ".join(
                f"{v} {r['sender_us']:.0f}/{r['receiver_us']:.0f} us" for v, r in measured.items()
            ),
            flush=True,
        )
    median = {
        variant: {
            end: statistics.median(r[variant][end] for r in rounds)
            for end in ("sender_us", "receiver_us")
        }
        for variant in variants
    }
    floor = median["floor"]
    for figures in median.values():
        figures["sender_ratio"] = figures["sender_us"] / floor["sender_us"]
        figures["receiver_ratio"] = figures["receiver_us"] / floor["receiver_us"]
    print(f"CPU per message at 1 kHz (median of {args.rounds}; sender / receiver, ratio to floor):")
    for variant, figures in median.items():
        print(
            f"  {variant:15s} {figures['sender_us']:6.1f} / {figures['receiver_us']:6.1f} us"
            f"   x{figures['sender_ratio']:.2f} / x{figures['receiver_ratio']:.2f}"
        )
    result = {
        "seconds": args.seconds,
        "payload_bytes_floor": size,
        "rounds": rounds,
        "median": median,
        "loadavg_before": loadavg_before,
        "loadavg_after": os.getloadavg(),
        "cpus": len(os.sched_getaffinity(0)),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
