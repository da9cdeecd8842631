"""The shared-memory layer: one Zenoh SHM provider per process, and path proofs.

Zenoh moves a payload through shared memory when it is published from a buffer of a
SHM provider (``ZShmMut``) and both ends have shared memory enabled; the receiver then
maps the same pages instead of reading a socket. Small payloads cost less inline, so the
publisher only takes the SHM path at or above :data:`SHM_THRESHOLD_BYTES`, the same
value the session uses for its own transport optimisation (:func:`configure_session`
sets it).

Python cannot write into a ``ZShmMut`` through the buffer protocol: the data is copied
once in (slice assignment) and once out (``to_bytes``) on the receiving side.

SHM segments are locked in memory, so a process without ``CAP_IPC_LOCK`` (an ordinary
user) can hold only ``RLIMIT_MEMLOCK`` bytes of them (``ulimit -l``, often 8 MiB). Seen
with Zenoh 1.10.2: a session locks about 1.3 MiB by itself; a publisher's pool costs its
size; a receiver that maps it costs the pool's size plus about 1.3-2.5 MiB. A pool the
publisher cannot lock fails to be created (``OS error 12``); one a receiver cannot map
is silently not received; and with the low-latency transport a large put that finds no
pool is lost without an error. So every pool here is sized within the limit, for the
receivers as well: the provider's pool (:func:`open_provider`, which falls back to the
socket path when not even the minimum fits) and the session's own transport pool
(:func:`configure_session`). A process that maps several pools (its own and its
peers', as a relay of the transport floor does) must fit all of them: the budget is
then shared (``pools_per_process``).
"""

from __future__ import annotations

import json
import logging
import re
import resource
import threading
from dataclasses import dataclass
from pathlib import Path

import zenoh
from zenoh.shm import BlockOn, GarbageCollect, ShmProvider

# Payloads of at least this many bytes go through SHM; smaller ones inline. Zenoh's
# default message_size_threshold: below it a socket write is cheaper than SHM bookkeeping.
SHM_THRESHOLD_BYTES = 3072

# Locked memory a Zenoh session with shared memory needs at start (its SHM metadata,
# seen: about 1.3 MiB); below it the session panics at open, so configure_session turns
# shared memory off instead, bytes.
SESSION_SHM_LOCKED_BYTES = 1536 * 1024
# Locked memory of a process that receives from a pool, besides the pool itself: its
# session and Zenoh's fixed SHM mappings (the recorder's, the largest, under 4 MiB), bytes.
RECEIVER_LOCKED_BYTES = 4 * 1024 * 1024
# A pool takes at most this share of what a receiver has left after RECEIVER_LOCKED_BYTES:
# the receiver's fixed share varies with the Zenoh build, so keep a margin of 2x.
RECEIVER_POOL_SHARE = 0.5
# Kept free besides a pool (segment headers, other small locked buffers), bytes.
MEMLOCK_MARGIN_BYTES = 256 * 1024
# Pools are sized in whole multiples of this (Zenoh's allocation granularity is far
# smaller; a round size reads better in a summary), bytes.
POOL_GRANULE_BYTES = 64 * 1024
# Bit of CAP_IPC_LOCK in /proc/self/status CapEff: a process that has it is not bound by
# RLIMIT_MEMLOCK.
CAP_IPC_LOCK_BIT = 14
_PROC_STATUS = Path("/proc/self/status")

logger = logging.getLogger(__name__)
_lock = threading.Lock()
_providers: dict[int, ShmProvider] = {}


def _status_field(name: str) -> str | None:
    match = re.search(rf"^{name}:\s*(\S+)", _PROC_STATUS.read_text(), re.MULTILINE)
    return match.group(1) if match else None


