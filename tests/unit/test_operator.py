"""The scripted operator, pure: scenario files (typed loading, repeats), the inverse
mapping, the closed loop, and the service's decision loop without a bus."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from teleop.bus.messages import Button, Event
from teleop.core.config import DEPLOY_DIR, Config, ConfigError, load_config
from teleop.core.ticks import is_sample_tick
from teleop.devices.scripted.loop import ScriptedLoop
from teleop.devices.scripted.operator import (
    HandCommand,
    Observation,
    ObservationBuffer,
    ScriptedOperator,
    critical_gain_per_s,
    hand_offset_for_velocity,
    resume_phase,
    rot_z,
)
from teleop.devices.scripted.routing import SceneKnowledge
from teleop.devices.scripted.scenario import Phase, Scenario, ScenarioError, Target

TIMESTEP_S = 0.001
GRASP_FILE = DEPLOY_DIR / "scenarios" / "grasp.toml"
CUBE_M = np.array([0.45, -0.25, 0.025])
BIN_M = np.array([0.35, 0.35, 0.0])
HOME_TOOL_M = np.array([0.40, 0.0, 0.40])
GRASP_RADIUS_M = 0.01  # the simulated gripper takes the cube when its centre is this close
LATENCY_FILE = DEPLOY_DIR / "scenarios" / "latency.toml"


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
        (
            lambda t: t["phase"][0]["target"].update(offset_m=[0, 0]),
            "phase 0 ('approach').target.offset_m: expected 3 items",
        ),
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


# The latency scenario as it was written out before the format had repeats: 90 phases
# shuttle_0 .. shuttle_89 cycling through four legs (y +-0.2 m, z +-0.03 m from the tool).
SHUTTLE_LEGS_M = [(0.0, 0.2, 0.03), (0.0, -0.2, 0.03), (0.0, 0.2, -0.03), (0.0, -0.2, -0.03)]
SHUTTLE_PHASES = 90


def test_latency_scenario_expands_to_the_90_shuttle_phases():
    scenario = Scenario.load(LATENCY_FILE)
    expected = [
        Phase(
            name=f"shuttle_{i}",
            target=Target("tool", SHUTTLE_LEGS_M[i % 4]),
            gripper="open",
            tolerance_m=0.02,
            timeout_s=20.0,
            dwell_s=0.0,
        )
        for i in range(SHUTTLE_PHASES)
    ]
    assert list(scenario.phases) == expected
    assert (scenario.max_task_s, scenario.held_object, scenario.carry_tolerance_m) == (
        600.0,
        "cube",
        0.03,
    )
    assert len(LATENCY_FILE.read_text().splitlines()) < 80


def test_repeat_entries_expand_in_place_with_numbered_names():
    table = grasp_table()
    first, second = table["phase"][0], table["phase"][1]
    table["phase"] = [
        first,
        {"repeat": 3, "block": [{**second, "name": "a"}, {**second, "name": "b"}]},
        {**second, "name": "last"},
    ]
    names = [p.name for p in Scenario.from_table(table).phases]
    assert names == ["approach", "a_0", "b_1", "a_2", "last"]


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ({"repeat": 0, "block": [{}]}, "phase 1 (repeat): repeat: must be >= 1"),
        ({"repeat": 2, "block": []}, "phase 1 (repeat): block: expected at least one"),
        ({"repeat": 2.5, "block": [{}]}, "phase 1 (repeat).repeat: expected an integer"),
        ({"repeat": 2}, "phase 1 (repeat): missing key(s) block"),
        ({"repeat": 2, "block": [{}], "name": "x"}, "phase 1 (repeat): unknown key(s) name"),
        (
            {"repeat": 2, "block": [{"name": "leg", "speed": 1}]},
            "phase 1 (repeat) block 0 ('leg'): unknown key(s) speed",
        ),
        (
            {"repeat": 2, "block": [{"name": "leg", "repeat": 2}]},
            "phase 1 (repeat) block 0 ('leg'): unknown key(s) repeat",
        ),
    ],
)
def test_repeat_errors_name_the_entry_and_the_key(entry, message):
    table = grasp_table()
    table["phase"] = [table["phase"][0], entry]
    with pytest.raises(ScenarioError) as err:
        Scenario.from_table(table, source="s.toml")
    assert str(err.value).startswith("s.toml: ")
    assert message in str(err.value)


def test_repeated_names_must_stay_unique():
    table = grasp_table()
    second = table["phase"][1]
    table["phase"] = [
        {**second, "name": "leg_1"},
        {"repeat": 2, "block": [{**second, "name": "leg"}]},
    ]
    with pytest.raises(ScenarioError, match="phase names must be unique"):
        Scenario.from_table(table)


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

    def __init__(
        self,
        scenario: Scenario,
        *,
        extra_lag_ticks: int = 0,
        sag_m_s: float = 0.0,
        scene: SceneKnowledge | None = None,
        reach_m: float = math.inf,
    ):
        cfg = load_config()
        self.cfg = cfg
        self.scenario = scenario
        self.scene = scene
        self.operator = self.new_operator()
        self.reach_m = reach_m  # the tool never gets farther than this from the origin
        self.buffer = self.new_buffer()
        self.period = round(1.0 / (cfg.operator.decision_rate_hz * TIMESTEP_S))
        self.lag = self.period + extra_lag_ticks
        self.sag_m_s = sag_m_s
        self.tool = HOME_TOOL_M.copy()
        self.cube = CUBE_M.copy()
        self.trace: list[tuple[int, int, np.ndarray, float]] = []  # tick, phase, tool, speed
        self.drops: list[np.ndarray] = []  # where the cube was when the gripper let it go

    def new_operator(self) -> ScriptedOperator:
        cfg = self.cfg
        return ScriptedOperator(
            self.scenario, cfg.operator, cfg.teleop, cfg.haptic, TIMESTEP_S, scene=self.scene
        )

    def new_buffer(self) -> ObservationBuffer:
        delay = round(self.cfg.operator.reaction_delay_s / TIMESTEP_S)
        return ObservationBuffer(("cube", "bin"), delay, self.cfg.hmd.head_yaw_rad)

    def yaw(self, tick: int) -> float:
        """The HMD's slow sway (rad): the operator sees it late, the controller now."""
        return 0.25 * math.sin(2 * math.pi * tick * TIMESTEP_S / 7.0) + 0.3

    def run(
        self,
        max_s: float,
        kill_in: tuple[str, float, float] | None = None,
        restart: bool = True,
        device_out: tuple[str, float, float] | None = None,
        told: bool = True,
        braked: tuple[str, float, float] | None = None,
        flagged: bool = True,
    ) -> ScriptedOperator:
        """Play until done or ``max_s``. ``kill_in`` = (phase name, s into it, outage s):
        the operator is killed that long into that phase and a new one (a restart, with
        nothing seen yet) joins after the outage; ``restart`` False: the same operator
        was only starved and decides again after the outage, from the newest look.
        Meanwhile no hand input comes: the hand holds its last one until it is
        ``haptic.hand_input_stale_s`` old, then centres the handle keeping its buttons
        (the haptic device's rule). ``device_out`` = (phase name, s into it, outage s): the
        haptic device is gone that long (nothing the hand does moves the tool; the grip
        holds); ``told``: the operator sees its token go (ScriptedOperator.device_gone).
        ``braked`` = (phase name, s into it, brake s): the plant's watchdog holds the tool
        that long (a silent controller, lost real time); ``flagged``: the tool samples
        say so (TOOL_POSE's BRAKING flag)."""
        pending: dict[int, tuple[np.ndarray, Button]] = {}
        hand, buttons = np.zeros(3), Button.NONE
        held: np.ndarray | None = None
        stale_ticks = round(self.cfg.haptic.hand_input_stale_s / TIMESTEP_S)
        hand_from = 0  # tick the hand input in effect applied from
        alive = True
        phase_began: dict[int, int] = {}
        back_tick = None
        device_back = None  # the tick the device comes back, while it is out
        device_done = device_out is None
        brake_ends = None  # the tick the plant stops braking, while it brakes
        brake_done = braked is None

        def outage_ends(spec: tuple[str, float, float], tick: int) -> int | None:
            """The tick an outage ``spec`` = (phase name, s into it, outage s) that begins
            at ``tick`` ends; None while it is not due."""
            phase = self.operator.phase
            phase_began.setdefault(phase, tick)
            name, into_s, outage_s = spec
            if phase < 0 or self.scenario.phases[phase].name != name:
                return None
            if tick - phase_began[phase] < round(into_s / TIMESTEP_S):
                return None
            return tick + round(outage_s / TIMESTEP_S)

        for tick in range(round(max_s / TIMESTEP_S)):
            if device_out is not None and not device_done and device_back is None:
                device_back = outage_ends(device_out, tick)
                if device_back is not None:
                    self.operator.device_gone = told
            if device_back is not None and tick == device_back:
                device_back, device_done = None, True
                self.operator.device_gone = False
            if braked is not None and not brake_done and brake_ends is None:
                brake_ends = outage_ends(braked, tick)
            if brake_ends is not None and tick == brake_ends:
                brake_ends, brake_done = None, True
            if kill_in is not None and alive and back_tick is None:
                back_tick = outage_ends(kill_in, tick)
                if back_tick is not None:
                    alive = False
                    pending.clear()  # what it sent before dying was lost with it
            if not alive and tick == back_tick:
                alive = True
                if restart:
                    self.operator, self.buffer = self.new_operator(), self.new_buffer()
                    self.operator.joining = True
            if tick % self.period == 0 and (alive or not restart):  # a starved one sees
                self.buffer.add_tool(tick, self.tool, flagged and brake_ends is not None)
                self.buffer.add_objects(tick, np.array([self.cube, BIN_M]))
                self.buffer.add_head(tick, self.yaw(tick))
            if alive and tick % self.period == 0:
                command = self.operator.decide(tick, self.buffer.observe(tick))
                if not (self.operator.joining and command.phase < 0):  # else withheld
                    pending[tick + self.lag] = (command.target_p_m, command.buttons)
                if command.done:
                    return self.operator
            if tick in pending:
                hand, buttons = pending.pop(tick)
                hand_from = tick
            elif tick - hand_from > stale_ticks:
                hand = np.zeros(3)
            v = reference_tool_velocity(hand, self.yaw(tick), self.cfg.teleop)
            if device_back is not None:
                v = np.zeros(3)  # no device: the controller commands no motion
            if brake_ends is not None:
                v = np.zeros(3)  # the plant holds the arm
            closed = bool(buttons & Button.GRIPPER_CLOSE)
            if closed and held is None and np.linalg.norm(self.cube - self.tool) < GRASP_RADIUS_M:
                held = self.cube - self.tool
            elif not closed and held is not None:
                held = None
                self.drops.append(self.cube.copy())
                self.cube = np.array([*self.cube[:2], BIN_M[2] + 0.035])  # drops onto the floor
            if held is not None:
                v = v + np.array([0.0, 0.0, -self.sag_m_s])
            self.tool = self.tool + v * TIMESTEP_S
            if np.linalg.norm(self.tool) > self.reach_m:  # the arm at full stretch
                self.tool *= self.reach_m / np.linalg.norm(self.tool)
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


