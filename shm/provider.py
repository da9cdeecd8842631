"""The shared-memory layer: one Zenoh SHM provider per process, and path proofs.

Zenoh moves a payload through shared memory when it is published from a buffer of a
SHM provider (``ZShmMut``) and both ends have shared memory enabled; the receiver then
maps the same pages instead of reading a socket. Small payloads cost less inline, so the
publisher only takes the SHM path at or above :data:`SHM_THRESHOLD_BYTES`, the same
value the session uses for its own transport optimisation (:func:`configure_session`
sets it).

Python cannot write into a ``ZShmMut`` through the buffer protocol: the data is copied
once in (slice assignment) and once out (``to_bytes``) on the receiving side.
"""

from __future__ import annotations

import json
import threading

import zenoh
from zenoh.shm import BlockOn, GarbageCollect, ShmProvider

# Payloads of at least this many bytes go through SHM; smaller ones inline. Zenoh's
# default message_size_threshold: below it a socket write is cheaper than SHM bookkeeping.
SHM_THRESHOLD_BYTES = 3072

_lock = threading.Lock()
_providers: dict[int, ShmProvider] = {}


def get_provider(pool_bytes: int) -> ShmProvider:
    """The process's SHM provider with a pool of ``pool_bytes`` (created on first use).

    One pool per process (per size): pools are POSIX SHM segments under /dev/shm,
    mode 0600, so they are shared by the user's processes and nobody else.
    """
    if pool_bytes <= 0:
        raise ValueError(f"pool_bytes must be > 0, got {pool_bytes}")
    with _lock:
        provider = _providers.get(pool_bytes)
        if provider is None:
            provider = ShmProvider.default_backend(pool_bytes)
            _providers[pool_bytes] = provider
        return provider


def configure_session(conf: zenoh.Config, *, enabled: bool, lowlatency: bool) -> None:
    """Set a session's shared-memory transport in ``conf``: on or off, and Zenoh's
    low-latency unicast transport (``lowlatency``, only with shared memory: it carries
    no QoS, so priorities and express stop applying, and every put goes out at once).

    With shared memory on: segments created at start (``init``: no first-message delay),
    used for puts only (a query dropped under CPU stalls otherwise), for payloads of at
    least :data:`SHM_THRESHOLD_BYTES`.
    """
    key = "transport/shared_memory"
    conf.insert_json5(f"{key}/enabled", json.dumps(enabled))
    lowlatency = enabled and lowlatency
    conf.insert_json5("transport/unicast/lowlatency", json.dumps(lowlatency))
    conf.insert_json5("transport/unicast/qos/enabled", json.dumps(not lowlatency))
    if enabled:
        conf.insert_json5(f"{key}/mode", json.dumps("init"))
        conf.insert_json5(f"{key}/transport_optimization/messages", json.dumps(["put"]))
        conf.insert_json5(
            f"{key}/transport_optimization/message_size_threshold",
            json.dumps(SHM_THRESHOLD_BYTES),
        )


def put_by_size(
    pub: zenoh.Publisher, data: bytes | bytearray, provider: ShmProvider | None
) -> None:
    """Put ``data`` on ``pub`` by the path its size calls for: through a SHM buffer of
    ``provider`` at or above the threshold, inline below it (or without a provider)."""
    if provider is not None and len(data) >= SHM_THRESHOLD_BYTES:
        publish_bytes(pub, data, provider)
    else:
        pub.put(bytes(data))


def publish_bytes(pub: zenoh.Publisher, data: bytes | bytearray, provider: ShmProvider) -> None:
    """Copy ``data`` into a SHM buffer of ``provider`` and put it on ``pub``.

    Allocation blocks (after garbage-collecting buffers receivers have released) when
    the pool is full, rather than silently falling back to the socket path.
    """
    buf = provider.alloc(len(data), policy=BlockOn(GarbageCollect()))
    buf[:] = data
    pub.put(buf)


def took_shm_path(sample: zenoh.Sample) -> bool:
    """True if ``sample`` arrived through shared memory (not copied over the socket)."""
    return sample.payload.as_shm() is not None
