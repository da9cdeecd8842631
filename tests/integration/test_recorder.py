"""Recorder service over a real Zenoh bus and a real Rerun file (no mocks).

The recorder runs in-process on a thread with its own loopback endpoint; a second
session publishes known records once the recorder's liveliness token is up. The
``.rrd`` is then read back with ``teleop.viz.rrd.read_rrd`` and every value and time
compared with what was sent: samples must sit at their own sim_time / source_time,
not at their arrival time.
"""

from __future__ import annotations

import json
import os
import socket
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from services import recorder as r
from teleop.bus import messages as m
from teleop.bus import session as bus
from teleop.bus.service import ServiceOptions
from teleop.core.config import Config, ConfigError, load_config
from teleop.core.rundir import (
    RECORDER_SEGMENTS_FILE,
    RECORDING_FILE,
    segment_paths,
    summary_path,
)
from teleop.viz import blueprint, recording, stream_writers
from teleop.viz import entities as ent
from teleop.viz.recording_file import RecordingFile, Segment, no_display_reason
from teleop.viz.report import write_reports
from teleop.viz.rrd import Recording, read_rrd
from tests.rerun_check import rerun_verify_problems

os.environ.setdefault("RERUN_ANALYTICS", "0")
os.environ.setdefault("TELEMETRY_ENABLED", "false")

TIMEOUT_S = 10.0  # bound on any single wait; passing runs take well under 1 s each
FLUSH_PERIOD_S = 0.05  # short, so a test spans several flushes
RATE_WINDOW_S = 0.05  # loop-rate window (producer clock): several per test
ROBOT = "rectest"
JOINTS = ("j1", "j2", "j3", "j4", "j5", "j6")
OBJECTS = ("cube", "ball")
SIM_T0_NS = 5_000_000_000  # sim times far from any monotonic arrival time
SIM_STEP_NS = 1_000_000  # between two records (any: each is logged at its own sim time)
F32_TOLERANCE = 1e-6  # positions go through float32 in Rerun
SOURCE_T0_NS = 123_000_000_000  # producer clock values, also far from arrival times
N = {  # records sent per stream
    "plant_state": 400,
    "tool_pose": 400,
    "objects": 50,
    "control_status": 120,
    "plant_events": 4,  # EVENTS[:4]
    "operator_events": 3,  # EVENTS[4:]
}
N_BILATERAL = {  # records sent per stream of the bilateral teleoperation test
    "haptic_state": 300,
    "hand_input": 30,
    "force_feedback": 300,
    "head_pose": 27,
    "teleop_status": 30,
}
EVENTS = (
    (m.Event.STARTED, 0, 0.0),
    (m.Event.WATCHDOG_BRAKE, 123, 0.025),
    (m.Event.WATCHDOG_RESUME, 200, 0.0),
    (m.Event.GRASP, 900, 0.0),
    (m.Event.PHASE, 1200, 3.0),
    (m.Event.TASK_DONE, 5000, 1.0),
    (m.Event.TASK_DONE, 6000, 0.0),
)
# PLANT_STATE's latency stamps: how long before the record's t_source_ns each was taken.
HOP_STAMPS_NS = {
    m.Stage.CONTROLLER_RX: 900_000,
    m.Stage.CONTROLLER_TX: 600_000,
    m.Stage.PLANT_RX: 450_000,
    m.Stage.PLANT_STATE_TX: 0,
}
HAND_TICK0 = 4_000  # first valid_from_tick of the HAND_INPUT records
# PLANT_STATE: contact and proximity computed every this many records (as outside
# teleoperation, at the scene rate); the records in between repeat them.
INTERACTION_EVERY = 10
CONTACT_FEEDBACK_N = (3.0, 4.0, 0.0)  # norm 5 N
WEIGHT_FEEDBACK_N = (0.0, 0.0, -1.962)  # 0.2 kg held


