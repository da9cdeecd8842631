"""Two sites' routers (services/router.py's config, teleop.bus.session.router_config)
between real Zenoh sessions on loopback, with the run's certificates and access list as
the robot site's launcher writes them: what one site publishes reaches the other through
both routers, a site's peer still sends only its own streams, and a session that is no
participant gets no link at the router.

As in test_tls.py, a negative check is bounded by a positive one that went through the
same links at the same time.
"""

from __future__ import annotations

import dataclasses
import time

import zenoh

from teleop.bus import graph
from teleop.bus import session as bus
from teleop.bus.access import write_run_credentials
from teleop.bus.messages import (
    HAPTIC_STATE,
    JOINT_COMMAND,
    PLANT_STATE,
    RUN_EVENT,
    DropCounter,
    Event,
)
from teleop.bus.topics import Topics
from teleop.core.config import OPERATOR_SITE, ROBOT_SITE, BusConfig, SiteConfig
from tests.integration.receiving import TIMEOUT_S, Seen, free_endpoint

ROBOT = "testarm"
RECORDS = 200
ROBOT_ROUTER, OPERATOR_ROUTER = graph.router_name(ROBOT_SITE), graph.router_name(OPERATOR_SITE)
PARTICIPANTS = ["plant", "controller", "haptic", ROBOT_ROUTER, OPERATOR_ROUTER]


class Sites:
    """Robot site: the plant (its mesh's listener), the controller and their router,
    which listens for the other site; operator site: its router (its mesh's listener),
    which connects to the robot site's, and the haptic service."""

    def __init__(self, files: dict, site_endpoint: str) -> None:
        self.topics = Topics(ROBOT)
        robot_mesh, operator_mesh = free_endpoint("tls"), free_endpoint("tls")
        controller_own = free_endpoint("tls")

        def config(name: str, endpoint: str, own: str = "", peers: tuple = ()) -> BusConfig:
            return dataclasses.replace(
                BusConfig(endpoint=endpoint),
                gossip=False,
                peer_listen_endpoint=own,
                peer_connect_endpoints=peers,
                credentials_file=str(files[name]),
            )

        self.plant = bus.open_session(config("plant", robot_mesh), listen=True)
        self.controller = bus.open_session(
            config("controller", robot_mesh, controller_own), listen=False
        )
        robot_router = config(ROBOT_ROUTER, robot_mesh, free_endpoint("tls"), (controller_own,))
        self.robot_router = zenoh.open(
            bus.router_config(
                robot_router, SiteConfig(ROBOT_SITE, listen=site_endpoint), listen=False
            )
        )
        self._operator_router_config = bus.router_config(
            config(OPERATOR_ROUTER, operator_mesh),
            SiteConfig(OPERATOR_SITE, connect=site_endpoint),
            listen=True,
        )
        self.open_operator_router()
        self.haptic = bus.open_session(
            config("haptic", operator_mesh, free_endpoint("tls")), listen=False
        )
        self.states, self.samples, self.commands = Seen(), Seen(), Seen()
        drops, topics = DropCounter(), self.topics
        self.entities = [
            bus.subscribe(self.controller, topics.haptic_state, HAPTIC_STATE, self.samples, drops),
            bus.subscribe(self.plant, topics.joint_command, JOINT_COMMAND, self.commands, drops),
            bus.subscribe(self.haptic, topics.plant_state, PLANT_STATE, self.states, drops),
        ]
        self.entities += [
            bus.declare_alive(session, topics, name)
            for name, session in (
                ("plant", self.plant),
                ("controller", self.controller),
                ("haptic", self.haptic),
            )
        ]

    def open_operator_router(self) -> None:
        """The operator site's router (again: after :meth:`drop_operator_router`)."""
        self.operator_router = zenoh.open(self._operator_router_config)

    def drop_operator_router(self) -> None:
        """The operator site's router gone: what it held is lost, the sites unlinked."""
        self.operator_router.close()

    def link(self) -> None:
        """Each end sees the other's token: through both routers, subscriptions included."""
        bus.wait_alive(self.plant, self.topics, ["haptic"], TIMEOUT_S)
        bus.wait_alive(self.controller, self.topics, ["haptic"], TIMEOUT_S)
        bus.wait_alive(self.haptic, self.topics, ["plant", "controller"], TIMEOUT_S)

    def close(self) -> None:
        for entity in self.entities:
            entity.undeclare()
        sessions = (self.haptic, self.operator_router, self.robot_router, self.controller)
        for session in (*sessions, self.plant):
            session.close()


def _send(publisher: bus.Publisher, first_seq: int) -> None:
    for i in range(1, RECORDS + 1):
        rec = publisher.schema.new()
        rec["seq"] = first_seq + i
        publisher.put(rec)


