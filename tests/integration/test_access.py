"""Per-run credentials and access control (teleop.bus.access) on real Zenoh sessions.

A run's plant, controller and haptic service, each with its own credentials, linked as a
launcher links them; a session with no credentials tries to join. Nothing waits on a
fixed sleep: every negative check is bounded by a positive one that went through the
same links at the same time.
"""

from __future__ import annotations

import dataclasses
import json
import stat
import time
from pathlib import Path

import pytest

from teleop.bus import session as bus
from teleop.bus.access import PASSWORDS_FILE, new_zid, write_run_credentials
from teleop.bus.messages import HAPTIC_STATE, JOINT_COMMAND, PLANT_STATE, DropCounter
from teleop.bus.service import Service, ServiceOptions
from teleop.bus.topics import Topics
from teleop.core.config import BusConfig, load_config
from tests.integration.receiving import TIMEOUT_S, Seen, free_endpoint

ROBOT = "testarm"
RECORDS = 300  # per sender: enough for any link to carry some if it is up


def test_only_the_graphs_producers_reach_a_stream_and_strangers_cannot_link(tmp_path):
    files = write_run_credentials(tmp_path / "auth", ["plant", "controller", "haptic"], (ROBOT,))
    assert stat.S_IMODE((tmp_path / "auth").stat().st_mode) == 0o700
    assert stat.S_IMODE((tmp_path / "auth" / PASSWORDS_FILE).stat().st_mode) == 0o600
    assert all(stat.S_IMODE(path.stat().st_mode) == 0o600 for path in files.values())

    topics = Topics(ROBOT)
    endpoint = free_endpoint()
    own = {name: free_endpoint() for name in ("controller", "haptic", "stranger")}

    def config(name: str, credentials: bool = True) -> BusConfig:
        # as a launcher's mesh: each pair links once (the plant listens on `endpoint`)
        connect = [own["controller"]] if name in ("haptic", "stranger") else []
        return dataclasses.replace(
            BusConfig(endpoint=endpoint),
            gossip=False,
            peer_listen_endpoint=own.get(name, ""),
            peer_connect_endpoints=tuple(connect),
            credentials_file=str(files[name]) if credentials else "",
        )

    drops = DropCounter()
    plant = bus.open_session(config("plant"), listen=True)
    controller = bus.open_session(config("controller"), listen=False)
    haptic = bus.open_session(config("haptic"), listen=False)
    stranger = bus.open_session(config("stranger", credentials=False), listen=False)
    commands, states_at_controller, states_at_stranger = Seen(), Seen(), Seen()
    haptic_at_controller = Seen()
    entities: list[object] = [
        bus.subscribe(plant, topics.joint_command, JOINT_COMMAND, commands, drops),
        bus.subscribe(controller, topics.plant_state, PLANT_STATE, states_at_controller, drops),
        bus.subscribe(controller, topics.haptic_state, HAPTIC_STATE, haptic_at_controller, drops),
        bus.subscribe(stranger, topics.plant_state, PLANT_STATE, states_at_stranger, drops),
    ]
    try:
        for name, session in (("plant", plant), ("controller", controller), ("haptic", haptic)):
            entities.append(bus.declare_alive(session, topics, name))
        bus.wait_alive(plant, topics, ["controller", "haptic"], TIMEOUT_S)
        bus.wait_alive(controller, topics, ["plant", "haptic"], TIMEOUT_S)
        publishers = {
            "state": bus.Publisher.declare(plant, topics.plant_state, PLANT_STATE),
            "command": bus.Publisher.declare(controller, topics.joint_command, JOINT_COMMAND),
            "haptic": bus.Publisher.declare(haptic, topics.haptic_state, HAPTIC_STATE),
            # the haptic service and a stranger posing as the controller
            "haptic_command": bus.Publisher.declare(haptic, topics.joint_command, JOINT_COMMAND),
            "stranger_command": bus.Publisher.declare(
                stranger, topics.joint_command, JOINT_COMMAND
            ),
            "stranger_state": bus.Publisher.declare(stranger, topics.plant_state, PLANT_STATE),
        }
        entities += publishers.values()
        # seq ranges tell the senders apart: 1.. real, 10_000.. haptic, 20_000.. stranger
        first = {"haptic_command": 10_000, "stranger_command": 20_000, "stranger_state": 20_000}
        for i in range(1, RECORDS + 1):
            for name, pub in publishers.items():
                rec = pub.schema.new()
                rec["seq"] = first.get(name, 0) + i
                pub.put(rec)
        assert commands.wait(RECORDS), "the controller's commands did not reach the plant"
        assert states_at_controller.wait(RECORDS), "the plant's states did not reach the controller"
        assert haptic_at_controller.wait(RECORDS), "the haptic samples did not reach the controller"
    finally:
        for session in (stranger, haptic, controller, plant):
            bus.close_session(session)  # its publishers, subscribers and tokens with it
    assert sorted(commands.seqs) == list(range(1, RECORDS + 1))  # none from haptic or stranger
    assert max(states_at_controller.seqs) <= RECORDS  # no state from the stranger
    # the stranger never linked: it saw its own states only (Zenoh delivers those locally)
    assert [seq for seq in states_at_stranger.seqs if seq <= RECORDS] == []


