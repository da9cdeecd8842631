"""The operator service as a real process on an isolated bus, in lockstep."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from teleop.bus.messages import (
    HAND_INPUT,
    OBJECT_POSES,
    RUN_EVENT,
    TOOL_POSE,
    Button,
    DropCounter,
    Event,
)
from teleop.bus.session import Publisher, close_session, open_session, subscribe, wait_alive
from teleop.bus.topics import Topics
from teleop.core.config import REPO_ROOT, load_config
from teleop.core.net import free_loopback_port
from teleop.core.ticks import is_sample_tick, lead_ticks
from tests.unit.test_operator import BIN_M, CUBE_M, HOME_TOOL_M

ALIVE_TIMEOUT_S = 60.0
RECORD_TIMEOUT_S = 10.0
RUN_S = 0.6  # sim time the test feeds the operator


# --- the service as a real process -------------------------------------------------------


class Bus:
    """The test's own session: the run's listener, feeding poses and collecting outputs."""

    def __init__(self, config) -> None:
        self.config = config
        self.tick_ns = round(config.tick_s * 1e9)  # one plant tick: one bus period
        self.topics = Topics(config.robot.robot_id)
        self.session = open_session(config.bus, listen=True)
        self.drops = DropCounter()
        self.cond = threading.Condition()
        self.hands: dict[int, np.ndarray] = {}
        self.events: list[tuple[int, int, float]] = []
        self.tool = Publisher.declare(self.session, self.topics.tool_pose, TOOL_POSE)
        self.objects = Publisher.declare(self.session, self.topics.objects, OBJECT_POSES)
        self.entities = [
            subscribe(self.session, self.topics.hand_input, HAND_INPUT, self._on_hand, self.drops),
            subscribe(
                self.session, self.topics.operator_events, RUN_EVENT, self._on_event, self.drops
            ),
        ]

    def _on_hand(self, rec: np.ndarray, rx_ns: int) -> None:
        with self.cond:
            self.hands[int(rec["valid_from_tick"])] = rec.copy()
            self.cond.notify_all()

    def _on_event(self, rec: np.ndarray, rx_ns: int) -> None:
        with self.cond:
            self.events.append((int(rec["event"]), int(rec["step"]), float(rec["value"])))
            self.cond.notify_all()

    def publish_scene(self, tick: int, tool_m: np.ndarray) -> None:
        objects = OBJECT_POSES.new()
        objects["sim_time_ns"] = tick * self.tick_ns
        objects["n_objects"] = 2
        objects["world_p_m"][:2] = [CUBE_M, BIN_M]
        objects["world_q_wxyz"][:2, 0] = 1.0
        tool = TOOL_POSE.new()
        tool["sim_time_ns"] = objects["sim_time_ns"]
        tool["world_p_tool_m"] = tool_m
        tool["world_q_tool_wxyz"][0] = 1.0
        self.objects.put(objects)
        self.tool.put(tool)

    def wait_hand(self, valid_from_tick: int) -> np.ndarray:
        with self.cond:
            ok = self.cond.wait_for(lambda: valid_from_tick in self.hands, RECORD_TIMEOUT_S)
            assert ok, f"no HAND_INPUT valid from {valid_from_tick}; got {sorted(self.hands)}"
            return self.hands[valid_from_tick]

    def close(self) -> None:
        close_session(self.session, self.tool, self.objects, *self.entities)


@pytest.fixture
def operator_process(tmp_path: Path):
    overrides = [f'bus.endpoint="tcp/127.0.0.1:{free_loopback_port()}"', 'run.mode="lockstep"']
    config = load_config(None, overrides)
    bus = Bus(config)
    command = [sys.executable, str(REPO_ROOT / "services" / "operator.py"), "--run-dir"]
    command += [str(tmp_path)]
    for override in overrides:
        command += ["--set", override]
    with open(tmp_path / "operator.log", "w") as log:
        proc = subprocess.Popen(
            command, cwd=REPO_ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=log,
        )  # fmt: skip
        try:
            wait_alive(bus.session, bus.topics, ["operator"], ALIVE_TIMEOUT_S)
            yield bus, proc, tmp_path
        finally:
            proc.terminate()
            proc.wait(timeout=30)
            bus.close()


def test_operator_service_answers_each_scene_tick_toward_the_cube(operator_process):
    bus, proc, run_dir = operator_process
    config = bus.config
    tick_s, rate_hz = config.tick_s, config.operator.decision_rate_hz
    # The plant's TOOL_POSE period (ticks), as PlantStepCore sends them.
    scene_period = max(1, round(1 / (config.plant.scene_rate_hz * tick_s)))
    lead = lead_ticks(rate_hz, tick_s)  # a decision at s is valid from s + lead
    seen_from = round(config.operator.reaction_delay_s / tick_s)  # first tick it sees tick 0
    last_tick = round(RUN_S / tick_s)
    tool_m = HOME_TOOL_M.copy()
    decided: list[int] = []  # the sample ticks decided so far
    for tick in range(0, last_tick + 1, scene_period):
        bus.publish_scene(tick, tool_m)
        # Lockstep: one record per sample tick up to this pose, each valid lead ticks on.
        first = decided[-1] + 1 if decided else 0
        for s in (s for s in range(first, tick + 1) if is_sample_tick(s, rate_hz, tick_s)):
            decided.append(s)
            hand = bus.wait_hand(s + lead)
            assert int(hand["buttons"]) == Button.NONE  # approach: gripper open, no clutch
            if s < seen_from:  # nothing seen yet (the reaction delay): the hand rests
                assert not hand["target_p_m"].any()
    assert sorted(bus.hands) == [s + lead for s in decided]
    assert decided[0] == 0 and any(s > seen_from for s in decided)
    # Toward the approach point above the cube (yaw 0 without an HMD: device = world).
    goal = CUBE_M + [0.0, 0.0, 0.12] - tool_m
    offsets = [bus.hands[s + lead]["target_p_m"] for s in decided if s > seen_from]
    for offset in offsets:
        cosine = offset @ goal / (np.linalg.norm(offset) * np.linalg.norm(goal))
        assert cosine > 0.999
    norms = [np.linalg.norm(o) for o in offsets]
    assert np.all(np.diff(norms) > 0)  # the hand moves out smoothly (low-pass)
    # The task began at the first sample tick that saw anything.
    began = next(s for s in decided if s >= seen_from)
    with bus.cond:
        assert (Event.PHASE, began, 0.0) in bus.events
    proc.terminate()
    assert proc.wait(timeout=30) == 0
    summary = (run_dir / "operator.summary.json").read_text()
    assert '"name": "approach"' in summary
