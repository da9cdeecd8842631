"""A run: the timing modes, the scenarios and what shapes the stack for each, and the
run's own section (``run``: duration, seed, mode, scenario, operator, robots)."""

from __future__ import annotations

from dataclasses import dataclass

from teleop.core.config.base import ConfigError, require
from teleop.core.config.operators import OPERATORS, SCRIPTED

TIMING_MODES = ("realtime", "lockstep")


@dataclass(frozen=True)
class ScenarioSpec:
    """A task the stack runs, and the one property that shapes the stack: whether a
    hand on the haptic device drives the arm (teleoperation: the device's clock paces
    the commands, contact and proximity feed the force every step, the haptic device,
    HMD and operator run) or the controller drives it on its own."""

    name: str
    teleoperated: bool
    what: str


SCENARIO_SPECS: tuple[ScenarioSpec, ...] = (
    ScenarioSpec("path-following", False, "paper experiment 1: the arm follows a path"),
    ScenarioSpec("grasp", True, "paper experiment 2: pick and place, teleoperated"),
)
SCENARIOS = tuple(s.name for s in SCENARIO_SPECS)
TELEOPERATED = tuple(s.name for s in SCENARIO_SPECS if s.teleoperated)
AUTONOMOUS = tuple(s.name for s in SCENARIO_SPECS if not s.teleoperated)


def scenario_spec(name: str) -> ScenarioSpec:
    """The spec of the scenario ``name`` (ConfigError naming the scenarios otherwise)."""
    for spec in SCENARIO_SPECS:
        if spec.name == name:
            return spec
    raise ConfigError(f"scenario {name!r}: one of {', '.join(SCENARIOS)}")


# Characters of a robot id that names services of a run of several robots (their
# participants' names, teleop.bus.access).
ROBOT_ID_ALPHABET = frozenset("abcdefghijklmnopqrstuvwxyz0123456789_")
# Robots one operator station drives (run.robots): each adds a plant and a controller.
MAX_ROBOTS = 4


@dataclass(frozen=True)
class RunConfig:
    """A scenario run: how long, which seed, when the accuracy measurement starts."""

    duration_s: float = 60.0
    seed: int = 0
    # realtime: the plant keeps wall-clock time; lockstep: one step per controller command.
    mode: str = "realtime"
    # path-following: paper experiment 1 (autonomous); grasp: experiment 2 (teleoperation).
    scenario: str = "path-following"
    settle_s: float = 10.0
    # Initial arm configuration (rad), one per arm joint; empty = robot.home_q_rad.
    initial_q_rad: tuple[float, ...] = ()
    # Standard deviation of the random perturbation of the initial configuration (rad).
    initial_q_noise_rad: float = 0.05
    # Who drives the handle in teleoperation: the scripted operator or a person's device
    # (OPERATORS; teleop run --operator).
    operator: str = SCRIPTED
    # Robots on the bus (teleop run --robots): each its own plant and controller under its
    # own id (Config.robot_ids), one operator station (haptic, HMD, operator, recorder)
    # driving them in turn.
    robots: int = 1

    @property
    def teleoperated(self) -> bool:
        """Whether this run's scenario is teleoperation (ScenarioSpec.teleoperated)."""
        return self.scenario in TELEOPERATED

    @property
    def follows_path(self) -> bool:
        """Whether the controller drives the tool along ``config.path``'s desired path
        (the autonomous scenarios): the run has a desired path to draw and to judge."""
        return not self.teleoperated

    def __post_init__(self) -> None:
        require(self.duration_s > 0, "run.duration_s > 0")
        require(self.mode in TIMING_MODES, f"run.mode: one of {', '.join(TIMING_MODES)}")
        require(self.scenario in SCENARIOS, f"run.scenario: one of {', '.join(SCENARIOS)}")
        require(0 <= self.settle_s, "run.settle_s >= 0")
        require(self.initial_q_noise_rad >= 0, "run.initial_q_noise_rad >= 0")
        require(self.operator in OPERATORS, f"run.operator: one of {', '.join(OPERATORS)}")
        require(1 <= self.robots <= MAX_ROBOTS, f"run.robots in [1, {MAX_ROBOTS}]")