# An obstacle on the straight carry from over the cube to over the bin (the default
# scene's lift and carry targets), and what the operator knows of it.
IN_THE_WAY_M = (0.40, 0.05, 0.19)
IN_THE_WAY_RADIUS_M = 0.05


def in_the_way_scene() -> SceneKnowledge:
    influence_m = load_config().teleop.obstacle_influence_m
    return SceneKnowledge(obstacles=((IN_THE_WAY_M, IN_THE_WAY_RADIUS_M),), influence_m=influence_m)


def _min_distance_to_obstacle_m(world: IntegratorWorld) -> float:
    tool = np.array([p for _, _, p, _ in world.trace])
    return float(np.linalg.norm(tool - np.array(IN_THE_WAY_M), axis=1).min())


def test_operator_routes_over_an_obstacle_in_the_way():
    """Seeing the obstacle, the operator goes over it and keeps the tool out of its
    influence; blind to it (the operator before routing), the carry cuts right through."""
    scenario = Scenario.load(GRASP_FILE)
    influence_m = load_config().teleop.obstacle_influence_m
    seeing = IntegratorWorld(scenario, scene=in_the_way_scene())
    operator = seeing.run(scenario.max_task_s + 1.0)
    assert operator.done and operator.success, operator.failure
    assert [r["phase"] for r in operator.routes] == ["carry"]
    assert _min_distance_to_obstacle_m(seeing) > IN_THE_WAY_RADIUS_M + influence_m
    blind = IntegratorWorld(scenario)
    blind.run(scenario.max_task_s + 1.0)
    assert _min_distance_to_obstacle_m(blind) < IN_THE_WAY_RADIUS_M


