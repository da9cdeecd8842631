"""Shared-memory transport helpers (see :mod:`shm.provider`)."""

from shm.provider import SHM_THRESHOLD_BYTES, get_provider, publish_bytes, took_shm_path

__all__ = ["SHM_THRESHOLD_BYTES", "get_provider", "publish_bytes", "took_shm_path"]
