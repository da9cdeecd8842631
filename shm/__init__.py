"""Shared-memory transport helpers (see :mod:`shm.provider`)."""

from shm.provider import (
    SHM_THRESHOLD_BYTES,
    PoolReport,
    ShmProvider,
    configure_session,
    get_provider,
    memlock_budget_bytes,
    open_provider,
    publish_bytes,
    put_by_size,
    took_shm_path,
)

__all__ = [
    "SHM_THRESHOLD_BYTES",
    "PoolReport",
    "ShmProvider",
    "configure_session",
    "get_provider",
    "memlock_budget_bytes",
    "open_provider",
    "publish_bytes",
    "put_by_size",
    "took_shm_path",
]
