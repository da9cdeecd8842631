"""Shared-memory pools sized within the locked-memory limit (no Zenoh session needed)."""

from __future__ import annotations

import resource

import pytest

from shm import provider
from shm.provider import POOL_GRANULE_BYTES, fit_pool_bytes


def test_a_pool_within_the_budget_is_kept_and_one_above_it_shrinks_to_whole_granules():
    assert fit_pool_bytes(16 << 20, None) == 16 << 20
    assert fit_pool_bytes(1 << 20, 2 << 20) == 1 << 20
    shrunk = fit_pool_bytes(16 << 20, 6_700_000)
    assert shrunk <= 6_700_000 and shrunk % POOL_GRANULE_BYTES == 0
    assert shrunk > 6_700_000 - POOL_GRANULE_BYTES
    assert fit_pool_bytes(16 << 20, POOL_GRANULE_BYTES - 1) == 0


def test_the_budget_leaves_room_for_the_receivers_under_an_ordinary_users_limit(monkeypatch):
    limit = 8 << 20  # the default `ulimit -l` of an ordinary user here
    monkeypatch.setattr(resource, "getrlimit", lambda which: (limit, limit))
    monkeypatch.setattr(provider, "_status_field", {"CapEff": "0", "VmLck": "1300"}.get)
    own = provider.memlock_budget_bytes()
    assert own == limit - 1300 * 1024 - provider.MEMLOCK_MARGIN_BYTES
    shared = provider.shared_pool_budget_bytes()
    assert shared is not None
    # A receiver locks its own share plus the pool: both must fit the same limit.
    assert shared + provider.RECEIVER_LOCKED_BYTES <= limit
    assert shared <= own


@pytest.mark.parametrize("cap_eff", ["0000000000004000", "000001ffffffffff"])
def test_cap_ipc_lock_or_an_infinite_limit_means_no_bound(monkeypatch, cap_eff):
    monkeypatch.setattr(resource, "getrlimit", lambda which: (8 << 20, 8 << 20))
    monkeypatch.setattr(provider, "_status_field", {"CapEff": cap_eff, "VmLck": "0"}.get)
    assert provider.memlock_budget_bytes() is None
    monkeypatch.setattr(provider, "_status_field", {"CapEff": "0", "VmLck": "0"}.get)
    inf = resource.RLIM_INFINITY
    monkeypatch.setattr(resource, "getrlimit", lambda which: (inf, inf))
    assert provider.memlock_budget_bytes() is None


def test_a_process_mapping_several_pools_gets_a_share_of_the_budget(monkeypatch):
    limit = 8 << 20
    monkeypatch.setattr(resource, "getrlimit", lambda which: (limit, limit))
    monkeypatch.setattr(provider, "_status_field", {"CapEff": "0", "VmLck": "1300"}.get)
    one = provider.shared_pool_budget_bytes()
    three = provider.shared_pool_budget_bytes(3)
    assert one is not None and three == one // 3
    # Three pools of that size, and a receiver's own locked memory, fit the limit.
    assert 3 * three + provider.RECEIVER_LOCKED_BYTES <= limit
    with pytest.raises(ValueError):
        provider.shared_pool_budget_bytes(0)


def test_a_pool_too_small_for_the_minimum_falls_back_to_the_socket_path(monkeypatch):
    monkeypatch.setattr(provider, "shared_pool_budget_bytes", lambda pools=1: 512 * 1024)
    monkeypatch.setattr(provider, "memlock_limit_bytes", lambda: 8 << 20)
    pool, report = provider.open_provider(16 << 20, 1 << 20)
    assert pool is None and report.path == "socket" and report.pool_bytes == 0
    assert "ulimit -l" in report.reason and "socket path" in report.reason


def test_a_requested_pool_below_the_minimum_is_named_as_the_cause_not_the_limit(monkeypatch):
    monkeypatch.setattr(provider, "shared_pool_budget_bytes", lambda pools=1: 2 << 20)
    monkeypatch.setattr(provider, "memlock_limit_bytes", lambda: 8 << 20)
    pool, report = provider.open_provider(256 * 1024, 1 << 20)
    assert pool is None and report.pool_bytes == 0
    assert "ulimit -l" not in report.reason
    assert "bus.shm_pool_bytes" in report.reason and "socket path" in report.reason