def test_a_target_out_of_reach_is_said_so_before_the_phase_times_out():
    """The tool stops at the arm's reach short of the approach target: the operator gives
    up with the reason and an OUT_OF_REACH event, well before the 15 s timeout."""
    scenario = Scenario.load(GRASP_FILE)
    approach = np.linalg.norm(CUBE_M + np.array(scenario.phases[0].target.offset_m))
    world = IntegratorWorld(scenario, reach_m=float(approach) - 0.1)
    operator = world.run(scenario.max_task_s + 1.0)
    assert operator.done and not operator.success
    assert operator.failure.startswith("the target out of reach in approach"), operator.failure
    assert [e for e, _ in operator.events] == [Event.OUT_OF_REACH]
    assert operator.events[0][1] == pytest.approx(0.1, abs=0.02)  # the distance left (m)
    assert operator.done_tick * TIMESTEP_S < 0.2 + scenario.phases[0].timeout_s / 2


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


# --- the service's decision loop, without a bus -----------------------------------------


def scene_tick_at(config: Config, t_s: float) -> tuple[int, int]:
    """(the scene tick nearest ``t_s`` of sim time, the scene period), in the run's ticks
    (loop.rate_hz): TOOL_POSE comes every ``1 / plant.scene_rate_hz``."""
    period = round(1.0 / (config.plant.scene_rate_hz * config.tick_s))
    return period * round(t_s / (period * config.tick_s)), period