def test_without_tls_the_controllers_password_with_another_id_gets_no_right(tmp_path):
    """A thief with the controller's user and password (accepted: the plant holds the
    run's dictionary) but a Zenoh id of its own matches no participant: none of its
    commands reaches the plant, while the controller's, sent in the same loop, all do."""
    files = write_run_credentials(tmp_path / "auth", ["plant", "controller"], (ROBOT,))
    thief_file = tmp_path / "thief.json"
    stolen = json.loads(files["controller"].read_text())
    thief_file.write_text(json.dumps({**stolen, "zid": new_zid()}))
    topics, endpoint = Topics(ROBOT), free_endpoint()

    def config(credentials: Path) -> BusConfig:
        return dataclasses.replace(
            BusConfig(endpoint=endpoint), gossip=False, credentials_file=str(credentials)
        )

    plant = bus.open_session(config(files["plant"]), listen=True)
    controller = bus.open_session(config(files["controller"]), listen=False)
    thief = bus.open_session(config(thief_file), listen=False)
    commands = Seen()
    entities = [bus.subscribe(plant, topics.joint_command, JOINT_COMMAND, commands, DropCounter())]
    try:
        entities.append(bus.declare_alive(controller, topics, "controller"))
        entities.append(bus.declare_alive(plant, topics, "plant"))
        bus.wait_alive(plant, topics, ["controller"], TIMEOUT_S)
        bus.wait_alive(controller, topics, ["plant"], TIMEOUT_S)
        plant_zid = str(plant.info.zid())
        deadline = time.monotonic() + TIMEOUT_S
        while plant_zid not in {str(z) for z in thief.info.peers_zid()}:
            assert time.monotonic() < deadline, "the thief's password did not link"
            time.sleep(0.01)
        senders = [
            (0, bus.Publisher.declare(controller, topics.joint_command, JOINT_COMMAND)),
            (20_000, bus.Publisher.declare(thief, topics.joint_command, JOINT_COMMAND)),
        ]
        for i in range(1, RECORDS + 1):
            for first, pub in senders:
                rec = pub.schema.new()
                rec["seq"] = first + i
                pub.put(rec)
        assert commands.wait(RECORDS), "the controller's commands did not reach the plant"
    finally:
        for session in (thief, controller, plant):
            bus.close_session(session)
    assert sorted(commands.seqs) == list(range(1, RECORDS + 1))  # none from the thief


