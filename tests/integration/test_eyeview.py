"""The operator's eye view: the renderer mirrors the plant and looks where the head does;
frames reach the recorder over shared memory in a real services run and land in the .rrd.
"""

from __future__ import annotations

import io
import json
import math
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from services.eyeview import EyeRenderer, EyeViewService, camera_forward
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
from teleop.run.stack import EYEVIEW, free_loopback_port, scenario_services
from teleop.viz import entities as ent
from tests.integration.test_recorder import read_rrd

# Mean absolute pixel difference (0-255) above which two renders show different scenes;
# identical inputs give exactly 0.
CHANGED_MEAN_ABS_DIFF = 1.0
RUN_TIMEOUT_S = 300
TIMEOUT_S = 30.0  # bound on one wait on the bus; passing runs take well under a second


@pytest.fixture(scope="module")
def renderer():
    eye = EyeRenderer(load_config())
    yield eye
    eye.close()


def _view(eye: EyeRenderer, config_yaw: float = 0.0) -> np.ndarray:
    cfg = load_config().eyeview
    return eye.render(np.array(cfg.fixed_p_m), config_yaw, cfg.fixed_pitch_rad).copy()


def _diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(np.int16) - b.astype(np.int16)).mean())


@pytest.mark.parametrize(("yaw_rad", "pitch_rad"), [(0.0, 0.5), (0.7, -0.2), (-2.5, 0.1)])
def test_the_camera_sits_at_the_head_and_looks_along_yaw_and_pitch(renderer, yaw_rad, pitch_rad):
    p_m = np.array([-0.4, 0.1, 0.6])
    renderer.render(p_m, yaw_rad, pitch_rad)
    np.testing.assert_allclose(renderer.eye_position_m(), p_m, atol=1e-6)
    forward = np.array(renderer.renderer.scene.camera[0].forward)
    np.testing.assert_allclose(forward, camera_forward(yaw_rad, pitch_rad), atol=1e-6)
    assert camera_forward(0.0, 0.3)[2] < 0  # positive pitch looks down


def test_the_mirror_follows_joints_gripper_and_objects(renderer):
    config = load_config()
    home = np.array(config.robot.home_q_rad)
    cube_p = np.array([[0.45, -0.25, 0.025], [0.35, 0.35, 0.0]])
    cube_q = np.array([[1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
    renderer.set_state(home, 0.02, cube_p, cube_q)
    base = _view(renderer)
    assert base.shape == (config.eyeview.height_px, config.eyeview.width_px, 3)
    assert _diff(base, _view(renderer)) == 0.0  # same inputs, same picture
    turned = home.copy()
    turned[0] += 0.8
    renderer.set_state(turned, 0.02, cube_p, cube_q)
    assert _diff(base, _view(renderer)) > CHANGED_MEAN_ABS_DIFF
    moved = cube_p.copy()
    moved[0] = [0.2, 0.1, 0.3]  # the cube lifted into view
    renderer.set_state(home, 0.02, moved, cube_q)
    cube_moved = _view(renderer)
    assert _diff(base, cube_moved) > 0.0
    renderer.set_state(home, 0.02, cube_p, cube_q)
    assert _diff(base, _view(renderer)) == 0.0


def test_the_stack_runs_the_eye_view_only_when_enabled():
    grasp = load_config(None, ['run.scenario="grasp"'])
    assert EYEVIEW in scenario_services(grasp)
    assert EYEVIEW in scenario_services(load_config())
    assert EYEVIEW not in scenario_services(load_config(None, ["eyeview.enabled=false"]))
    lockstep = 'run.mode="lockstep"'
    assert EYEVIEW not in scenario_services(load_config(None, [lockstep]))
    assert EYEVIEW in scenario_services(load_config(None, [lockstep, "eyeview.in_lockstep=true"]))


def _run(tmp_path: Path, name: str, *overrides: str) -> dict:
    out = tmp_path / f"{name}.json"
    sets = [arg for o in overrides for arg in ("--set", o)]
    result = subprocess.run(
        [
            sys.executable, "-m", "teleop.cli", "run", "path-following", "--mode", "realtime",
            "--duration", "2", "--set", "run.settle_s=1", *sets,
            "--run-dir", str(tmp_path / name), "--summary-json", str(out), "--quiet",
        ],
        capture_output=True, text=True, timeout=RUN_TIMEOUT_S, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads(out.read_text())


def test_frames_reach_the_recorder_over_shared_memory_and_land_in_the_rrd(tmp_path):
    summary = _run(tmp_path, "shm", "eyeview.rate_hz=20")
    eye = summary["eye_view"]
    assert eye["frames_published"] > 0
    assert eye["frames_received"] == eye["frames_published"]
    assert eye["frames_received_shm"] == eye["frames_received"]  # every one over SHM
    assert summary["dropped_messages"] == 0
    latency = eye["latency_ms"]["publish_to_received_ms"]
    assert latency["count"] == eye["frames_received"] and latency["p50"] > 0

    data = read_rrd(Path(summary["rrd"]))
    cols = data[ent.ENTITY_EYE_VIEW]
    blobs = cols["EncodedImage:blob"]
    assert len(blobs) == eye["frames_received"]
    assert all(m == ["image/jpeg"] for m in cols["EncodedImage:media_type"])
    config = load_config()
    image = Image.open(io.BytesIO(bytes(blobs[0][0])))
    assert image.size == (config.eyeview.width_px, config.eyeview.height_px)
    # Logged at the plant's sim time of the state each frame shows (whole plant ticks,
    # within the run), not at arrival time.
    sim_ns = np.array(cols[ent.TIMELINE_SIM])
    step_ns = round(config.plant.timestep_s * 1e9)
    assert np.all(sim_ns % step_ns == 0) and sim_ns.max() <= 2 * 10**9
    assert len(set(cols[ent.TIMELINE_SOURCE])) == len(blobs)


def test_without_shared_memory_the_frames_come_over_the_socket(tmp_path):
    """The SHM assertion above can fail: with SHM off the same frames arrive inline.

    Also logs them raw (``jpeg_quality=0``): RGB images of the configured size."""
    summary = _run(tmp_path, "noshm", "bus.shm=false", "eyeview.jpeg_quality=0")
    eye = summary["eye_view"]
    assert eye["frames_received"] > 0
    assert eye["frames_received_shm"] == 0
    buffers = read_rrd(Path(summary["rrd"]))[ent.ENTITY_EYE_VIEW]["Image:buffer"]
    assert len(buffers) == eye["frames_received"]
    cfg = load_config().eyeview
    assert {len(b[0]) for b in buffers} == {cfg.width_px * cfg.height_px * 3}


def test_fixed_viewpoint_pitch_is_refused_beyond_straight_down():
    with pytest.raises(ValueError, match="fixed_pitch_rad"):
        load_config(None, [f"eyeview.fixed_pitch_rad={math.pi / 2}"])


def test_the_service_renders_the_newest_state_and_head_pose_and_survives_bad_input(tmp_path):
    """EyeViewService on a real Zenoh bus (in a thread: the GL context lives where it was
    built): bad states are counted and dropped, frames follow the newest state, and the
    view moves to the HMD's predicted pose once HEAD_POSE arrives.

    Ingress downsampling is off (``state_rate_hz = 0``): it would keep only the first of
    three states sent back to back (at any rate: one TCP read may hold all three)."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    config = load_config(
        None, [f'bus.endpoint="{endpoint}"', "eyeview.rate_hz=50", "eyeview.state_rate_hz=0"]
    )
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