def decision_ticks(config: Config, first: int, last: int) -> list[int]:
    """The operator's sample ticks (operator.decision_rate_hz on the run's ticks) in
    [first, last]."""
    rate_hz, tick_s = config.operator.decision_rate_hz, config.tick_s
    return [s for s in range(first, last + 1) if is_sample_tick(s, rate_hz, tick_s)]


class Outputs:
    """ScriptedOutputs that keeps what the loop sends."""

    def __init__(self) -> None:
        self.hands: dict[int, HandCommand] = {}
        self.events: list[tuple[int, int, int, float]] = []

    def hand(self, valid_from_tick: int, command: HandCommand) -> None:
        self.hands[valid_from_tick] = command

    def event(self, event: Event, tick: int, step: int, value: float) -> None:
        self.events.append((int(event), tick, step, value))


def test_operator_loop_answers_each_scene_tick_toward_the_cube():
    """The operator service's decisions (tests/integration/test_operator.py runs the same
    through a process): the scene ticks' arrivals give one HAND_INPUT per decision sample
    tick (operator.decision_rate_hz), valid a lead later."""
    config = load_config(None, ['run.mode="lockstep"'])
    outputs = Outputs()
    loop = ScriptedLoop(config, Scenario.load(GRASP_FILE), outputs, lockstep=True)
    lead = loop.hand_schedule.lead_ticks
    last_tick, scene_period = scene_tick_at(config, 0.6)
    for tick in range(0, last_tick + 1, scene_period):
        loop.buffer.add_objects(tick, np.array([CUBE_M, BIN_M]))
        loop.buffer.add_tool(tick, HOME_TOOL_M)
        loop.on_arrival(tick)
    decided = decision_ticks(config, 0, last_tick)
    assert len(decided) == round(0.6 * config.operator.decision_rate_hz) + 1  # 100 Hz
    assert sorted(outputs.hands) == [s + lead for s in decided]
    # Nothing seen before one reaction delay: no target; then toward the cube.
    delay = round(config.operator.reaction_delay_s / config.tick_s)
    seen_from = decision_ticks(config, delay, last_tick)[0]
    assert not any(outputs.hands[s + lead].target_p_m.any() for s in decided if s < seen_from)
    goal = CUBE_M + [0.0, 0.0, 0.12] - HOME_TOOL_M
    offsets = [outputs.hands[s + lead].target_p_m for s in decided if s > seen_from]
    for offset in offsets:
        assert offset @ goal / (np.linalg.norm(offset) * np.linalg.norm(goal)) > 0.999
    assert np.all(np.diff([np.linalg.norm(o) for o in offsets]) > 0)
    assert outputs.events == [(int(Event.PHASE), seen_from, seen_from, 0.0)]
    loop.on_arrival(last_tick)  # a re-send
    loop.on_started()  # the plant's STARTED after this run's poses: a new run
    summary = loop.summary()
    assert summary["duplicate_poses"] == 1 and summary["runs"] == 2  # tick 0, then STARTED
    assert summary["decisions"] == len(decided) and summary["phases"] == []
    assert summary["late_observations"] == 0