def free_endpoint() -> str:
    """A loopback TCP endpoint on a port the OS just reported free."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return f"tcp/127.0.0.1:{port}"


def make_config(rrd_path: Path | str, endpoint: str, *extra: str) -> Config:
    return load_config(
        None,
        (
            f'bus.endpoint="{endpoint}"',
            f'robot.robot_id="{ROBOT}"',
            f"robot.arm_joints={json.dumps(list(JOINTS))}",
            f"robot.arm_actuators={json.dumps([j + '_vel' for j in JOINTS])}",
            f"robot.home_q_rad={[0.0] * len(JOINTS)}",
            f"robot.object_bodies={json.dumps(list(OBJECTS))}",
            f'recorder.rrd_path="{rrd_path}"',
            f"recorder.flush_period_s={FLUSH_PERIOD_S}",
            f"recorder.rate_window_s={RATE_WINDOW_S}",
            *extra,
        ),
    )


# --- what the producer sends: record i of each stream is fully determined by i -------------


def sim_ns(i: int) -> int:
    return SIM_T0_NS + i * SIM_STEP_NS


def source_ns(i: int) -> int:
    return SOURCE_T0_NS + 3 * i * SIM_STEP_NS + 7


def build(stream: str, i: int) -> np.ndarray:
    rec = recording.STREAM_SCHEMAS[stream].new()
    rec["seq"] = i
    rec["t_source_ns"] = source_ns(i)
    if "sim_time_ns" in rec.dtype.names:
        rec["sim_time_ns"] = sim_ns(i)
    if stream == "plant_state":
        rec["n_joints"] = len(JOINTS)
        rec["q_rad"][: len(JOINTS)] = 0.001 * i + np.arange(len(JOINTS))
        rec["qd_rad_s"][: len(JOINTS)] = -0.002 * i
        rec["qd_ref_applied_rad_s"][: len(JOINTS)] = 0.01 * i - np.arange(len(JOINTS))
        rec["step"] = i
        for stage, before_ns in HOP_STAMPS_NS.items():
            rec["trace_ns"][stage] = source_ns(i) - before_ns
        computed = i - i % INTERACTION_EVERY
        rec["interaction_step"] = computed
        rec["world_f_contact_n"] = (0.0, 0.0, float(computed))
        rec["n_contacts"] = computed // INTERACTION_EVERY % 3
        rec["distance_m"] = 0.5 - 0.001 * computed
    elif stream == "tool_pose":
        rec["world_p_tool_m"] = (0.3, 0.0, 0.001 * i)
        rec["world_q_tool_wxyz"] = (1.0, 0.0, 0.0, 0.0)
    elif stream == "objects":
        rec["n_objects"] = 1 if i % 2 else 2  # the ball is only in the even records
        rec["world_p_m"][:2] = ((0.1, 0.2, 0.001 * i), (0.5, 0.5, 0.5))
        rec["world_q_wxyz"][:2] = (0.0, 0.0, 0.0, 1.0)  # 180 deg about z
    elif stream == "control_status":
        rec["path_error_m"] = 0.0001 * i
        rec["manipulability"] = 0.05
        rec["desired_p_m"] = (0.1, 0.2, 0.3)
        rec["tool_p_m"] = (0.1, 0.2, 0.3 + 0.0001 * i)
    elif stream in ("plant_events", "operator_events"):
        index = i if stream == "plant_events" else N["plant_events"] + i
        event, step, value = EVENTS[index]
        rec["event"], rec["step"], rec["value"] = event, step, value
        rec["sim_time_ns"] = sim_ns(index)
    elif stream == "haptic_state":
        rec["tick"] = i
        rec["device_p_m"] = (0.0001 * i, -0.0001 * i, 0.01)
        rec["device_v_m_s"] = (0.1, 0.0, -0.001 * i)
        rec["device_f_n"] = (0.0, 0.0, 0.01 * i)
        rec["buttons"] = i % 4
    elif stream == "hand_input":
        rec["valid_from_tick"] = HAND_TICK0 + i
        rec["target_p_m"] = (0.001 * i, 0.0, -0.02)
        rec["buttons"] = m.Button.GRIPPER_CLOSE if i % 2 else m.Button.NONE
    elif stream == "force_feedback":
        rec["tick"] = i
        rec["device_f_n"] = (0.01 * i, 0.0, 0.0)
        rec["world_f_contact_n"] = CONTACT_FEEDBACK_N
        rec["world_f_weight_n"] = WEIGHT_FEEDBACK_N
        rec["world_f_obstacle_n"] = (0.0, 0.001 * i, 0.0)
        rec["device_f_workspace_n"] = (0.0, 0.0, -0.5)
    elif stream == "head_pose":
        rec["valid_from_tick"] = i + 20
        rec["measured_p_m"] = (-0.45, 0.001 * i, 0.65)
        rec["measured_yaw_rad"] = 0.01 * i
        rec["filtered_p_m"] = (-0.45, 0.0, 0.65 + 0.001 * i)
        rec["predicted_p_m"] = (-0.45, 0.0, 0.65)
        rec["predicted_yaw_rad"] = 0.02 * i
        rec["predicted_pitch_rad"] = 0.05
        rec["horizon_s"] = 0.02
    elif stream == "teleop_status":
        rec["tick"] = i
        rec["world_v_ref_m_s"] = (0.01 * i, 0.0, 0.0)
        rec["world_v_tool_m_s"] = (0.009 * i, 0.0, 0.0)
        rec["world_p_tool_m"] = (0.3, 0.0, 0.2)
        rec["speed_scale"] = 1.0 - 0.01 * i
        rec["gripper_cmd"] = i % 2
        rec["holding"] = i % 2
    return rec


# --- reading the .rrd back ---------------------------------------------------------------


def series(data: dict[str, dict[str, list[Any]]], entity: str) -> dict[int, float]:
    """A Scalars entity as {sim_time or source_time ns: value}."""
    cols = data[entity]
    times = cols.get(ent.TIMELINE_SIM) or cols[ent.TIMELINE_SOURCE]
    values = [v[0] for v in cols["Scalars:scalars"]]
    assert len(times) == len(values) == len(set(times)), entity
    return dict(zip(times, values, strict=True))


# --- a recorder on a thread plus a producer session ----------------------------------------


@dataclass
class Rig:
    service: r.RecorderService
    session: zenoh.Session  # the producer's
    stop: threading.Event
    thread: threading.Thread

    def publish(
        self,
        counts: dict[str, int],
        first: int = 0,
        received: dict[str, int] | None = None,
        robot: int = 0,
    ) -> None:
        """Send records ``first .. first + counts[stream] - 1`` of each stream, interleaved,
        under the keys of the run's robot ``robot``, then wait until the recorder has
        received them all (``received`` records per stream in total; default ``first +
        counts[stream]``)."""
        topics = self.service.robot_topics[robot]
        pubs = {  # plant states go on their observers' copy, here one record per message
            s: bus.Publisher.declare(
                self.session,
                getattr(topics, recording.BATCHED_STREAMS.get(s, s)),
                recording.STREAM_SCHEMAS[s],
            )
            for s in counts
        }
        try:
            for pub in pubs.values():
                assert pub.wait_matched(TIMEOUT_S)
            for i in range(max(counts.values())):
                for stream, n in counts.items():
                    if i < n:
                        pubs[stream].put(build(stream, first + i))
            expected = received or {s: first + n for s, n in counts.items()}
            writer = self.service.writers[robot]
            assert writer.wait_received(expected, TIMEOUT_S), "recorder missed records"
        finally:
            for pub in pubs.values():
                pub.undeclare()

    def finish(self) -> None:
        self.stop.set()
        self.thread.join(TIMEOUT_S)
        assert not self.thread.is_alive()
        self.service.close()


@pytest.fixture
def rig_factory(tmp_path: Path) -> Iterator[Any]:
    rigs: list[Rig] = []

    def start(service_class: type[r.RecorderService] = r.RecorderService, *overrides: str) -> Rig:
        endpoint = free_endpoint()
        config = make_config(tmp_path / "out" / "rec.rrd", endpoint, *overrides)
        service = service_class(config, ServiceOptions(run_dir=tmp_path, listen=True))
        service.open()
        stop = threading.Event()
        thread = threading.Thread(target=service.run, args=(stop,), name="recorder")
        thread.start()
        session = bus.open_session(config.bus, listen=False)
        rig = Rig(service, session, stop, thread)
        rigs.append(rig)
        for topics in service.robot_topics:
            bus.wait_alive(session, topics, [r.RecorderService.name], TIMEOUT_S)
        return rig

    yield start
    for rig in rigs:
        rig.stop.set()
        rig.thread.join(TIMEOUT_S)
        rig.service.close()
        bus.close_session(rig.session)


# --- tests ---------------------------------------------------------------------------------


def test_every_stream_is_logged_at_its_own_time(rig_factory, tmp_path):
    rig = rig_factory()
    rig.publish(N)
    rig.finish()
    summary = json.loads(summary_path(tmp_path, "recorder").read_text())
    assert summary["samples_logged"] == {**dict.fromkeys(recording.STREAM_SCHEMAS, 0), **N}
    assert summary["rerun_errors"] == 0 and summary["dropped_messages"] == 0
    assert sum(summary["overflow_drops"].values()) == 0
    assert summary["flushes"] >= 1 and summary["wall_time_s"] > 0
    assert summary["rrd_path"] == str(rig.service.rrd_path)

    data = read_rrd(rig.service.rrd_path)
    sims = [sim_ns(i) for i in range(N["plant_state"])]
    for j, joint in enumerate(JOINTS):
        q = series(data, ent.joint_entity(ent.ENTITY_JOINT_Q, joint))
        assert sorted(q) == sims  # sim_time = the records' own sim_time_ns
        assert all(q[sim_ns(i)] == pytest.approx(0.001 * i + j) for i in range(N["plant_state"]))
        qd = series(data, ent.joint_entity(ent.ENTITY_JOINT_QD, joint))
        assert len(qd) == N["plant_state"]
        # The references the drives got come with the state, at its sim time.
        cmd = series(data, ent.joint_entity(ent.ENTITY_QD_REF, joint))
        assert sorted(cmd) == sims
        assert cmd[sim_ns(5)] == pytest.approx(0.05 - j)
    q_cols = data[ent.joint_entity(ent.ENTITY_JOINT_Q, JOINTS[0])]
    by_sim = dict(zip(q_cols[ent.TIMELINE_SIM], q_cols[ent.TIMELINE_SOURCE], strict=True))
    assert by_sim == {sim_ns(i): source_ns(i) for i in range(N["plant_state"])}

    tool = data[ent.ENTITY_TOOL]
    assert sorted(tool[ent.TIMELINE_SIM]) == sims
    rows = dict(zip(tool[ent.TIMELINE_SIM], tool["Transform3D:translation"], strict=True))
    # One translation per row; Rerun stores Vec3D as float32.
    assert rows[sim_ns(10)][0] == pytest.approx([0.3, 0.0, 0.01], abs=F32_TOLERANCE)
    assert tool["Transform3D:quaternion"][0][0] == pytest.approx([0.0, 0.0, 0.0, 1.0])  # xyzw
    trace = data[ent.ENTITY_TOOL_TRACE]["LineStrips3D:strips"]
    assert trace and len(trace[-1][0]) > 1  # re-logged per flush, never per sample

    # Contact and proximity: only the states that computed them, at their own times.
    computed = range(0, N["plant_state"], INTERACTION_EVERY)
    force_z = series(data, ent.axis_entity(ent.ENTITY_CONTACT_FORCE, "z"))
    assert force_z == {sim_ns(i): float(i) for i in computed}
    count = series(data, ent.ENTITY_CONTACT_COUNT)
    assert count == {sim_ns(i): float(i // INTERACTION_EVERY % 3) for i in computed}
    distance = series(data, ent.ENTITY_OBSTACLE_DISTANCE)
    assert sorted(distance) == [sim_ns(i) for i in computed]
    assert distance[sim_ns(100)] == pytest.approx(0.4)
    cube = data[ent.object_entity("cube")][ent.TIMELINE_SIM]
    ball = data[ent.object_entity("ball")][ent.TIMELINE_SIM]
    assert sorted(cube) == [sim_ns(i) for i in range(N["objects"])]
    assert sorted(ball) == [sim_ns(i) for i in range(0, N["objects"], 2)]

    error = series(data, ent.ENTITY_PATH_ERROR)
    assert sorted(error) == [sim_ns(i) for i in range(N["control_status"])]
    assert error[sim_ns(7)] == pytest.approx(0.0007)
    for base in (ent.ENTITY_DESIRED_P, ent.ENTITY_TOOL_P):
        for axis in ent.AXES:
            assert len(series(data, ent.axis_entity(base, axis))) == N["control_status"]
    assert len(series(data, ent.ENTITY_MANIPULABILITY)) == N["control_status"]

    events = data[ent.ENTITY_EVENTS]
    texts = dict(zip(events[ent.TIMELINE_SIM], events["TextLog:text"], strict=True))
    assert texts[sim_ns(1)] == ["WATCHDOG_BRAKE at step 123 (value 0.025)"]
    assert texts[sim_ns(0)] == ["STARTED at step 0"]
    assert texts[sim_ns(3)] == ["GRASP at step 900"]
    assert texts[sim_ns(4)] == ["PHASE 3 at step 1200"]
    assert texts[sim_ns(5)] == ["TASK_DONE (success) at step 5000"]
    assert texts[sim_ns(6)] == ["TASK_DONE (gave up) at step 6000"]
    levels = dict(zip(events[ent.TIMELINE_SIM], events["TextLog:level"], strict=True))
    assert levels[sim_ns(1)] == [stream_writers.LEVEL_WARN]

    stats = json.loads(data[ent.ENTITY_STATS]["TextDocument:text"][0][0])
    assert stats["samples_logged"] == summary["samples_logged"]


def test_bilateral_streams_are_logged_at_their_own_time(rig_factory, tmp_path):
    rig = rig_factory()
    n_tool = 20
    rig.publish({"tool_pose": n_tool})  # first, so the force arrows start at tool n_tool - 1
    rig.publish(N_BILATERAL)
    rig.finish()
    summary = json.loads(summary_path(tmp_path, "recorder").read_text())
    assert summary["samples_logged"] == {
        **dict.fromkeys(recording.STREAM_SCHEMAS, 0),
        "tool_pose": n_tool,
        **N_BILATERAL,
    }
    assert summary["rerun_errors"] == 0 and summary["dropped_messages"] == 0
    data = read_rrd(rig.service.rrd_path)

    def sims(stream: str) -> list[int]:
        return [sim_ns(i) for i in range(N_BILATERAL[stream])]

    # Haptic device: every coordinate at the records' own sim and source times.
    for base in (ent.ENTITY_HAPTIC_P, ent.ENTITY_HAPTIC_V, ent.ENTITY_HAPTIC_F):
        for axis in ent.AXES:
            assert sorted(series(data, ent.axis_entity(base, axis))) == sims("haptic_state")
    haptic_px = data[ent.axis_entity(ent.ENTITY_HAPTIC_P, "x")]
    by_sim = dict(zip(haptic_px[ent.TIMELINE_SIM], haptic_px[ent.TIMELINE_SOURCE], strict=True))
    assert by_sim == {sim_ns(i): source_ns(i) for i in range(N_BILATERAL["haptic_state"])}
    assert series(data, ent.axis_entity(ent.ENTITY_HAPTIC_F, "z"))[sim_ns(7)] == pytest.approx(0.07)
    assert series(data, ent.ENTITY_HAPTIC_BUTTONS)[sim_ns(3)] == 3.0

    # Hand input: sim_time from valid_from_tick and the tick (the bus period, loop.rate_hz).
    tick_ns = round(rig.service.config.tick_s * 1e9)
    hand_x = series(data, ent.axis_entity(ent.ENTITY_HAND_TARGET, "x"))
    ticks = range(HAND_TICK0, HAND_TICK0 + N_BILATERAL["hand_input"])
    assert sorted(hand_x) == [t * tick_ns for t in ticks]
    assert hand_x[(HAND_TICK0 + 5) * tick_ns] == pytest.approx(0.005)
    hand_cols = data[ent.ENTITY_HAND_BUTTONS]
    assert sorted(hand_cols[ent.TIMELINE_SOURCE]) == [
        source_ns(i) for i in range(N_BILATERAL["hand_input"])
    ]
    assert series(data, ent.ENTITY_HAND_BUTTONS)[(HAND_TICK0 + 1) * tick_ns] == 1.0

    # Force feedback: each component and its norm per sample.
    for _, base in ent.FEEDBACK_COMPONENTS.values():
        for axis in ent.AXES:
            assert sorted(series(data, ent.axis_entity(base, axis))) == sims("force_feedback")
    for component in ent.FEEDBACK_COMPONENTS:
        assert sorted(series(data, ent.norm_entity(component))) == sims("force_feedback")
    assert set(series(data, ent.norm_entity("contact")).values()) == {5.0}  # |(3, 4, 0)|
    device_norm = series(data, ent.norm_entity("device"))
    assert device_norm[sim_ns(40)] == pytest.approx(0.4)
    obstacle_y = series(data, ent.axis_entity(ent.ENTITY_FEEDBACK_OBSTACLE_F, "y"))
    assert obstacle_y[sim_ns(40)] == pytest.approx(0.04)

    # Force arrows: one row per flush (not per sample), the newest at the newest feedback,
    # from the newest tool position.
    last = N_BILATERAL["force_feedback"] - 1
    newest_tool_m = build("tool_pose", n_tool - 1)["world_p_tool_m"]
    for component, newest_n in (
        ("contact", CONTACT_FEEDBACK_N),
        ("weight", WEIGHT_FEEDBACK_N),
        ("obstacle", build("force_feedback", last)["world_f_obstacle_n"]),
    ):
        arrows = data[ent.force_arrow_entity(component)]
        times = arrows[ent.TIMELINE_SIM]
        assert 1 <= len(times) <= summary["flushes"] < N_BILATERAL["force_feedback"]
        newest = times.index(max(times))
        assert times[newest] == sim_ns(last)
        vectors = np.asarray(arrows["Arrows3D:vectors"][newest])
        origins = np.asarray(arrows["Arrows3D:origins"][newest])
        expected_m = np.asarray(newest_n) * stream_writers.FORCE_ARROW_M_PER_N
        np.testing.assert_allclose(vectors, [expected_m], atol=F32_TOLERANCE)
        np.testing.assert_allclose(origins, [newest_tool_m], atol=F32_TOLERANCE)
        assert arrows["Arrows3D:colors"]  # static, one colour per component

    # Head pose: scalars, and the camera transform at the predicted pose plus a frustum.
    assert sorted(series(data, ent.ENTITY_HMD_MEASURED_YAW)) == sims("head_pose")
    assert series(data, ent.ENTITY_HMD_PREDICTED_YAW)[sim_ns(10)] == pytest.approx(0.2)
    for base in (ent.ENTITY_HMD_FILTERED_P, ent.ENTITY_HMD_MEASURED_P):
        for axis in ent.AXES:
            assert sorted(series(data, ent.axis_entity(base, axis))) == sims("head_pose")
    hmd = data[ent.ENTITY_HMD]
    assert sorted(hmd[ent.TIMELINE_SIM]) == sims("head_pose")
    quats = dict(zip(hmd[ent.TIMELINE_SIM], hmd["Transform3D:quaternion"], strict=True))
    expected_q = stream_writers.yaw_pitch_to_xyzw(np.array(0.2), np.array(0.05))
    np.testing.assert_allclose(quats[sim_ns(10)][0], expected_q, atol=F32_TOLERANCE)
    assert hmd["Pinhole:image_from_camera"]  # static: the viewer draws a frustum
    assert hmd["Pinhole:camera_xyz"]

    # Teleoperation status.
    for base in (ent.ENTITY_TELEOP_V_REF, ent.ENTITY_TELEOP_V_TOOL):
        for axis in ent.AXES:
            assert sorted(series(data, ent.axis_entity(base, axis))) == sims("teleop_status")
    for entity in (ent.ENTITY_TELEOP_SPEED_SCALE, ent.ENTITY_TELEOP_GRIPPER_CMD):
        assert sorted(series(data, entity)) == sims("teleop_status")
    holding = series(data, ent.ENTITY_TELEOP_HOLDING)
    assert (holding[sim_ns(4)], holding[sim_ns(5)]) == (0.0, 1.0)
    assert series(data, ent.ENTITY_TELEOP_SPEED_SCALE)[sim_ns(10)] == pytest.approx(0.9)


class FaultyArm(stream_writers.ArmWriter):
    """Sends a malformed control-status batch (more values than times): a real Rerun error."""

    def control_status(self, records: np.ndarray, out: stream_writers.Columns) -> None:
        values = np.zeros(records.size + 1)
        out.scalars(ent.ENTITY_PATH_ERROR, out.indexes(records), values)


class FaultyWriter(recording.RecordingWriter):
    arm_writer = FaultyArm


class FaultyRecorder(r.RecorderService):
    writer_class = FaultyWriter


def test_rerun_error_is_counted_and_recording_goes_on(rig_factory, tmp_path):
    rig = rig_factory(FaultyRecorder)
    n = 50
    counts = {"control_status": n, "plant_state": n}
    rig.publish(counts)
    # The first batch is flushed (and rejected) before the second one arrives.
    # (+2: the flush under way when the wait starts may have missed the last records.)
    assert rig.service.writer.wait_flushes(rig.service.writer.flushes + 2, TIMEOUT_S)
    rig.publish(counts, first=n)
    rig.finish()
    summary = json.loads(summary_path(tmp_path, "recorder").read_text())
    assert summary["rerun_errors"] >= 2  # one per flush that held control-status records
    assert summary["samples_logged"]["control_status"] == 0
    assert summary["samples_logged"]["plant_state"] == 2 * n
    data = read_rrd(rig.service.rrd_path)
    q = series(data, ent.joint_entity(ent.ENTITY_JOINT_Q, JOINTS[0]))
    assert sorted(q) == [sim_ns(i) for i in range(2 * n)]
    assert ent.ENTITY_PATH_ERROR not in data


def test_buffer_is_bounded_and_keeps_the_newest():
    capacity, sent = 10, 25
    buffer = recording.StreamBuffer(m.PLANT_STATE, capacity, threading.Condition())
    for i in range(sent):
        buffer(build("plant_state", i), 0)
    assert (buffer.received, buffer.overflow) == (sent, sent - capacity)
    records = buffer.take()
    assert list(records["seq"]) == list(range(sent - capacity, sent))
    assert records["sim_time_ns"][0] == sim_ns(sent - capacity)
    assert buffer.take().size == 0


def test_record_copy_outlives_the_received_bytes():
    buffer = recording.StreamBuffer(m.TOOL_POSE, 4, threading.Condition())
    wire = bytearray(m.TOOL_POSE.encode(build("tool_pose", 3)))
    buffer(np.frombuffer(wire, m.TOOL_POSE.dtype, 1).reshape(()), 0)
    wire[:] = bytes(len(wire))  # the receive buffer is reused
    assert int(buffer.take()["seq"][0]) == 3


def test_no_rrd_path_and_no_run_dir_is_a_config_error():
    config = make_config("", free_endpoint())
    with pytest.raises(ConfigError, match="rrd_path"):
        r.RecorderService(config, ServiceOptions(run_dir=None))


def test_default_rrd_path_is_in_the_run_dir(tmp_path):
    service = r.RecorderService(make_config("", free_endpoint()), ServiceOptions(run_dir=tmp_path))
    assert service.rrd_path == tmp_path / RECORDING_FILE


def test_event_text_and_quaternion_order():
    assert (
        stream_writers.event_text(int(m.Event.WATCHDOG_BRAKE), 123, 0.0)
        == "WATCHDOG_BRAKE at step 123"
    )
    assert stream_writers.event_text(99, 1, 0.0) == "EVENT_99 at step 1"
    q_wxyz = np.array([[0.5, 0.1, 0.2, 0.3]])
    np.testing.assert_array_equal(stream_writers.wxyz_to_xyzw(q_wxyz), [[0.1, 0.2, 0.3, 0.5]])


def rotate(q_xyzw: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Reference: v rotated by the unit quaternion q, v' = v + 2w (u x v) + 2u x (u x v)."""
    u, w = q_xyzw[:3], q_xyzw[3]
    return v + 2.0 * w * np.cross(u, v) + 2.0 * np.cross(u, np.cross(u, v))


