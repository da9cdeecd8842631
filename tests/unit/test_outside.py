"""A service left out of the stack: its Zenoh config, its instructions, the checks."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh

from teleop import cli
from teleop.bus import graph
from teleop.bus.access import LAUNCHER, OBSERVER
from teleop.bus.messages import PROTOCOL_VERSION
from teleop.bus.session import session_config
from teleop.core.config import SCENARIOS, ConfigError, load_config
from teleop.core.net import LoopbackPorts
from teleop.run import outside
from teleop.run.stack import Launch, StackServices, _plant_awaits, peer_mesh, plan_stack
from teleop.run.supervise import Stack

PROTOCOL_DOC = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"
JOIN_BEGIN, JOIN_END = "<!-- join_tables() begin -->", "<!-- join_tables() end -->"


def test_without_names_only_services_of_the_stack_in_stack_order():
    stack = ("plant", "controller", "recorder")
    assert outside.check_without(stack, ["recorder", "controller"]) == ("controller", "recorder")
    with pytest.raises(ConfigError, match="--without haptic: not a service of this stack"):
        outside.check_without(stack, ["haptic"])


def test_the_outside_config_is_the_stacks_own_session_config(tmp_path):
    with LoopbackPorts() as ports:
        mesh = peer_mesh(["plant", "recorder", "controller"], None, ports)
    overrides = ['bus.endpoint="tcp/127.0.0.1:7000"', 'robot.robot_id="arm7"', *mesh["controller"]]
    config = load_config(None, overrides)
    path = outside.write_outside_config(tmp_path, "controller", config)
    assert path == tmp_path / "outside" / "controller.json5"
    assert path.stat().st_mode & 0o777 == 0o600
    loaded = json.loads(str(zenoh.Config.from_file(str(path))))
    # The robot id is in the file, where Zenoh takes it (metadata: not interpreted).
    assert loaded.pop("metadata") == {
        "robot_id": "arm7",
        "service": "controller",
        "loop_rate_hz": config.loop.rate_hz,
        "protocol_version": PROTOCOL_VERSION,
    }
    assert "// Robot id: arm7 " in path.read_text()
    own_session = json.loads(str(session_config(config.bus, listen=False)))
    assert own_session.pop("metadata") is None  # Zenoh's default: nothing
    assert loaded == own_session
    assert loaded["mode"] == "peer"
    assert loaded["scouting"]["gossip"]["enabled"] is False
    assert loaded["scouting"]["multicast"]["enabled"] is False
    assert loaded["listen"]["endpoints"] == [config.bus.peer_listen_endpoint]
    # The listener and every service before it in the mesh: a link to each of them.
    assert len(loaded["connect"]["endpoints"]) == 3
    # Low latency goes with shared memory, which an ordinary user's process may not have
    # room to lock (shm.configure_session).
    shm_on = loaded["transport"]["shared_memory"]["enabled"]
    assert loaded["transport"]["unicast"]["lowlatency"] == (config.bus.lowlatency and shm_on)


def test_join_instructions_name_the_tokens_and_the_scenarios_streams(tmp_path):
    config = load_config(None, ['run.scenario="path-following"'])
    text = outside.join_instructions(
        "controller", config, tmp_path / "c.json5", ("plant", "controller", "recorder"),
        timeout_s=5,
    )  # fmt: skip
    assert "teleop/arm0/alive/controller" in text and "teleop/arm0/ready/controller" in text
    assert "alive tokens of: plant, recorder" in text
    assert "robot id:      arm0" in text
    assert "teleop/arm0/cmd/joint_velocity" in text and "teleop/arm0/state/plant" in text
    assert "haptic/state" not in text  # a stream of the grasp scenario only


def test_the_cli_default_timeout_is_the_launchers():
    assert cli.DEFAULT_WITHOUT_TIMEOUT_S == outside.DEFAULT_WITHOUT_TIMEOUT_S


def test_the_tokens_each_service_awaits_are_the_launchers_and_in_the_doc():
    """The launcher's lists (the plant's --await, the join instructions) are the rule of
    tokens_to_await, whose table docs/protocol.md embeds between markers."""
    for scenario in SCENARIOS:
        stack = graph.scenario_services(scenario)
        for launcher, extra in ((True, (LAUNCHER,)), (False, ())):
            ready = outside.tokens_to_await("plant", stack, launcher=launcher)[1]
            assert list(ready) == _plant_awaits(stack, *extra)
        config = load_config(None, [f'run.scenario="{scenario}"'])
        for service in stack:
            alive, ready = outside.tokens_to_await(service, stack, launcher=True)
            assert set(alive) == set(stack) - {service}
            assert bool(ready) == (service == "plant")
            text = outside.join_instructions(
                service, config, Path("x.json5"), stack, awaits=ready, timeout_s=1
            )
            assert f"alive tokens of: {', '.join(alive)})" in text
    text = PROTOCOL_DOC.read_text()
    embedded = text[text.index(JOIN_BEGIN) + len(JOIN_BEGIN) : text.index(JOIN_END)]
    assert embedded.strip() == outside.join_tables().strip(), (
        "docs/protocol.md is stale: paste `python -m teleop.run.outside` between the markers"
    )


def _stack_dir(tmp_path, *, launch, secure):
    """A run directory as a launcher leaves it (teleop.run.stack.plan_stack, the one
    launch recipe): credentials, supervisord.conf (rendered, not started) and the config
    of an outside controller. The stack's own listen endpoints, in mesh order."""
    sets = ['robot.robot_id="arm3"', "bus.shm=false", 'run.mode="lockstep"', "bus.tls=false",
            f"bus.secure={str(secure).lower()}"]  # fmt: skip
    config = load_config(None, sets)
    layout = StackServices.of(config, ["controller"])
    with LoopbackPorts() as ports:
        plan = plan_stack(
            launch, config, None, sets, tmp_path, ports, layout, endpoint="tcp/127.0.0.1:7000"
        )
    assert plan.credentials is None or (LAUNCHER in plan.credentials) == (launch is Launch.RUN)
    Stack(tmp_path, plan.programs).conf_path.write_text(Stack(tmp_path, plan.programs).render())
    assert (tmp_path / "outside" / "controller.json5").is_file()
    return [e.split("=", 1)[1].strip('"') for m in plan.mesh.values() for e in m if "listen_" in e]


