"""A service's links to its peers at start-up, over real Zenoh sessions: a peer that
comes after the service gave up waiting for it is reported as linked late, not as never
linked (a starved machine can take longer to start a service than the wait)."""

from __future__ import annotations

import threading
import time

from teleop.bus import service as service_module
from teleop.bus import session as bus
from teleop.bus.service import Service, ServiceOptions
from teleop.bus.topics import Topics
from teleop.core.config import load_config
from tests.integration.receiving import TIMEOUT_S, free_endpoint


class Probe(Service):
    name = "probe"

    def run(self, stop: threading.Event) -> None:
        stop.wait()


def test_a_peer_that_links_after_the_wait_is_linked_late_not_unlinked(monkeypatch):
    monkeypatch.setattr(service_module, "PEER_LINK_WAIT_S", 0.5)
    config = load_config(None, [f'bus.endpoint="{free_endpoint()}"', "bus.gossip=false"])
    options = ServiceOptions(listen=True, peers=("late",))
    stop = threading.Event()
    with Probe(config, options) as probe:
        assert probe.become_ready(stop)  # gave up on "late" after the wait
        assert probe.unlinked_peers == ["late"] and probe.peers_linked_late == {}
        session = bus.open_session(config.bus, listen=False)
        token = bus.declare_alive(session, Topics(config.robot.robot_id), "late")
        try:
            deadline = time.monotonic() + TIMEOUT_S
            while "late" not in probe.peers_linked_late and time.monotonic() < deadline:
                time.sleep(0.01)
            summary = probe.summary()
        finally:
            bus.close_session(session, token)
    assert summary["unlinked_peers"] == []
    assert 0.5 <= summary["peers_linked_late"]["late"] < 0.5 + TIMEOUT_S