@pytest.mark.parametrize(
    ("yaw_rad", "pitch_rad"), [(0.0, 0.0), (0.7, 0.0), (0.3, 0.2), (-2.5, -0.4)]
)
def test_head_quaternion_looks_along_yaw_and_pitch(yaw_rad, pitch_rad):
    q = stream_writers.yaw_pitch_to_xyzw(np.array([yaw_rad]), np.array([pitch_rad]))[0]
    assert np.linalg.norm(q) == pytest.approx(1.0)
    # The head's +x (forward): yaw turns it toward +y, positive pitch lowers the nose.
    forward = [
        np.cos(yaw_rad) * np.cos(pitch_rad),
        np.sin(yaw_rad) * np.cos(pitch_rad),
        -np.sin(pitch_rad),
    ]
    np.testing.assert_allclose(rotate(q, np.array([1.0, 0.0, 0.0])), forward, atol=1e-12)
    # The head's +z (up) stays in the plane of forward and world z: no roll.
    up = rotate(q, np.array([0.0, 0.0, 1.0]))
    assert np.cross(forward, [0.0, 0.0, 1.0]) @ up == pytest.approx(0.0, abs=1e-12)


def test_rates_hops_and_seq_gaps_are_derived_from_the_records(rig_factory, tmp_path):
    rig = rig_factory()
    n = 60
    rig.publish({"plant_state": n})
    assert rig.service.writer.wait_flushes(rig.service.writer.flushes + 2, TIMEOUT_S)
    missing = 7
    # The seq jumps: 7 records lost.
    rig.publish({"plant_state": n}, first=n + missing, received={"plant_state": 2 * n})
    rig.finish()
    data = read_rrd(rig.service.rrd_path)

    # Each hop between consecutive stamps, in ms, at the record's own sim time: one
    # series per hop in the stream's latency entity, named by the stages.
    stages = list(HOP_STAMPS_NS)
    sent = [sim_ns(i) for i in (*range(n), *range(n + missing, 2 * n + missing))]
    cols = data[ent.latency_entity("plant_state")]
    assert sorted(cols[ent.TIMELINE_SIM]) == sent
    hops = list(zip(stages, stages[1:], strict=False))
    assert cols["SeriesLines:names"][-1] == [ent.hop_name(a, b) for a, b in hops]
    expected_ms = [(HOP_STAMPS_NS[a] - HOP_STAMPS_NS[b]) / 1e6 for a, b in hops]
    for row in cols["Scalars:scalars"]:
        assert row == pytest.approx(expected_ms)

    # Loop rate: records per second of the producer's clock over each window (one record
    # per 3 ms here), lower only for a window that spans the gap.
    rates = [v[0] for v in data[ent.rate_entity("plant_state")]["Scalars:scalars"]]
    full_hz = 1e9 / (source_ns(1) - source_ns(0))
    assert len(rates) >= 2
    assert max(rates) == pytest.approx(full_hz, rel=1e-6)
    assert all(0.5 * full_hz <= v <= full_hz * (1 + 1e-6) for v in rates)

    texts = [t[0] for t in data[ent.ENTITY_RECORDER_EVENTS]["TextLog:text"]]
    assert f"plant_state: {missing} record(s) missing (seq gaps)" in texts
    assert "service recorder joined the bus" in texts


