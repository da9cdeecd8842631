"""The scripted operator: scenario files, the inverse mapping, the closed loop, the service."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import tomllib
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
from teleop.core.config import DEPLOY_DIR, REPO_ROOT, load_config
from teleop.devices.operator import (
    ObservationBuffer,
    Scenario,
    ScenarioError,
    ScriptedOperator,
    Target,
    critical_gain_per_s,
    hand_offset_for_velocity,
    rot_z,
)
from teleop.run.stack import free_loopback_port

TIMESTEP_S = 0.001
GRASP_FILE = DEPLOY_DIR / "scenarios" / "grasp.toml"
CUBE_M = np.array([0.45, -0.25, 0.025])
BIN_M = np.array([0.35, 0.35, 0.0])
HOME_TOOL_M = np.array([0.40, 0.0, 0.40])
GRASP_RADIUS_M = 0.01  # the simulated gripper takes the cube when its centre is this close
ALIVE_TIMEOUT_S = 60.0
RECORD_TIMEOUT_S = 10.0


def reference_tool_velocity(offset_m, yaw_rad, teleop) -> np.ndarray:
    """The controller's documented rate mapping, written out independently."""
    radius = float(np.linalg.norm(offset_m))
    if radius <= teleop.deadband_m:
        return np.zeros(3)
    device_v = teleop.rate_gain_per_s * (radius - teleop.deadband_m) * np.asarray(offset_m) / radius
    speed = np.linalg.norm(device_v)
    if speed > teleop.max_tool_speed_m_s:
        device_v = device_v * teleop.max_tool_speed_m_s / speed
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ device_v


def grasp_table() -> dict:
    return tomllib.loads(GRASP_FILE.read_text())


# --- scenario files ------------------------------------------------------------------------


def test_grasp_scenario_loads_with_the_task_numbers():
    scenario = Scenario.load(GRASP_FILE)
    names = [p.name for p in scenario.phases]
    assert names == [
        "approach", "open", "descend", "close", "lift", "carry", "release", "retreat",
    ]  # fmt: skip
    by_name = {p.name: p for p in scenario.phases}
    assert by_name["approach"].target.offset_m == (0.0, 0.0, 0.12)
    assert by_name["descend"].target.relative_to == "cube"
    assert by_name["close"].gripper_closed and by_name["close"].dwell_s == 0.6
    assert by_name["carry"].target.relative_to == "bin" and by_name["carry"].carrying
    assert not by_name["release"].gripper_closed
    assert by_name["retreat"].target == Target("tool", (0.0, 0.0, 0.1))
    assert scenario.anchors == {"cube", "bin"}
    assert load_config().operator.scenario_path == GRASP_FILE


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t["phase"][2].update(speed=1.0), "phase 2 ('descend'): unknown key(s) speed"),
        (lambda t: t["phase"][1].pop("target"), "phase 1 ('open'): missing key(s) target"),
        (lambda t: t["phase"][0].update(tolerance_m=-0.01), "tolerance_m: must be > 0"),
        (lambda t: t["phase"][0].update(timeout_s="soon"), "timeout_s: expected a number"),
        (lambda t: t["phase"][3].update(dwell_s=9.0), "dwell_s (9) must be below timeout_s"),
        (lambda t: t["phase"][0]["target"].update(relative_to="table"), "relative_to 'table'"),
        (lambda t: t["phase"][0]["target"].update(offset_m=[0, 0]), "expected [x, y, z]"),
        (lambda t: t["phase"][0]["target"].update(offset_m=[0, 0, math.inf]), "must be finite"),
        (lambda t: t["phase"][0].update(gripper="half"), "gripper 'half': one of open, closed"),
        (lambda t: t["task"].pop("max_task_s"), "[task]: missing key(s) max_task_s"),
        (lambda t: t.update(phases=[]), "unknown key(s) phases"),
        (lambda t: t.update(phase=[]), "no [[phase]] tables"),
    ],
)
def test_scenario_validation_names_the_problem(edit, message):
    table = grasp_table()
    edit(table)
    with pytest.raises(ScenarioError) as err:
        Scenario.from_table(table, source="grasp.toml")
    assert message in str(err.value)
    assert str(err.value).startswith("grasp.toml: ")


