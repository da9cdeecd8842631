"""Several robots on one bus (run.robots), without Zenoh: their ids, which process runs
for which robot, the stack's plan (programs, their robot, peers, credentials) and the
access list that keeps each robot's processes to that robot's keys."""

from __future__ import annotations

import json

import pytest

from teleop.bus import graph
from teleop.bus.access import Credentials, access_control, participant_robots
from teleop.bus.messages import PROTOCOL_VERSION
from teleop.core.config import ConfigError, load_config
from teleop.core.net import LoopbackPorts
from teleop.core.rundir import (
    RECORDING_FILE,
    checkpoint_path,
    clear_run_results,
    report_dir,
    shed_path,
    summary_path,
)
from teleop.run.stack import Launch, StackServices, plan_stack, start_detached

TWO = ['run.scenario="grasp"', 'run.mode="lockstep"', "run.robots=2", "bus.tls=false"]


def test_robot_ids_number_the_stem_of_robot_id():
    assert load_config(None, TWO).robot_ids() == ("arm0", "arm1")
    assert load_config(None, [*TWO, 'robot.robot_id="arm3"']).robot_ids() == ("arm3", "arm4")
    assert load_config(None, [*TWO, 'robot.robot_id="ur"', "run.robots=3"]).robot_ids() == (
        "ur0", "ur1", "ur2",
    )  # fmt: skip
    assert load_config(None, ['robot.robot_id="Arm-7"']).robot_ids() == ("Arm-7",)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (['run.scenario="path-following"'], "teleoperated"),
        (['run.operator="spacemouse"'], "spacemouse.switch_buttons is empty"),
        (["site.emulated_round_trip_ms=20"], "emulated_round_trip_ms"),
        (['teleop.stabiliser="wave"'], "wave"),
        (['robot.robot_id="Arm-0"'], "lower-case"),
        (["run.robots=9"], r"run.robots in \[1, 4\]"),
    ],
)
def test_what_several_robots_do_not_support_is_refused_in_one_line(extra, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [*TWO, *extra])


def test_per_robot_services_run_once_per_robot_under_their_own_name():
    assert graph.PER_ROBOT == ("plant", "controller", "eyeview")
    stack = graph.instances(["plant", "controller", "haptic", "recorder"], ["arm0", "arm1"])
    assert stack == ("plant-arm0", "plant-arm1", "controller-arm0", "controller-arm1",
                     "haptic", "recorder")  # fmt: skip
    assert graph.instances(["plant", "haptic"], ["arm0"]) == ("plant", "haptic")
    assert [graph.role_of(n) for n in stack[:3]] == ["plant", "plant", "controller"]
    assert [graph.robot_of(n) for n in ("plant-arm1", "haptic")] == ["arm1", None]


def test_the_plan_gives_each_process_its_robot_and_its_peers_by_service(tmp_path):
    config = load_config(None, TWO)
    layout = StackServices.of(config, ())
    assert layout.started == (
        *("plant-arm0", "plant-arm1", "controller-arm0", "controller-arm1"),
        *("haptic", "hmd", "operator", "recorder"),
    )
    with LoopbackPorts() as ports:
        plan = plan_stack(Launch.RUN, config, None, [], tmp_path, ports, layout)
    programs = {p.name: p.command for p in plan.programs}
    plant1 = programs["plant-arm1"]
    assert "services.plant" in plant1
    assert 'robot.robot_id="arm1"' in plant1
    assert plant1[plant1.index("--peers") + 1] == "controller,haptic,hmd,operator,recorder"
    assert plant1[plant1.index("--await") + 1] == "controller,haptic,hmd,operator,recorder,launcher"
    haptic = programs["haptic"]
    assert not any(arg.startswith("robot.robot_id") for arg in haptic)
    assert haptic[haptic.index("--peers") + 1] == "plant,controller,hmd,operator,recorder"
    assert plan.credentials is not None
    assert set(plan.credentials) == {*layout.started, "launcher", "observer"}
    content = json.loads(plan.credentials["controller-arm1"].read_text())
    assert content["user"] == "controller-arm1"


def test_a_robots_processes_may_use_that_robots_keys_only():
    robots = ("arm0", "arm1")
    assert participant_robots("controller-arm1", robots) == ("controller", ("arm1",))
    assert participant_robots("haptic", robots) == ("haptic", robots)
    assert participant_robots("plant-arm9", robots) == ("plant-arm9", robots)  # no such robot
    names = ["controller-arm0", "controller-arm1", "haptic", "observer"]
    acl = access_control({n: Credentials.generate(n) for n in names}, robots)
    rules = {rule["id"]: rule["key_exprs"] for rule in acl["rules"]}
    assert rules["controller-arm1-publishes"] == sorted(
        f"teleop/arm1/{s.key}" for s in graph.STREAMS if "controller" in s.producers
    )
    assert rules["controller-arm1-tokens"] == [
        "teleop/arm1/alive/controller",
        f"teleop/arm1/protocol/{PROTOCOL_VERSION}",  # the stack's version, no other
        "teleop/arm1/ready/controller",
    ]
    assert {key.split("/")[1] for key in rules["haptic-publishes"]} == {"arm0", "arm1"}
    assert {key.split("/")[1] for key in rules["haptic-tokens"]} == {"arm0", "arm1"}
    assert {key.split("/")[1] for key in rules["observer-subscribes"]} == {"arm0", "arm1"}


def test_each_robots_files_are_its_own_and_a_new_run_clears_them(tmp_path):
    paths = [
        checkpoint_path(tmp_path, "plant-arm1"),
        shed_path(tmp_path, "controller-arm1"),
        summary_path(tmp_path, "plant-arm1"),
        report_dir(tmp_path / RECORDING_FILE) / "arm1" / "report.md",
    ]
    assert checkpoint_path(tmp_path, "plant") != paths[0]
    for path in paths:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("stale")
    assert sorted(clear_run_results(tmp_path)) == sorted(paths)


def test_leaving_a_service_out_or_starting_detached_is_refused_with_several_robots(tmp_path):
    config = load_config(None, TWO)
    with pytest.raises(ConfigError, match="--without: not in a run of several robots"):
        StackServices.of(config, ["haptic"])
    with pytest.raises(ConfigError, match="teleop up runs one robot"):
        start_detached(config, None, [], tmp_path)