def memlock_budget_bytes(reserve_bytes: int = 0) -> int | None:
    """Bytes this process may still lock (``RLIMIT_MEMLOCK`` soft limit minus what it has
    locked, ``VmLck``, minus ``reserve_bytes`` and a margin); None when nothing bounds it
    (the limit is infinite, or the process has ``CAP_IPC_LOCK``, as root does)."""
    soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    cap_eff = _status_field("CapEff")
    if soft == resource.RLIM_INFINITY or (
        cap_eff is not None and int(cap_eff, 16) >> CAP_IPC_LOCK_BIT & 1
    ):
        return None
    locked_kib = _status_field("VmLck")
    locked = int(locked_kib) * 1024 if locked_kib is not None else 0
    return max(0, soft - locked - reserve_bytes - MEMLOCK_MARGIN_BYTES)


def fit_pool_bytes(requested_bytes: int, budget_bytes: int | None) -> int:
    """The largest pool of at most ``requested_bytes`` within ``budget_bytes`` (None: no
    bound), in whole :data:`POOL_GRANULE_BYTES`; 0 when not even one fits."""
    if budget_bytes is None or requested_bytes <= budget_bytes:
        return requested_bytes
    return budget_bytes // POOL_GRANULE_BYTES * POOL_GRANULE_BYTES


@dataclass(frozen=True)
class PoolReport:
    """How a process's SHM pool came out, for its summary."""

    requested_bytes: int
    pool_bytes: int  # 0: no pool, payloads go over the socket
    memlock_limit_bytes: int | None  # RLIMIT_MEMLOCK soft limit; None: unlimited
    memlock_bound: bool  # the limit applies to this process (no CAP_IPC_LOCK)
    reason: str  # why the pool is smaller than asked or absent; empty when it is not

    @property
    def path(self) -> str:
        """ "shm" when payloads go through the pool, "socket" when there is none."""
        return "shm" if self.pool_bytes else "socket"

    def as_dict(self) -> dict[str, object]:
        return {
            "path": self.path,
            "requested_bytes": self.requested_bytes,
            "pool_bytes": self.pool_bytes,
            "memlock_limit_bytes": self.memlock_limit_bytes,
            "memlock_bound": self.memlock_bound,
            "reason": self.reason,
        }


def memlock_limit_bytes() -> int | None:
    """``RLIMIT_MEMLOCK``'s soft limit (``ulimit -l``), bytes; None when unlimited."""
    soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    return None if soft == resource.RLIM_INFINITY else soft


def shared_pool_budget_bytes(pools_per_process: int = 1) -> int | None:
    """The largest pool this process can lock and a receiver under the same limit can
    map (the run's processes are one user's: same limit), when each process holds or
    maps up to ``pools_per_process`` pools of that size; None when nothing bounds it."""
    if pools_per_process < 1:
        raise ValueError(f"pools_per_process must be >= 1, got {pools_per_process}")
    own = memlock_budget_bytes()
    limit = memlock_limit_bytes()
    if own is None or limit is None:
        return None
    receiver = int(max(0, limit - RECEIVER_LOCKED_BYTES) * RECEIVER_POOL_SHARE)
    return min(own, receiver) // pools_per_process