def test_a_restarted_recorder_writes_the_next_segment_and_the_reader_joins_them(tmp_path):
    """Two recorder incarnations of one run: the second never overwrites the first, and
    the reader (and the report) see one timeline with the gap between them marked."""
    config = make_config("", free_endpoint())
    options = ServiceOptions(run_dir=tmp_path)
    spans = ((0, 40), (60, 100))  # records 40..59 fall while the recorder is down
    paths = []
    for first, last in spans:
        service = r.RecorderService(config, options)
        writer = service.writer
        service.file.open()
        writer.open()
        for i in range(first, last):
            writer.buffers["plant_state"](build("plant_state", i), 0)
        writer.close()  # a killed recorder flushed until its end: same files, less data
        service.file.close()
        paths.append(service.rrd_path)
    assert paths == [tmp_path / RECORDING_FILE, tmp_path / "recording.1.rrd"]
    rec = Recording(tmp_path / RECORDING_FILE)
    assert [s.path for s in rec.segments] == paths
    (gap,) = rec.gaps()
    assert (gap.start_ns, gap.end_ns) == (sim_ns(39), sim_ns(60))
    q = rec.scalars(ent.TIMELINE_SIM)[ent.joint_entity(ent.ENTITY_JOINT_Q, JOINTS[0])]
    assert len(q.t_ns) == 80  # both segments' samples, one series
    texts = [t for rows in rec.column(ent.ENTITY_RECORDER_EVENTS, "TextLog:text").values()
             for row in rows for t in row]  # fmt: skip
    assert any("recorder restarted: segment 1" in t for t in texts)
    (report,) = write_reports(tmp_path / RECORDING_FILE)
    text = report.summary.read_text()
    assert "recording.1.rrd" in text and f"from sim {sim_ns(39) * 1e-9:.3f} s" in text
    # A new run (no ledger: the launcher clears it) starts over and drops stale segments.
    (tmp_path / RECORDER_SEGMENTS_FILE).unlink()
    assert r.RecorderService(config, options).rrd_path == paths[0]
    assert not paths[1].exists()