def test_operator_loop_refuses_decisions_faster_than_the_scene():
    config = load_config(None, ["operator.decision_rate_hz=200"])
    with pytest.raises(ConfigError, match="decision_rate_hz"):
        ScriptedLoop(config, Scenario.load(GRASP_FILE), Outputs(), lockstep=False)


# --- a restarted operator takes the task up where the world is ----------------------------


def restart_scene() -> SceneKnowledge:
    """The default scene's bin and rest heights, without its obstacle (the integrator
    world has none)."""
    known = SceneKnowledge.from_config(load_config())
    return SceneKnowledge(
        bin_low_m=known.bin_low_m, bin_high_m=known.bin_high_m, rest_z_m=known.rest_z_m
    )


def _look(tool_m, cube_m) -> Observation:
    objects = {"cube": np.array(cube_m, float), "bin": BIN_M}
    return Observation(0, np.array(tool_m, float), objects, 0.0)


LIFT_TARGET_Z_M = CUBE_M[2] + 0.15  # grasp.toml: lift = cube + 0.15 (from where it rests)
OVER_BIN_M = BIN_M + [0.0, 0.0, 0.20]  # grasp.toml: carry = bin + 0.20


@pytest.mark.parametrize(
    ("tool_m", "cube_m", "expected"),
    [
        (HOME_TOOL_M, CUBE_M, "approach"),  # nothing done yet
        (CUBE_M + [0, 0, 0.06], CUBE_M, "approach"),  # half way down: from the start
        (CUBE_M + [0.004, 0, 0.002], CUBE_M, "close"),  # at the grasp point (open or closed)
        (CUBE_M + [0, 0, 0.06], CUBE_M + [0, 0, 0.06], "lift"),  # lifted 6 of 15 cm
        (CUBE_M + [0.1, 0.2, 0.16], CUBE_M + [0.1, 0.2, 0.16], "carry"),  # on the way
        (OVER_BIN_M, OVER_BIN_M + [0, 0, -0.01], "release"),  # held over the bin
        (OVER_BIN_M + [0, 0, 0.05], BIN_M + [0.03, -0.02, 0.035], "release"),  # in the bin
        (HOME_TOOL_M, [0.3, -0.3, 0.025], "approach"),  # dropped on the table: again
    ],
    ids=["home", "descending", "grasp-point", "lifting", "carrying", "over-bin", "in-bin", "drop"],
)
def test_a_restarted_operator_takes_the_grasp_up_from_what_it_sees(tool_m, cube_m, expected):
    scenario = Scenario.load(GRASP_FILE)
    resumption = resume_phase(scenario, _look(tool_m, cube_m), restart_scene())
    assert scenario.phases[resumption.phase].name == expected, resumption.why
    if expected == "lift":  # the lift's height is counted from where the cube rests
        target = resumption.anchors["cube"] + scenario.phases[resumption.phase].target.offset_m
        assert target[2] == pytest.approx(LIFT_TARGET_Z_M)
        assert target[:2] == pytest.approx(np.asarray(cube_m)[:2])


def test_without_rest_heights_a_cube_at_the_tool_is_gripped_before_anything_else():
    """Nothing known of where the cube rests, so no lift can be told: the tool at the
    cube's centre closes the gripper (whether or not it was closed) and lifts from there."""
    scenario = Scenario.load(GRASP_FILE)
    lifted = CUBE_M + [0, 0, 0.06]
    resumption = resume_phase(scenario, _look(lifted, lifted), SceneKnowledge())
    assert scenario.phases[resumption.phase].name == "close"