@pytest.mark.parametrize("launch", [Launch.RUN, Launch.UP])
def test_an_observer_finds_every_endpoint_of_a_stack_from_its_run_dir(tmp_path, launch):
    own = _stack_dir(tmp_path, launch=launch, secure=True)
    assert outside.stack_endpoints(tmp_path) == ("tcp/127.0.0.1:7000", tuple(own))
    path = outside.write_observer_config(tmp_path)
    assert path == tmp_path / "outside" / "observer.json5"
    loaded = json.loads(str(zenoh.Config.from_file(str(path))))
    assert loaded["metadata"] == {
        "robot_id": "arm3",
        "service": OBSERVER,
        "loop_rate_hz": load_config().loop.rate_hz,
        "protocol_version": PROTOCOL_VERSION,
    }
    assert loaded["connect"]["endpoints"] == ["tcp/127.0.0.1:7000", *own]
    assert loaded["listen"]["endpoints"] not in ([], own)  # a port of its own choice
    assert loaded["transport"]["shared_memory"]["enabled"] is False  # the run's settings
    observer = json.loads((tmp_path / "auth" / "observer.json").read_text())
    assert loaded["id"] == observer["zid"]
    assert loaded["transport"]["auth"]["usrpwd"]["user"] == observer["user"]
    # The stack's own file is not taken for the observer's next time.
    assert outside.stack_endpoints(tmp_path)[1] == tuple(own)


def test_an_open_bus_gives_the_observer_no_credentials(tmp_path):
    _stack_dir(tmp_path, launch=Launch.RUN, secure=False)
    config = outside.observer_config(tmp_path)
    assert config.bus.credentials_file == ""
    with pytest.raises(FileNotFoundError, match="no stack was started"):
        outside.stack_endpoints(tmp_path / "nothing")