def test_several_robots_are_recorded_side_by_side_in_one_recording(rig_factory, tmp_path):
    """A run of two robots: one file, each robot's entities under its id, its world
    placed beside the other's, the blueprint's views all fed, a report per robot."""
    rig = rig_factory(r.RecorderService, "run.robots=2", 'run.scenario="grasp"')
    robots = [t.robot_id for t in rig.service.robot_topics]
    assert robots == [f"{ROBOT}0", f"{ROBOT}1"]
    streams = ("plant_state", "teleop_status", "force_feedback", "haptic_state")
    counts = (dict.fromkeys(streams, 40), dict.fromkeys(streams, 60))
    for robot, sent in enumerate(counts):
        rig.publish(sent, robot=robot)
    rig.finish()

    summary = json.loads(summary_path(tmp_path, "recorder").read_text())
    for robot_id, sent in zip(robots, counts, strict=True):
        logged = summary["robots"][robot_id]["samples_logged"]
        assert {s: logged[s] for s in sent} == sent, robot_id
        assert summary["robots"][robot_id]["rrd_path"] == str(rig.service.rrd_path)
    rec = Recording(rig.service.rrd_path)
    assert rec.robots == robots
    q = ent.joint_entity(ent.ENTITY_JOINT_Q, JOINTS[0])
    assert q not in rec.batches  # nothing of a robot outside its root
    for robot_id, sent in zip(robots, counts, strict=True):
        series_q = rec.under(robot_id).scalars(ent.TIMELINE_SIM)[q]
        assert list(series_q.t_ns) == [sim_ns(i) for i in range(sent["plant_state"])]
    for index, robot_id in enumerate(robots):  # each world beside the other
        placed = np.reshape(rec.lists([robot_id])[robot_id]["Transform3D:translation"], -1)
        assert placed == pytest.approx(blueprint.robot_offset_m(index))
    assert blueprint.robot_offset_m(0) != blueprint.robot_offset_m(1)
    specs = blueprint.view_specs(rig.service.config)
    (scene,) = [spec for spec in specs if spec.kind == "3d"]
    assert scene.subtrees == tuple(f"{r_id}/{ent.ENTITY_WORLD}" for r_id in robots)
    for spec in specs:
        for root in spec.subtrees:
            if not root.endswith(ent.ENTITY_EYE_VIEW):  # no eye view in this test
                assert any(e == root or e.startswith(root + "/") for e in rec.batches), root
        for entity in spec.entities:
            assert entity.split("/")[0] in robots and entity in rec.batches, entity

    reports = write_reports(rig.service.rrd_path, tmp_path / "report")
    assert [rep.out_dir for rep in reports] == [tmp_path / "report" / r_id for r_id in robots]
    for robot_id, rep in zip(robots, reports, strict=True):
        assert rep.summary is not None
        assert rep.summary.read_text().startswith(f"# Run report: rec.rrd, robot {robot_id}")