@pytest.mark.parametrize("phase", ["approach", "close", "lift", "carry", "release"])
def test_an_operator_killed_mid_task_is_replaced_and_the_task_succeeds(phase):
    """The closed loop on sim ticks (no wall clock anywhere): the operator dies half a
    second into a phase, the hand holds, and a new operator joins 3 s later; it takes the
    task up at the phase the world is in, and the cube ends in the bin."""
    scenario = Scenario.load(GRASP_FILE)
    world = IntegratorWorld(scenario, scene=restart_scene())
    operator = world.run(scenario.max_task_s + 1.0, kill_in=(phase, 0.5, 3.0))
    assert operator.resumed is not None and operator.resumed["name"] == phase
    assert operator.done and operator.success, operator.failure
    assert np.all(np.abs(world.cube[:2] - BIN_M[:2]) < 0.09 - 0.025)
    # Let go once, over the bin: never dropped and picked up again.
    (drop,) = world.drops
    assert np.linalg.norm(drop[:2] - BIN_M[:2]) < 0.03
    # The task's clock counts from the run's first look, the outage included.
    assert operator.task_start_tick == round(world.cfg.operator.reaction_delay_s / TIMESTEP_S)


def test_the_operator_loop_joining_a_run_sends_nothing_until_it_has_seen_the_world():
    """A restarted operator's first pose is past tick 0: it withholds its hand for one
    reaction delay (a guess would open the gripper), then takes the task up where the
    world is (the cube lifted in the gripper: the lift) and says so with its PHASE."""
    config = load_config(None, ['run.mode="lockstep"'])
    outputs = Outputs()
    loop = ScriptedLoop(
        config, Scenario.load(GRASP_FILE), outputs, lockstep=True, scene=restart_scene()
    )
    (joined, scene_period), (last_tick, _) = (scene_tick_at(config, t_s) for t_s in (8.0, 8.4))
    lifted = CUBE_M + [0.0, 0.0, 0.05]
    for tick in range(joined, last_tick + 1, scene_period):
        loop.buffer.add_objects(tick, np.array([lifted, BIN_M]))
        loop.buffer.add_tool(tick, lifted)
        loop.on_arrival(tick)
    # The first decision that sees a pose of this run: one reaction delay after the join.
    delay = round(config.operator.reaction_delay_s / config.tick_s)
    first_sent = decision_ticks(config, joined + delay, last_tick)[0]
    assert min(outputs.hands) == first_sent + loop.hand_schedule.lead_ticks
    summary = loop.summary()
    # The decisions of one reaction delay (20: 0.2 s at 100 Hz), all withheld.
    withheld = round(config.operator.reaction_delay_s * config.operator.decision_rate_hz)
    assert summary["withheld_inputs"] == withheld
    assert summary["resumed"]["name"] == "lift" and summary["late_observations"] == 0
    lift = 4
    assert outputs.events[0] == (int(Event.PHASE), first_sent, first_sent, float(lift))
    assert all(c.buttons & Button.GRIPPER_CLOSE for c in outputs.hands.values())
    assert all(c.target_p_m[2] > 0 for c in list(outputs.hands.values())[5:])  # going up


@pytest.mark.parametrize("phase", ["descend", "lift", "carry"])
def test_an_operator_starved_for_seconds_catches_up_and_the_task_succeeds(phase):
    """A late operator (starved: no decision for 3 s of sim ticks, the device centring
    the handle meanwhile) decides again from the newest look: it knows its hand was held
    (no drift learnt from commands never applied, no stall counted: taking the still tool
    for blocked, it would give up) and goes on."""
    scenario = Scenario.load(GRASP_FILE)
    world = IntegratorWorld(scenario)
    operator = world.run(scenario.max_task_s + 1.0, kill_in=(phase, 0.5, 3.0), restart=False)
    assert operator.done and operator.success, operator.failure
    assert operator.hand_holds == 1 and operator.resumed is None
    (drop,) = world.drops
    assert np.linalg.norm(drop[:2] - BIN_M[:2]) < 0.03


