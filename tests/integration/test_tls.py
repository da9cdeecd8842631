"""Mutual TLS between a run's processes (bus.tls: teleop.bus.tls, teleop.bus.access) on
real Zenoh sessions linked as a launcher links them, over tls/ endpoints.

As in test_access.py, nothing waits on a fixed sleep: a negative check is bounded by a
positive one that went through the same links at the same time.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from teleop.bus import session as bus
from teleop.bus.access import new_zid, participant_zids, strangers, write_run_credentials
from teleop.bus.messages import HAPTIC_STATE, JOINT_COMMAND, PLANT_STATE, DropCounter
from teleop.bus.topics import Topics
from teleop.core.config import BusConfig, ConfigError
from tests.integration.receiving import TIMEOUT_S, Seen, free_endpoint

ROBOT = "testarm"
RECORDS = 300  # per sender: enough for any link to carry some if it is up
PARTICIPANTS = ["plant", "controller", "haptic"]


def edit_credentials(path: Path, edit: Callable[[dict], None]) -> None:
    content = json.loads(path.read_text())
    edit(content)
    path.write_text(json.dumps(content))


class Run:
    """The plant (the run's listener), the controller and the haptic service, each with
    its credentials file, linked as a launcher's mesh links them; the plant's states,
    the controller's commands and the haptic samples sent :data:`RECORDS` times."""

    def __init__(self, files: dict[str, Path]) -> None:
        self.topics = Topics(ROBOT)
        self.endpoint = endpoint = free_endpoint("tls")
        own = {"controller": free_endpoint("tls"), "haptic": free_endpoint("tls")}

        def config(name: str) -> BusConfig:
            return dataclasses.replace(
                BusConfig(endpoint=endpoint),
                gossip=False,
                peer_listen_endpoint=own.get(name, ""),
                peer_connect_endpoints=(own["controller"],) if name == "haptic" else (),
                credentials_file=str(files[name]),
            )

        self.plant = bus.open_session(config("plant"), listen=True)
        self.controller = bus.open_session(config("controller"), listen=False)
        self.haptic = bus.open_session(config("haptic"), listen=False)
        self.commands, self.states, self.haptic_samples = Seen(), Seen(), Seen()
        self._publishers: list[tuple[int, bus.Publisher]] = []
        drops, topics = DropCounter(), self.topics
        self.entities = [
            bus.subscribe(self.plant, topics.joint_command, JOINT_COMMAND, self.commands, drops),
            bus.subscribe(self.controller, topics.plant_state, PLANT_STATE, self.states, drops),
            bus.subscribe(
                self.controller, topics.haptic_state, HAPTIC_STATE, self.haptic_samples, drops
            ),
        ]

    def link(self, linked: list[str]) -> None:
        """Declare every participant's token and wait until each of ``linked`` sees the
        others of ``linked``: their subscriptions have reached each other by then."""
        sessions = {"plant": self.plant, "controller": self.controller, "haptic": self.haptic}
        for name, session in sessions.items():
            self.entities.append(bus.declare_alive(session, self.topics, name))
        for name in linked:
            others = [other for other in linked if other != name]
            bus.wait_alive(sessions[name], self.topics, others, TIMEOUT_S)

    def send(self) -> None:
        """Every participant's records; the haptic service also sends commands (seq
        10_000..), which only the controller may."""
        for i in range(1, RECORDS + 1):
            self.send_once(i)

    def send_once(self, i: int) -> None:
        """The ``i``-th record of each sender of :meth:`send`."""
        if not self._publishers:
            topics = self.topics
            self._publishers = [
                (0, bus.Publisher.declare(self.plant, topics.plant_state, PLANT_STATE)),
                (0, bus.Publisher.declare(self.controller, topics.joint_command, JOINT_COMMAND)),
                (0, bus.Publisher.declare(self.haptic, topics.haptic_state, HAPTIC_STATE)),
                (10_000, bus.Publisher.declare(self.haptic, topics.joint_command, JOINT_COMMAND)),
            ]
        for first, pub in self._publishers:
            rec = pub.schema.new()
            rec["seq"] = first + i
            pub.put(rec)

    def close(self) -> None:
        for session in (self.haptic, self.controller, self.plant):
            bus.close_session(session)


@pytest.mark.parametrize("haptic_ca", ["own", "another"])
def test_only_certificates_of_the_runs_authority_link(tmp_path, haptic_ca):
    """The haptic service holds this run's Zenoh id; only its certificate differs: signed
    by this run's authority, it links and its samples reach the controller; signed by
    another run's, it links to nobody."""
    files = write_run_credentials(tmp_path / "auth", PARTICIPANTS, (ROBOT,), tls=True)
    if haptic_ca == "another":
        other = write_run_credentials(tmp_path / "other", ["haptic"], (ROBOT,), tls=True)
        foreign_tls = json.loads(other["haptic"].read_text())["tls"]
        edit_credentials(files["haptic"], lambda content: content.update(tls=foreign_tls))
    run = Run(files)
    try:
        run.link(PARTICIPANTS if haptic_ca == "own" else ["plant", "controller"])
        run.send()
        assert run.commands.wait(RECORDS), "the controller's commands did not reach the plant"
        assert run.states.wait(RECORDS), "the plant's states did not reach the controller"
        if haptic_ca == "own":
            assert run.haptic_samples.wait(RECORDS)
            assert len(run.haptic.info.peers_zid()) == 2
        else:
            assert run.haptic.info.peers_zid() == []
    finally:
        run.close()
    assert sorted(run.commands.seqs) == list(range(1, RECORDS + 1))  # none from the haptic
    if haptic_ca == "another":
        assert run.haptic_samples.seqs == []


@pytest.mark.parametrize("borrowed", ["controller", "observer"])
def test_a_second_session_with_a_borrowed_certificate_gets_no_right(tmp_path, borrowed):
    """A thief holding the controller's (or the observer's) certificate and key, with a
    Zenoh id of its own, links to the plant (TLS accepts the certificate) but matches no
    participant of the access list: not one of its commands reaches the plant, while the
    real controller's, sent in the same loop, all do."""
    files = write_run_credentials(
        tmp_path / "auth", [*PARTICIPANTS, "observer"], (ROBOT,), tls=True
    )
    stolen = json.loads(files[borrowed].read_text())
    thief_file = tmp_path / "thief.json"
    thief_zid = new_zid()
    thief_file.write_text(json.dumps({**stolen, "zid": thief_zid}))
    run = Run(files)
    plant_zid = json.loads(files["plant"].read_text())["zid"]
    thief = bus.open_session(
        dataclasses.replace(
            BusConfig(endpoint=run.endpoint), gossip=False, credentials_file=str(thief_file)
        ),
        listen=False,
    )
    try:
        run.link(PARTICIPANTS)
        deadline = time.monotonic() + TIMEOUT_S
        while plant_zid not in {str(z) for z in thief.info.peers_zid()}:
            assert time.monotonic() < deadline, "the thief's certificate did not link"
            time.sleep(0.01)
        thief_commands = bus.Publisher.declare(thief, run.topics.joint_command, JOINT_COMMAND)
        for i in range(1, RECORDS + 1):
            rec = thief_commands.schema.new()
            rec["seq"] = 20_000 + i
            thief_commands.put(rec)
            run.send_once(i)
        assert run.commands.wait(RECORDS), "the controller's commands did not reach the plant"
        # the plant knows it for no participant of the run (a service logs and counts it)
        participants = participant_zids(files["plant"])
        assert strangers(run.plant.info.peers_zid(), participants) == [thief_zid]
        assert strangers(run.controller.info.peers_zid(), participants) == []
    finally:
        bus.close_session(thief)
        run.close()
    assert sorted(run.commands.seqs) == list(range(1, RECORDS + 1))  # none from the thief


def test_a_process_holding_certificates_refuses_a_tcp_endpoint(tmp_path):
    files = write_run_credentials(tmp_path / "auth", ["plant"], (ROBOT,), tls=True)
    config = BusConfig(endpoint=free_endpoint("tcp"), credentials_file=str(files["plant"]))
    with pytest.raises(ConfigError, match="must be tls/HOST:PORT, not tcp/127.0.0.1"):
        bus.open_session(config, listen=True)
