"""A service left out of the stack: its Zenoh config, its instructions, the checks."""

from __future__ import annotations

import json

import pytest
import zenoh

from teleop import cli
from teleop.bus.session import session_config
from teleop.core.config import ConfigError, load_config
from teleop.core.net import LoopbackPorts
from teleop.run import outside
from teleop.run.stack import peer_mesh


def test_without_names_only_services_of_the_stack_in_stack_order():
    stack = ("plant", "controller", "recorder")
    assert outside.check_without(stack, ["recorder", "controller"]) == ("controller", "recorder")
    with pytest.raises(ConfigError, match="--without haptic: not a service of this stack"):
        outside.check_without(stack, ["haptic"])


def test_the_outside_config_is_the_stacks_own_session_config(tmp_path):
    with LoopbackPorts() as ports:
        mesh = peer_mesh(["plant", "recorder", "controller"], None, ports)
    config = load_config(None, ['bus.endpoint="tcp/127.0.0.1:7000"', *mesh["controller"]])
    path = outside.write_outside_config(tmp_path, "controller", config.bus)
    assert path == tmp_path / "outside" / "controller.json5"
    assert path.stat().st_mode & 0o777 == 0o600
    loaded = json.loads(str(zenoh.Config.from_file(str(path))))
    assert loaded == json.loads(str(session_config(config.bus, listen=False)))
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
    assert "teleop/arm0/cmd/joint_velocity" in text and "teleop/arm0/state/plant" in text
    assert "haptic/state" not in text  # a stream of the grasp scenario only


def test_the_cli_default_timeout_is_the_launchers():
    assert cli.DEFAULT_WITHOUT_TIMEOUT_S == outside.DEFAULT_WITHOUT_TIMEOUT_S