@pytest.mark.parametrize("phase", ["descend", "lift", "carry"])
def test_an_operator_waits_out_its_devices_restart_and_the_task_succeeds(phase):
    """The haptic device is gone for 4 s (killed, restarting: the tool does not move
    whatever the hand does). An operator that sees the device's token go waits, the grip
    held, and goes on once it is back; one that does not took the still tool for out of
    reach (stalled longer than its 3 s window) and gave up."""
    scenario = Scenario.load(GRASP_FILE)
    outage = (phase, 0.5, 4.0)
    world = IntegratorWorld(scenario)
    operator = world.run(scenario.max_task_s + 5.0, device_out=outage)
    assert operator.done and operator.success, operator.failure
    assert operator.device_gone_decisions > 0
    (drop,) = world.drops
    assert np.linalg.norm(drop[:2] - BIN_M[:2]) < 0.03
    blind = IntegratorWorld(scenario).run(scenario.max_task_s + 5.0, device_out=outage, told=False)
    assert not blind.success and "out of reach" in blind.failure


@pytest.mark.parametrize("phase", ["approach", "descend", "carry"])
def test_a_tool_the_plant_holds_is_no_target_out_of_reach(phase):
    """The plant's watchdog holds the tool 4 s (longer than the 3 s stall window): an
    operator that sees the tool samples' BRAKING flag expects no progress of a held tool
    and goes on once it moves; one that does not see it takes the still tool for out
    of reach and gives up."""
    scenario = Scenario.load(GRASP_FILE)
    brake = (phase, 0.5, 4.0)
    operator = IntegratorWorld(scenario).run(scenario.max_task_s + 5.0, braked=brake)
    assert operator.done and operator.success, operator.failure
    blind = IntegratorWorld(scenario).run(scenario.max_task_s + 5.0, braked=brake, flagged=False)
    assert not blind.success and "out of reach" in blind.failure


def test_a_late_operator_loop_catches_up_by_skipping_not_by_a_burst():
    """Realtime, poses queued behind a newer one: the loop decides the newest sample tick
    only (one hand input, not a burst of late ones) and counts the ticks it skipped."""
    config = load_config(None, ['run.mode="realtime"'])
    outputs = Outputs()
    loop = ScriptedLoop(config, Scenario.load(GRASP_FILE), outputs, lockstep=False)
    one_s, scene_period = scene_tick_at(config, 1.0)
    for tick in range(0, one_s + 1, scene_period):
        loop.buffer.add_objects(tick, np.array([CUBE_M, BIN_M]))
        loop.buffer.add_tool(tick, HOME_TOOL_M)
    loop.on_arrival(0)
    loop.on_arrival(one_s, catch_up=True)  # the poses of the second in between were skipped
    lead = loop.hand_schedule.lead_ticks
    assert sorted(outputs.hands) == [0 + lead, one_s + lead]
    # The decisions strictly inside that second (99 at 100 Hz).
    skipped = round(1.0 * config.operator.decision_rate_hz) - 1
    assert loop.summary()["skipped_decisions"] == skipped


def test_after_a_frozen_view_the_realtime_loop_decides_the_newest_pose_not_a_burst():
    """Realtime, the poses stop for 5 s (the link to the robot's site cut), then come
    again: the loop decides the newest sample tick only. A burst over the frozen
    stretch would judge 5 s of decisions on the last picture before the cut, in which
    the tool does not move, and give the target up as out of reach."""
    config = load_config(None, ['run.mode="realtime"'])
    outputs = Outputs()
    loop = ScriptedLoop(config, Scenario.load(GRASP_FILE), outputs, lockstep=False)
    one_s, scene_period = scene_tick_at(config, 1.0)
    back, _ = scene_tick_at(config, 6.0)
    for tick in [*range(0, one_s + 1, scene_period), back]:
        loop.buffer.add_objects(tick, np.array([CUBE_M, BIN_M]))
        loop.buffer.add_tool(tick, HOME_TOOL_M)
    for tick in range(0, one_s + 1, scene_period):
        loop.on_arrival(tick)
    decided = loop.summary()["decisions"]
    loop.on_arrival(back)
    summary = loop.summary()
    assert summary["decisions"] == decided + 1 and summary["frozen_views"] == 1
    assert not loop.operator.done, loop.operator.failure


