"""Shared-memory transport helpers (see :mod:`shm.provider`)."""

from shm.provider import (
    POOL_GRANULE_BYTES,
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
    "POOL_GRANULE_BYTES",
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
