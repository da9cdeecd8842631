"""The eye view service on a real Zenoh bus: bad input counted and dropped, frames follow
the newest state and head pose."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from services.eyeview import EyeViewService
from teleop.bus.messages import EYE_VIEW, HEAD_POSE, PLANT_STATE, DropCounter
from teleop.bus.service import ServiceOptions
from teleop.bus.session import (
    Latest,
    Publisher,
    close_session,
    open_session,
    subscribe_frames,
    wait_alive,
)
from teleop.bus.topics import Topics
from teleop.core.config import load_config
from teleop.core.net import free_loopback_port
from teleop.run.stack import EYEVIEW

TIMEOUT_S = 30.0  # bound on one wait on the bus; passing runs take well under a second


def test_the_service_renders_the_newest_state_and_head_pose_and_survives_bad_input(tmp_path):
    """EyeViewService on a real Zenoh bus (in a thread: the GL context lives where it was
    built): bad states are counted and dropped, frames follow the newest state, and the
    view moves to the HMD's predicted pose once HEAD_POSE arrives.

    Ingress downsampling is off (``state_rate_hz = 0``): it would keep only the first of
    three states sent back to back (at any rate: one TCP read may hold all three).

    Frames go over the socket (``bus.shm = false``): publisher and receiver are this one
    test process, which under an ordinary user's locked-memory limit may already have
    spent it on pools mapped by earlier tests, and a pool a receiver cannot map is
    silently not received (shm/provider.py). As ``nobody``, after the e2e tests in one
    pytest process, no frame came. Frames through shared memory, within the limit, are
    test_unprivileged.py's and the stack tests'."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    config = load_config(
        None,
        [f'bus.endpoint="{endpoint}"', "eyeview.rate_hz=50", "eyeview.state_rate_hz=0",
         "bus.shm=false"],
    )  # fmt: skip
    topics = Topics(config.robot.robot_id)
    holder: list[EyeViewService] = []
    stop, opened = threading.Event(), threading.Event()

    def serve() -> None:
        with EyeViewService(config, ServiceOptions(run_dir=tmp_path, listen=True)) as service:
            holder.append(service)
            opened.set()
            service.run(stop)

    worker = threading.Thread(target=serve)
    worker.start()
    session = open_session(config.bus, listen=False)
    frames = Latest()
    drops = DropCounter()
    sub = subscribe_frames(
        session, topics.eye_view, EYE_VIEW, lambda rec, px, rx, shm: frames(rec.copy(), rx), drops
    )
    state_pub = Publisher.declare(session, topics.plant_state_batch, PLANT_STATE)  # a batch of 1
    head_pub = Publisher.declare(session, topics.head_pose, HEAD_POSE)
    try:
        assert opened.wait(TIMEOUT_S)
        wait_alive(session, topics, [EYEVIEW], TIMEOUT_S)
        assert state_pub.wait_matched(TIMEOUT_S)
        service = holder[0]
        state_pub.put_bytes(b"garbage")
        wrong = PLANT_STATE.new()
        wrong["n_joints"] = 3
        state_pub.put(wrong)
        state = PLANT_STATE.new()
        state["seq"], state["sim_time_ns"], state["n_joints"] = 7, 5_000_000, 6
        state["q_rad"][:6] = config.robot.home_q_rad
        state_pub.put(state)
        got = frames.wait_newer(-1, TIMEOUT_S)
        assert got is not None
        while int(got[0]["state_seq"]) != 7:  # frames rendered before the state arrived
            got = frames.wait_newer(int(got[0]["seq"]), TIMEOUT_S)
            assert got is not None
        rec = got[0]
        assert int(rec["sim_time_ns"]) == 5_000_000 and int(rec["head_t_source_ns"]) == 0
        np.testing.assert_allclose(rec["world_p_eye_m"], config.eyeview.fixed_p_m)
        assert service.drops.total == 2  # the garbage and the 3-joint state, nothing else

        head = HEAD_POSE.new()
        head["seq"], head["t_source_ns"] = 3, time.monotonic_ns()
        head["predicted_p_m"] = (-0.5, 0.2, 0.7)
        head["predicted_yaw_rad"], head["predicted_pitch_rad"] = 0.3, 0.1
        head_pub.put(head)
        while int(got[0]["head_seq"]) != 3:
            got = frames.wait_newer(int(got[0]["seq"]), TIMEOUT_S)
            assert got is not None
        rec = got[0]
        assert int(rec["head_t_source_ns"]) == int(head["t_source_ns"])
        assert int(rec["head_t_source_ns"]) < int(rec["head_rx_ns"]) <= int(rec["render_start_ns"])
        assert int(rec["render_start_ns"]) < int(rec["render_end_ns"]) <= int(rec["publish_ns"])
        np.testing.assert_allclose(rec["world_p_eye_m"], head["predicted_p_m"])
        assert float(rec["yaw_rad"]) == pytest.approx(0.3)
        assert drops.total == 0
    finally:
        stop.set()
        worker.join(TIMEOUT_S)
        close_session(session, sub, state_pub, head_pub)
    assert not worker.is_alive()
    summary = json.loads((tmp_path / "eyeview.summary.json").read_text())
    assert summary["frames_from_hmd"] > 0 and summary["dropped_messages"] == 2