def test_a_lockstep_operator_left_behind_catches_up_and_waits_for_nothing_it_missed():
    """Lockstep, restarted: the device went on without it, so its poses run far ahead of
    its decisions. It is left behind (never while the device waits for it: a pose at
    most ``lockstep_lag_ticks`` ahead), and a head pose older than every one it holds
    (sent before it subscribed) is not waited for: no decision times out on it."""
    config = load_config(None, ['run.mode="lockstep"'])
    outputs = Outputs()
    loop = ScriptedLoop(
        config, Scenario.load(GRASP_FILE), outputs, lockstep=True, scene=restart_scene()
    )
    loop.hmd_seen()
    joined, scene_period = scene_tick_at(config, 8.0)
    later, _ = scene_tick_at(config, 8.0 + 3.0)  # 3 s on
    for tick in range(joined, later + 1, scene_period):
        loop.buffer.add_objects(tick, np.array([CUBE_M, BIN_M]))
        loop.buffer.add_tool(tick, HOME_TOOL_M)
    head_from = joined + round(0.030 / loop.tick_s)  # the HMD's, from after the join only
    for tick in range(head_from, later + 1):
        valid_from = loop.head_schedule.valid_from_for(tick)
        loop.buffer.add_head(valid_from, 0.0)
    assert not loop.left_behind(joined)  # nothing decided yet: the join decides the newest
    loop.on_arrival(joined)
    assert not loop.left_behind(joined + loop.lockstep_lag_ticks)
    assert loop.left_behind(joined + loop.lockstep_lag_ticks + 1)
    loop.on_arrival(later, catch_up=True)
    summary = loop.summary()
    skipped = round(3.0 * config.operator.decision_rate_hz) - 1  # 299: those in between
    assert summary["decisions"] == 2 and summary["skipped_decisions"] == skipped
    assert summary["late_observations"] == 0  # waited for no head pose it could not get
    assert max(outputs.hands) == later + loop.hand_schedule.lead_ticks
    realtime = ScriptedLoop(config, Scenario.load(GRASP_FILE), Outputs(), lockstep=False)
    assert realtime.left_behind(0)  # realtime: always on the newest pose


def test_the_observation_buffer_waits_for_no_head_pose_older_than_it_holds():
    buffer = ObservationBuffer(("cube", "bin"), delay_ticks=0, default_yaw_rad=0.0)
    buffer.add_tool(500, [0, 0, 0])
    buffer.add_objects(500, np.zeros((2, 3)))
    assert not buffer.ready(500, 480)  # no head pose yet: it may still come
    buffer.add_head(490, 0.2)
    assert buffer.ready(500, 480)  # older than the first one held: never coming
    assert not buffer.ready(500, 501) and buffer.ready(500, 490)


def test_the_grasp_loop_plays_the_grasp_then_puts_the_cube_back_round_after_round():
    """deploy/scenarios/grasp_loop.toml (the soak's teleoperated task): each round is
    grasp.toml's phases into the bin, then the cube out of the bin and set down at its
    place on the table; a round ends with the gripper open, clear of the cube."""
    grasp = Scenario.load(GRASP_FILE)
    loop = Scenario.load(DEPLOY_DIR / "scenarios" / "grasp_loop.toml")
    per_round = 2 * len(grasp.phases) + 1  # out and back (+ the lower before set-down)
    assert len(loop.phases) % per_round == 0 and len(loop.phases) // per_round >= 60
    first = loop.phases[: len(grasp.phases)]
    assert [p.target for p in first] == [p.target for p in grasp.phases]
    assert [p.gripper for p in first] == [p.gripper for p in grasp.phases]
    back = loop.phases[len(grasp.phases) : per_round]
    lowered = next(p for p in back if p.name.startswith("lower"))
    assert lowered.target.relative_to == "bin" and lowered.carrying
    # teleop/assets/scene_arm6.xml: the bin's origin at (0.35, 0.35), the cube at (0.45, -0.25)
    cube_home_m = np.array([0.35, 0.35, 0.0]) + np.array(lowered.target.offset_m)
    assert cube_home_m[:2] == pytest.approx([0.45, -0.25])
    assert back[-1].gripper == "open" and back[-1].target.offset_m[2] > 0
    assert loop.phases[per_round].target == grasp.phases[0].target  # the next round