def test_no_display_reason_reads_the_x11_and_wayland_variables():
    assert no_display_reason({}) is not None
    assert no_display_reason({"DISPLAY": ""}) is not None
    assert no_display_reason({"DISPLAY": ":0"}) is None
    assert no_display_reason({"WAYLAND_DISPLAY": "wayland-0"}) is None


def test_spawn_without_a_display_records_the_whole_run_to_the_file(tmp_path, monkeypatch):
    """recorder.spawn on a machine without a display: no viewer is started (it could not
    open a window, and a sink to it stalled the recording: a tenth of the run reached
    the file), the summary says why, and the file has every record."""
    for name in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"):
        monkeypatch.delenv(name, raising=False)
    config = make_config(tmp_path / "spawn.rrd", free_endpoint(), "recorder.spawn=true")
    file = RecordingFile(config, Segment.only(tmp_path / "spawn.rrd"))
    writer = recording.RecordingWriter(config, file, m.DropCounter())
    file.open()
    writer.open()
    for i in range(50):
        writer.buffers["plant_state"](build("plant_state", i), 0)
    writer.close()
    file.close()
    assert writer.stats()["viewer"].startswith("not spawned: no display")
    rec = Recording(tmp_path / "spawn.rrd")
    q = rec.scalars(ent.TIMELINE_SIM)[ent.joint_entity(ent.ENTITY_JOINT_Q, JOINTS[0])]
    assert len(q.t_ns) == 50


