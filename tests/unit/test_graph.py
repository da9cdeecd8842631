"""The graph description: consistent, the one source of keys, QoS, tables and the doc."""

from __future__ import annotations

from pathlib import Path

import pytest

from teleop.bus import graph
from teleop.bus.access import LAUNCHER, Credentials, access_control
from teleop.bus.messages import Event, Stage, code_tables
from teleop.bus.topics import Topics
from teleop.core.config import SCENARIO_SPECS, SCENARIOS, load_config
from teleop.run.stack import PRIORITY, scenario_services
from teleop.viz import recording as recorder

PROTOCOL_DOC = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"
BEGIN, END = "<!-- graph_tables() begin -->", "<!-- graph_tables() end -->"


def test_every_producer_and_consumer_is_a_service_of_the_graph():
    known = set(graph.SERVICES_BY_NAME) | {"launcher"}
    for stream in graph.STREAMS:
        assert stream.producers and set(stream.producers) <= known, stream.name
        assert stream.consumers and set(stream.consumers) <= known, stream.name
        if stream.batch_of:
            copied = graph.stream(stream.batch_of)
            assert (copied.schema, copied.producers) == (stream.schema, stream.producers)


def test_topics_keys_come_from_the_graph():
    topics = Topics("arm7")
    for stream in graph.STREAMS:
        assert getattr(topics, stream.name) == f"teleop/arm7/{stream.key}"
    assert len({s.key for s in graph.STREAMS}) == len(graph.STREAMS)
    with pytest.raises(KeyError, match="no stream 'nope'"):
        graph.stream("nope")


def test_the_recorder_and_the_launcher_read_the_graph():
    assert recorder.BATCHED_STREAMS == {
        "plant_state": "plant_state_batch",
        "haptic_state": "haptic_state_batch",
        "force_feedback": "force_feedback_batch",
    }
    assert "joint_command" not in recorder.STREAM_SCHEMAS  # the plant's state carries it
    assert not {"plant_events", "operator_events"} & recorder.PERIODIC_STREAMS
    assert "control_status" not in recorder.SEQ_CHECKED_STREAMS
    grasp = scenario_services(load_config(None, ['run.scenario="grasp"', "eyeview.enabled=false"]))
    assert grasp == ("plant", "controller", "haptic", "hmd", "operator", "recorder")
    assert PRIORITY["plant"] > PRIORITY["controller"] > PRIORITY["recorder"]


def test_protocol_doc_embeds_the_current_graph_tables():
    text = PROTOCOL_DOC.read_text()
    embedded = text[text.index(BEGIN) + len(BEGIN) : text.index(END)]
    assert embedded.strip() == graph.graph_tables().strip(), (
        "docs/protocol.md is stale: paste `python -m teleop.bus.graph` between the markers"
    )


def _embedded(begin: str, end: str) -> str:
    text = PROTOCOL_DOC.read_text()
    return text[text.index(begin) + len(begin) : text.index(end)]


def test_protocol_doc_embeds_the_current_codes_and_every_token():
    """Trace stages, RUN_EVENT codes, flag and button bits are generated from the code;
    every liveliness token of the graph is named in the doc as a client spells it."""
    codes = _embedded("<!-- code_tables() begin -->", "<!-- code_tables() end -->")
    assert codes.strip() == code_tables().strip(), (
        "docs/protocol.md is stale: paste `python -m teleop.bus.messages codes` between the markers"
    )
    for stage in Stage:
        assert f"| {int(stage)} | {stage.name} |" in codes
    for event in Event:
        assert f"| {event.name} | {int(event)} |" in codes
    text = PROTOCOL_DOC.read_text()
    topics = Topics("<robot_id>")
    for token in (graph.ALIVE_TOKEN, graph.READY_TOKEN):
        assert f"`teleop/<robot_id>/{token}/<service>`" in text
        assert topics.alive("x", ready=token == graph.READY_TOKEN).startswith(
            f"teleop/<robot_id>/{token}/"
        )


def test_scenario_streams_are_those_between_its_services():
    for scenario in SCENARIOS:
        services = set(graph.scenario_services(scenario)) | {"eyeview", "launcher"}
        for stream in graph.scenario_streams(scenario):
            assert set(stream.producers) & services, (scenario, stream.name)
            assert set(stream.consumers) & services, (scenario, stream.name)
    assert "control_status" not in {s.name for s in graph.scenario_streams("grasp")}
    assert "haptic_state" not in {s.name for s in graph.scenario_streams("path-following")}


def test_whether_a_scenario_is_teleoperated_decides_its_stack():
    """One property of the scenario (core.config.SCENARIO_SPECS), read once: a
    teleoperated scenario's stack has the haptic device, the HMD and the operator and
    carries the bilateral streams; an autonomous one has none of them."""
    hand = {"haptic", "hmd", "operator"}
    for spec in SCENARIO_SPECS:
        config = load_config(None, [f'run.scenario="{spec.name}"'])
        assert config.run.teleoperated is spec.teleoperated
        services = set(graph.scenario_services(spec.name))
        streams = {s.name for s in graph.scenario_streams(spec.name)}
        if spec.teleoperated:
            assert hand <= services and {"haptic_state", "force_feedback"} <= streams
        else:
            assert not hand & services and not {"haptic_state", "force_feedback"} & streams


def test_only_the_launcher_may_declare_a_release_and_every_participant_sees_it():
    """A lockstep plant held at a fault's instant steps on at the launcher's release token
    (graph.RELEASED_TOKEN): the access list lets the launcher alone declare one."""
    topics = Topics("arm0")
    key = topics.released(1_500_000_000)
    assert key == "teleop/arm0/released/1500000000"
    assert topics.released_ns_of(key) == 1_500_000_000
    for bad in (
        "teleop/arm0/released/-1",
        "teleop/arm0/released/1.5",
        "teleop/arm1/released/1",
        "teleop/arm0/ready/plant",
        "teleop/arm0/released/",
        "teleop/arm0/released/١",
    ):
        assert topics.released_ns_of(bad) is None, bad
    with pytest.raises(ValueError):
        topics.released(-1)
    names = ["plant", "controller", LAUNCHER]
    acl = access_control({n: Credentials.generate(n) for n in names}, ("arm0",))
    rules = {rule["id"]: rule for rule in acl["rules"]}
    declares = {name: rules[f"{name}-tokens"]["key_exprs"] for name in names}
    assert topics.released_all in declares[LAUNCHER]
    assert all(topics.released_all not in declares[n] for n in ("plant", "controller"))
    # The plant may watch for it and be sent it.
    assert topics.released_all in rules["plant-watch-in"]["key_exprs"]
    assert topics.released_all in rules["plant-peer-tokens"]["key_exprs"]