def test_scenario_file_errors(tmp_path):
    with pytest.raises(ScenarioError, match="not found"):
        Scenario.load(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[task\n")
    with pytest.raises(ScenarioError, match="bad.toml"):
        Scenario.load(bad)


# --- the inverse mapping and the gain ------------------------------------------------------


@pytest.mark.parametrize("yaw_rad", [0.0, 0.3, -1.2, math.pi])
@pytest.mark.parametrize(
    "world_v", [(0.1, 0.0, 0.0), (0.0, -0.05, 0.02), (0.03, 0.04, -0.12), (0.0, 0.0, 0.002)]
)
def test_inverse_mapping_gives_back_the_intended_velocity(yaw_rad, world_v):
    teleop = load_config().teleop
    offset = hand_offset_for_velocity(np.array(world_v), yaw_rad, teleop)
    # Beyond the deadband by exactly speed / gain: the deadband was added back.
    expected_radius = np.linalg.norm(world_v) / teleop.rate_gain_per_s + teleop.deadband_m
    assert np.linalg.norm(offset) == pytest.approx(expected_radius)
    back = reference_tool_velocity(offset, yaw_rad, teleop)
    np.testing.assert_allclose(back, world_v, atol=1e-12)


def test_inverse_mapping_at_rest_and_the_view_rotation():
    teleop = load_config().teleop
    assert not hand_offset_for_velocity(np.zeros(3), 0.7, teleop).any()
    # Looking along +y (yaw 90 deg), "forward" on the handle is world +y.
    offset = hand_offset_for_velocity(np.array([0.0, 0.1, 0.0]), math.pi / 2, teleop)
    np.testing.assert_allclose(offset / np.linalg.norm(offset), [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(rot_z(0.4) @ rot_z(-0.4), np.eye(3), atol=1e-15)


def test_critical_gain_limits():
    assert critical_gain_per_s(0.2, 0.0) == pytest.approx(1 / (math.e * 0.2))
    assert critical_gain_per_s(0.0, 0.15) == pytest.approx(1 / (4 * 0.15))
    k = critical_gain_per_s(0.25, 0.15)
    assert critical_gain_per_s(0.25, 1e-9) > k > critical_gain_per_s(0.25, 0.3)
    assert k * 0.25 < math.pi / 2 / 4  # far inside the delayed loop's stability bound


# --- the closed loop, simulated in Python ------------------------------------------------


class IntegratorWorld:
    """The robot as a pure integrator of the mapped handle velocity.

    Decisions at 100 Hz on 1 kHz ticks, each applied from ``tick + lead`` (plus an optional
    extra lag standing in for the handle's dynamics); the operator sees every sample
    ``reaction_delay_s`` late through an :class:`ObservationBuffer`. The cube moves with
    the tool while the gripper is closed and the cube was within GRASP_RADIUS_M when it
    closed; ``sag_m_s`` is a downward drift while holding (the cube's weight on the handle).
    """

    def __init__(self, scenario: Scenario, *, extra_lag_ticks: int = 0, sag_m_s: float = 0.0):
        cfg = load_config()
        self.cfg = cfg
        self.operator = ScriptedOperator(scenario, cfg.operator, cfg.teleop, cfg.haptic, TIMESTEP_S)
        delay = round(cfg.operator.reaction_delay_s / TIMESTEP_S)
        self.buffer = ObservationBuffer(("cube", "bin"), delay, cfg.hmd.head_yaw_rad)
        self.period = round(1.0 / (cfg.operator.decision_rate_hz * TIMESTEP_S))
        self.lag = self.period + extra_lag_ticks
        self.sag_m_s = sag_m_s
        self.tool = HOME_TOOL_M.copy()
        self.cube = CUBE_M.copy()
        self.trace: list[tuple[int, int, np.ndarray, float]] = []  # tick, phase, tool, speed

    def yaw(self, tick: int) -> float:
        """The HMD's slow sway (rad): the operator sees it late, the controller now."""
        return 0.25 * math.sin(2 * math.pi * tick * TIMESTEP_S / 7.0) + 0.3

    def run(self, max_s: float) -> ScriptedOperator:
        pending: dict[int, tuple[np.ndarray, Button]] = {}
        hand, buttons = np.zeros(3), Button.NONE
        held: np.ndarray | None = None
        for tick in range(round(max_s / TIMESTEP_S)):
            if tick % self.period == 0:
                self.buffer.add_tool(tick, self.tool)
                self.buffer.add_objects(tick, np.array([self.cube, BIN_M]))
                self.buffer.add_head(tick, self.yaw(tick))
                command = self.operator.decide(tick, self.buffer.observe(tick))
                pending[tick + self.lag] = (command.target_p_m, command.buttons)
                if command.done:
                    return self.operator
            if tick in pending:
                hand, buttons = pending.pop(tick)
            v = reference_tool_velocity(hand, self.yaw(tick), self.cfg.teleop)
            closed = bool(buttons & Button.GRIPPER_CLOSE)
            if closed and held is None and np.linalg.norm(self.cube - self.tool) < GRASP_RADIUS_M:
                held = self.cube - self.tool
            elif not closed and held is not None:
                held = None
                self.cube = np.array([*self.cube[:2], BIN_M[2] + 0.035])  # drops onto the floor
            if held is not None:
                v = v + np.array([0.0, 0.0, -self.sag_m_s])
            self.tool = self.tool + v * TIMESTEP_S
            if held is not None:
                self.cube = self.tool + held
            self.trace.append((tick, self.operator.phase, self.tool.copy(), np.linalg.norm(v)))
        return self.operator


@pytest.mark.parametrize(
    ("extra_lag_ticks", "sag_m_s"), [(0, 0.0), (60, 0.0), (0, 0.03)], ids=["plain", "lag", "sag"]
)
def test_operator_plays_the_grasp_task_to_success(extra_lag_ticks, sag_m_s):
    scenario = Scenario.load(GRASP_FILE)
    world = IntegratorWorld(scenario, extra_lag_ticks=extra_lag_ticks, sag_m_s=sag_m_s)
    operator = world.run(scenario.max_task_s + 1.0)
    assert operator.done and operator.success, operator.failure
    assert len(operator.phase_start_ticks) == len(scenario.phases)
    assert np.all(np.diff(operator.phase_start_ticks) > 0)
    # The cube ended in the bin, and the operator never asked for more than its cap.
    assert np.all(np.abs(world.cube[:2] - BIN_M[:2]) < 0.09 - 0.025)
    speeds = np.array([s for *_, s in world.trace])
    assert speeds.max() <= world.cfg.teleop.max_tool_speed_m_s * 0.8 + 1e-9
    # The descent never went below the cube centre (the fingertips stay off the table).
    descend = scenario.phases.index(next(p for p in scenario.phases if p.name == "descend"))
    z_descend = [tool[2] for _, phase, tool, _ in world.trace if phase == descend]
    assert min(z_descend) > CUBE_M[2] - 1e-3


@pytest.mark.parametrize("extra_lag_ticks", [0, 100])
def test_delayed_p_loop_converges_without_overshoot(extra_lag_ticks):
    """One long-dwell phase: the tool must settle on the target from one side only."""
    table = grasp_table()
    descend = next(p for p in table["phase"] if p["name"] == "descend")
    table["phase"] = [{**descend, "tolerance_m": 0.001, "dwell_s": 8.0, "timeout_s": 25.0}]
    world = IntegratorWorld(Scenario.from_table(table), extra_lag_ticks=extra_lag_ticks)
    operator = world.run(20.0)
    tool = np.array([p for _, _, p, _ in world.trace])
    direction = (CUBE_M - HOME_TOOL_M) / np.linalg.norm(CUBE_M - HOME_TOOL_M)
    overshoot_m = float(((tool - CUBE_M) @ direction).max())
    assert overshoot_m < 0.0, f"overshoot {overshoot_m * 1e3:.2f} mm"
    assert np.linalg.norm(tool[-1] - CUBE_M) < 0.001
    assert operator.done and operator.success  # the 8 s dwell inside 1 mm completed


def test_timeout_ends_the_task_without_success():
    table = grasp_table()
    table["phase"][0]["timeout_s"] = 1.0  # the approach takes about 4 s
    world = IntegratorWorld(Scenario.from_table(table))
    operator = world.run(10.0)
    assert operator.done and not operator.success
    assert "timeout in approach" in operator.failure
    assert operator.done_tick * TIMESTEP_S == pytest.approx(0.2 + 1.0, abs=0.02)


def test_observation_buffer_returns_what_was_seen_a_delay_ago():
    buffer = ObservationBuffer(("cube", "bin"), delay_ticks=200, default_yaw_rad=0.1)
    assert buffer.observe(1000) is None
    for tick in range(0, 1001, 10):
        buffer.add_tool(tick, [tick * 1e-3, 0, 0])
        buffer.add_objects(tick, np.array([[0, tick * 1e-3, 0], [1, 1, 0]]))
    seen = buffer.observe(1005)
    assert seen.tick == 800 and seen.tool_p_m[0] == pytest.approx(0.8)
    assert seen.objects_p_m["cube"][1] == pytest.approx(0.8) and seen.view_yaw_rad == 0.1
    buffer.add_head(790, 0.5)
    buffer.add_head(812, 0.7)
    assert buffer.observe(1005).view_yaw_rad == 0.5
    assert buffer.ready(1005, 790) and not buffer.ready(1005, 801)
    buffer.add_tool(0, [9, 9, 9])  # a new run: the tool's history starts over
    assert buffer.observe(1005).tool_p_m[0] == 9


# --- the service as a real process -------------------------------------------------------


class Bus:
    """The test's own session: the run's listener, feeding poses and collecting outputs."""

    def __init__(self, config) -> None:
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
            subscribe(self.session, self.topics.events, RUN_EVENT, self._on_event, self.drops),
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
        objects["sim_time_ns"] = tick * round(TIMESTEP_S * 1e9)
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
    tool_m = HOME_TOOL_M.copy()
    last_tick = 600
    for tick in range(0, last_tick + 1, 10):
        bus.publish_scene(tick, tool_m)
        hand = bus.wait_hand(tick + 10)  # lockstep: one record per sample tick, lead 10
        assert int(hand["buttons"]) == Button.NONE  # approach: gripper open, no clutch
        if tick < 200:  # nothing seen yet (0.2 s reaction delay): the hand rests
            assert not hand["target_p_m"].any()
    assert sorted(bus.hands) == list(range(10, last_tick + 11, 10))
    # Toward the approach point above the cube (yaw 0 without an HMD: device = world).
    goal = CUBE_M + [0.0, 0.0, 0.12] - tool_m
    offsets = [bus.hands[t + 10]["target_p_m"] for t in range(210, last_tick + 1, 10)]
    for offset in offsets:
        cosine = offset @ goal / (np.linalg.norm(offset) * np.linalg.norm(goal))
        assert cosine > 0.999
    norms = [np.linalg.norm(o) for o in offsets]
    assert np.all(np.diff(norms) > 0)  # the hand moves out smoothly (low-pass)
    with bus.cond:
        assert (Event.PHASE, 200, 0.0) in bus.events  # the task began once seen
    proc.terminate()
    assert proc.wait(timeout=30) == 0
    summary = (run_dir / "operator.summary.json").read_text()
    assert '"name": "approach"' in summary