def test_a_robots_controller_commands_its_own_robot_only(tmp_path):
    """Two robots on one bus: each robot's plant takes the commands of its own robot's
    controller. arm1's controller publishing on arm0's command key (a mistake, or a
    compromised process) reaches no one, while its commands to arm1, sent in the same
    loop, all arrive."""
    robots = ("arm0", "arm1")
    names = ["plant-arm0", "plant-arm1", "controller-arm1"]
    files = write_run_credentials(tmp_path / "auth", names, robots)
    arm0, arm1 = Topics("arm0"), Topics("arm1")
    endpoint = free_endpoint()
    own = {name: free_endpoint() for name in names[1:]}

    def config(name: str) -> BusConfig:
        before = [own[n] for n in names[1 : names.index(name)]]
        return dataclasses.replace(
            BusConfig(endpoint=endpoint),
            gossip=False,
            peer_listen_endpoint=own.get(name, ""),
            peer_connect_endpoints=tuple(before),
            credentials_file=str(files[name]),
        )

    drops = DropCounter()
    plant0 = bus.open_session(config("plant-arm0"), listen=True)
    plant1 = bus.open_session(config("plant-arm1"), listen=False)
    controller1 = bus.open_session(config("controller-arm1"), listen=False)
    at_arm0, at_arm1 = Seen(), Seen()
    entities: list[object] = [
        bus.subscribe(plant0, arm0.joint_command, JOINT_COMMAND, at_arm0, drops),
        bus.subscribe(plant1, arm1.joint_command, JOINT_COMMAND, at_arm1, drops),
        bus.declare_alive(plant0, arm0, "plant"),
        bus.declare_alive(plant1, arm1, "plant"),
        bus.declare_alive(controller1, arm1, "controller"),
    ]
    try:
        bus.wait_alive(controller1, arm1, ["plant"], TIMEOUT_S)
        bus.wait_alive(plant0, arm1, ["plant", "controller"], TIMEOUT_S)
        own_robot = bus.Publisher.declare(controller1, arm1.joint_command, JOINT_COMMAND)
        other_robot = bus.Publisher.declare(controller1, arm0.joint_command, JOINT_COMMAND)
        entities += [own_robot, other_robot]
        for i in range(1, RECORDS + 1):
            for pub in (own_robot, other_robot):
                rec = pub.schema.new()
                rec["seq"] = i
                pub.put(rec)
        assert at_arm1.wait(RECORDS), "arm1's controller's commands did not reach arm1's plant"
    finally:
        for session in (controller1, plant1, plant0):
            bus.close_session(session)
    assert at_arm0.seqs == []


@pytest.mark.parametrize("tls", [False, True], ids=["password", "tls"])
def test_a_stranger_linked_for_a_moment_is_reported_all_the_same(tmp_path, tls):
    """A session that is no participant (the controller's password, or certificate,
    under an id of its own) links to a running service and leaves within a few
    milliseconds, long before the service's next running summary: the service lists it
    all the same, as the link opens (Zenoh's transport events)."""
    files = write_run_credentials(tmp_path / "auth", ["plant", "controller"], (ROBOT,), tls=tls)
    thief_file = tmp_path / "thief.json"
    thief_zid = new_zid()
    stolen = json.loads(files["controller"].read_text())
    thief_file.write_text(json.dumps({**stolen, "zid": thief_zid}))
    endpoint = free_endpoint("tls" if tls else "tcp")
    config = load_config(
        None,
        [f'bus.endpoint="{endpoint}"', f"bus.tls={str(tls).lower()}", "bus.gossip=false",
         f'bus.credentials_file="{files["plant"]}"', f'robot.robot_id="{ROBOT}"'],
    )  # fmt: skip

    class Watching(Service):
        name = "plant"

    service = Watching(config, ServiceOptions(listen=True))
    service.open()
    try:
        thief_config = dataclasses.replace(
            config.bus, credentials_file=str(thief_file), peer_connect_endpoints=()
        )
        thief = bus.open_session(thief_config, listen=False)
        deadline = time.monotonic() + TIMEOUT_S
        while not thief.info.peers_zid():
            assert time.monotonic() < deadline, "the thief's password did not link"
            time.sleep(0.001)
        bus.close_session(thief)
        while thief_zid.lower() not in [z.lower() for z in service.unknown_peers]:
            assert time.monotonic() < deadline, "the stranger went unreported"
            time.sleep(0.01)
    finally:
        service.close()
