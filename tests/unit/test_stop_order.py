"""Which programs a stopping stack tells at once and which it stops after them."""

from __future__ import annotations

from teleop.bus.graph import ROUTERS
from teleop.run.stack import IDLE_POLL_PRIORITY, PRIORITY
from teleop.run.supervise import STOP_AT_ONCE_MIN_PRIORITY


def test_the_recorder_and_the_pollers_stop_after_every_producer():
    producers = {name: p for name, p in PRIORITY.items() if name not in ("recorder", *ROUTERS)}
    assert min(producers.values()) >= STOP_AT_ONCE_MIN_PRIORITY
    assert PRIORITY["recorder"] < STOP_AT_ONCE_MIN_PRIORITY
    assert IDLE_POLL_PRIORITY < PRIORITY["recorder"]


def test_a_sites_router_starts_first_and_stops_after_the_recorder_it_feeds():
    for router in ROUTERS:
        assert IDLE_POLL_PRIORITY < PRIORITY[router] < PRIORITY["recorder"]