def test_a_long_recording_goes_on_in_segments_each_one_whole(rig_factory, tmp_path):
    """Past ``recorder.segment_mb`` the recorder closes its file (footer written: Rerun's
    own check passes) and goes on in the next segment, which carries the blueprint and
    every static entity again (it opens alone); the segments together hold every record."""
    rig = rig_factory(r.RecorderService, "recorder.segment_mb=0.02")
    rounds = 4
    per_round = {"plant_state": 100, "tool_pose": 100}
    for k in range(rounds):
        flushes = rig.service.writer.flushes
        rig.publish(per_round, first=k * 100)
        assert rig.service.writer.wait_flushes(flushes + 2, TIMEOUT_S)
    rig.finish()
    segments = segment_paths(rig.service.file.segment.recording_path)
    assert len(segments) >= 2 and rig.service.file.segments_closed == len(segments) - 1
    assert rerun_verify_problems(segments[0]) == []
    ledger = json.loads((tmp_path / RECORDER_SEGMENTS_FILE).read_text())
    assert ledger["segments"] == [str(p) for p in segments]
    whole = read_rrd(segments[0])
    q = series(whole, ent.joint_entity(ent.ENTITY_JOINT_Q, JOINTS[0]))
    assert sorted(q) == [sim_ns(i) for i in range(rounds * 100)]  # nothing lost between
    assert all(Recording(p, one_segment=True).has_blueprint for p in segments)
    newest = Recording(segments[-1], one_segment=True)
    statics = [e for e in newest.entities if e.startswith(ent.ENTITY_WORLD)]
    assert statics, "the scene's static entities are in the newest segment too"