def test_streams_cross_both_routers_and_a_peer_still_sends_only_its_own(tmp_path):
    endpoint = free_endpoint("tls")
    files = write_run_credentials(tmp_path / "auth", PARTICIPANTS, (ROBOT,), tls=True)
    sites = Sites(files, endpoint)
    try:
        sites.link()
        topics = sites.topics
        _send(bus.Publisher.declare(sites.plant, topics.plant_state, PLANT_STATE), 0)
        _send(bus.Publisher.declare(sites.haptic, topics.haptic_state, HAPTIC_STATE), 0)
        # Not the haptic service's to send: its own site's router refuses it.
        _send(bus.Publisher.declare(sites.haptic, topics.joint_command, JOINT_COMMAND), 0)
        assert sites.states.wait(RECORDS), "the plant's states did not reach the other site"
        assert sites.samples.wait(RECORDS), "the haptic samples did not reach the robot site"
        assert [str(z) for z in sites.operator_router.info.routers_zid()]  # linked routers
        assert sites.controller.info.routers_zid() and sites.haptic.info.routers_zid()
    finally:
        sites.close()
    assert sites.states.seqs == list(range(1, RECORDS + 1))  # each once, in order
    assert sites.samples.seqs == list(range(1, RECORDS + 1))
    assert sites.commands.seqs == []


def test_a_session_of_another_run_gets_no_link_at_the_routers(tmp_path):
    """A stranger holding a certificate and id of another run (its own authority, a
    participant's name) dials the robot router's site endpoint while the sites carry
    records: no link, nothing received."""
    endpoint = free_endpoint("tls")
    files = write_run_credentials(tmp_path / "auth", PARTICIPANTS, (ROBOT,), tls=True)
    other = write_run_credentials(tmp_path / "other", [OPERATOR_ROUTER], (ROBOT,), tls=True)
    sites = Sites(files, endpoint)
    stranger_bus = dataclasses.replace(
        BusConfig(endpoint=endpoint), gossip=False, credentials_file=str(other[OPERATOR_ROUTER])
    )
    stranger = bus.open_session(stranger_bus, listen=False)
    seen = Seen()
    drops = DropCounter()
    watch = bus.subscribe(stranger, sites.topics.plant_state, PLANT_STATE, seen, drops)
    try:
        sites.link()
        deadline = time.monotonic() + 1.0  # the stranger keeps retrying meanwhile
        publisher = bus.Publisher.declare(sites.plant, sites.topics.plant_state, PLANT_STATE)
        while time.monotonic() < deadline:
            _send(publisher, 0)
        assert sites.states.wait(RECORDS)
        assert list(stranger.info.routers_zid()) == [] and list(stranger.info.peers_zid()) == []
    finally:
        watch.undeclare()
        stranger.close()
        sites.close()
    assert seen.seqs == []


def test_a_recovered_stream_loses_no_record_while_a_router_is_away(tmp_path):
    """The plant's events (graph: recovered) and its states (not: the loop sends its own
    again) from the robot site to the operator site, the operator site's router gone
    for a while and back: the states sent meanwhile are lost, every event comes, in
    order, asked for from the plant's cache once the routers linked again (zenoh-ext's
    recovery, under the run's access list)."""
    endpoint = free_endpoint("tls")
    files = write_run_credentials(tmp_path / "auth", PARTICIPANTS, (ROBOT,), tls=True)
    sites = Sites(files, endpoint)
    events, drops = Seen(), DropCounter()
    topics = sites.topics
    recovering = bus.subscribe(
        sites.haptic, topics.plant_events, RUN_EVENT, events, drops, recovery=True
    )
    try:
        sites.link()
        states = bus.Publisher.for_stream(sites.plant, topics, "plant_state", recovery=True)
        cached = bus.Publisher.for_stream(sites.plant, topics, "plant_events", recovery=True)
        assert states.key == topics.plant_state and cached.key == topics.plant_events
        seq = 0
        for away in (False, True, False):
            if away:
                # Nothing in flight when the router goes: a record put just before could
                # be lost with it, and only those sent while it is away are to be.
                assert sites.states.wait(seq) and events.wait(seq)
                sites.drop_operator_router()
            for _ in range(RECORDS // 4):
                seq += 1
                for publisher in (states, cached):
                    rec = publisher.schema.new()
                    rec["seq"] = seq
                    if publisher is cached:
                        rec["event"] = Event.PHASE
                    publisher.put(rec)
                time.sleep(0.002)
            if away:
                sites.open_operator_router()
                sites.link()
        assert events.wait(seq), f"events: {len(events.seqs)} of {seq}"
        assert sites.states.wait_seq(seq)  # the last state, sent once the routers linked
    finally:
        recovering.undeclare()
        sites.close()
    assert events.seqs == list(range(1, seq + 1))  # each once, in order
    lost = sorted(set(range(1, seq + 1)) - set(sites.states.seqs))
    assert lost and all(seq // 3 < s <= 2 * seq // 3 for s in lost)  # sent while away