def open_provider(
    requested_bytes: int, minimum_bytes: int, *, pools_per_process: int = 1
) -> tuple[ShmProvider | None, PoolReport]:
    """The process's provider with a pool of ``requested_bytes``, or less to fit the
    locked-memory limit (never less than ``minimum_bytes``); without one (even the
    minimum does not fit, or Zenoh refuses the segment) None: the caller publishes over
    the socket. ``pools_per_process``: pools of this size one process of the run holds
    or maps at once (see :func:`shared_pool_budget_bytes`). The report says which, and
    why."""
    budget = shared_pool_budget_bytes(pools_per_process)
    pool_bytes = fit_pool_bytes(requested_bytes, budget)
    limit = memlock_limit_bytes()
    shared = f" (in this process and its receivers, {pools_per_process} pools each)"
    if pools_per_process == 1:
        shared = " (in this process and its receivers)"
    reason = ""
    if pool_bytes < requested_bytes:
        reason = (
            f"RLIMIT_MEMLOCK (ulimit -l) {limit} B leaves room for a pool of {budget} B"
            f"{shared}: pool of {pool_bytes} B instead of {requested_bytes} B"
        )
    provider = None
    if pool_bytes < minimum_bytes:
        if pool_bytes < requested_bytes:
            reason = (
                f"RLIMIT_MEMLOCK (ulimit -l) {limit} B leaves room for a pool of {budget} B"
                f"{shared}, below the {minimum_bytes} B needed: socket path (raise the "
                "limit for shared memory)"
            )
        else:
            reason = (
                f"a pool of {requested_bytes} B (bus.shm_pool_bytes) is below the "
                f"{minimum_bytes} B needed: socket path"
            )
        pool_bytes = 0
    else:
        try:
            provider = get_provider(pool_bytes)
        except zenoh.ZError as exc:
            reason = f"SHM pool of {pool_bytes} B refused ({exc}): socket path"
            pool_bytes = 0
    report = PoolReport(requested_bytes, pool_bytes, limit, budget is not None, reason)
    return provider, report


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
    least :data:`SHM_THRESHOLD_BYTES`, its transport pool (``pool_size``, taken when a
    large payload is put without a provider) shrunk to fit the locked-memory limit.
    """
    key = "transport/shared_memory"
    budget = memlock_budget_bytes()
    if enabled and budget is not None and budget < SESSION_SHM_LOCKED_BYTES:
        # Every process of a run is the same user's, under the same limit: all of them
        # turn it off alike, so the peers still agree on the transport.
        logger.warning(
            "shared memory off: RLIMIT_MEMLOCK (ulimit -l) %s B leaves %d B to lock, a "
            "session needs about %d B; payloads go over the socket",
            memlock_limit_bytes(),
            budget,
            SESSION_SHM_LOCKED_BYTES,
        )
        enabled = False
    conf.insert_json5(f"{key}/enabled", json.dumps(enabled))
    if not enabled:
        # "init" (local.json5) creates Zenoh's SHM metadata segment at open even with
        # shared memory off, and panics if it cannot lock it.
        conf.insert_json5(f"{key}/mode", json.dumps("lazy"))
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
        pool_key = f"{key}/transport_optimization/pool_size"
        requested = int(json.loads(conf.get_json(pool_key)))
        fitted = fit_pool_bytes(requested, shared_pool_budget_bytes())
        if fitted < requested:
            conf.insert_json5(pool_key, json.dumps(max(fitted, POOL_GRANULE_BYTES)))


def put_by_size(
    pub: zenoh.Publisher,
    data: bytes | bytearray,
    provider: ShmProvider | None,
    *,
    block: bool = True,
) -> bool:
    """Put ``data`` on ``pub`` by the path its size calls for: through a SHM buffer of
    ``provider`` at or above the threshold, inline below it (or without a provider).
    False when the pool was full and ``block`` is off (see :func:`publish_bytes`)."""
    if provider is not None and len(data) >= SHM_THRESHOLD_BYTES:
        return publish_bytes(pub, data, provider, block=block)
    pub.put(bytes(data))
    return True


def publish_bytes(
    pub: zenoh.Publisher, data: bytes | bytearray, provider: ShmProvider, *, block: bool = True
) -> bool:
    """Copy ``data`` into a SHM buffer of ``provider`` and put it on ``pub``; whether it
    was sent.

    When the pool is full (receivers still hold its buffers), allocation first
    garbage-collects the buffers receivers have released; then, with ``block``, it waits
    for more (a stream that must not lose a record), else the record is not sent and
    False returned (a viewer's stream: a slow receiver must not stall the publisher, and
    a thread blocked in that native wait cannot even run its stop signal's handler).
    """
    policy = BlockOn(GarbageCollect()) if block else GarbageCollect()
    try:
        buf = provider.alloc(len(data), policy=policy)
    except zenoh.ZError:
        if block:
            raise
        return False
    buf[:] = data
    pub.put(buf)
    return True


def took_shm_path(sample: zenoh.Sample) -> bool:
    """True if ``sample`` arrived through shared memory (not copied over the socket)."""
    return sample.payload.as_shm() is not None
