"""The whole configuration: every section together, and the checks that span sections
(the bus rate against the physics and render periods, a two-site round trip, a run of
several robots)."""

from __future__ import annotations

from dataclasses import dataclass, field

from teleop.core.config.base import require
from teleop.core.config.control import ClearanceConfig, ControlConfig, PathConfig, SceneConfig
from teleop.core.config.devices import EyeViewConfig, HapticConfig, HmdConfig, TeleopConfig
from teleop.core.config.operators import (
    INPUT_DEVICE_OPERATORS,
    SCRIPTED,
    GamepadConfig,
    KeyboardConfig,
    OperatorConfig,
    SpaceMouseConfig,
    WebConfig,
)
from teleop.core.config.robot import LoopConfig, PlantConfig, RobotConfig
from teleop.core.config.run import ROBOT_ID_ALPHABET, RunConfig
from teleop.core.config.system import ROBOT_SITE, BusConfig, CpuConfig, RecorderConfig, SiteConfig


@dataclass(frozen=True)
class Config:
    """The whole configuration a service receives: one frozen section per TOML table
    (``[robot]``, ``[plant]``, ...), each checked on its own, and here the rules that
    tie sections together, so a run refused for them fails before any process starts."""

    robot: RobotConfig = field(default_factory=RobotConfig)
    plant: PlantConfig = field(default_factory=PlantConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    path: PathConfig = field(default_factory=PathConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    clearance: ClearanceConfig = field(default_factory=ClearanceConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    haptic: HapticConfig = field(default_factory=HapticConfig)
    hmd: HmdConfig = field(default_factory=HmdConfig)
    eyeview: EyeViewConfig = field(default_factory=EyeViewConfig)
    teleop: TeleopConfig = field(default_factory=TeleopConfig)
    operator: OperatorConfig = field(default_factory=OperatorConfig)
    keyboard: KeyboardConfig = field(default_factory=KeyboardConfig)
    gamepad: GamepadConfig = field(default_factory=GamepadConfig)
    spacemouse: SpaceMouseConfig = field(default_factory=SpaceMouseConfig)
    web: WebConfig = field(default_factory=WebConfig)
    cpu: CpuConfig = field(default_factory=CpuConfig)
    bus: BusConfig = field(default_factory=BusConfig)
    recorder: RecorderConfig = field(default_factory=RecorderConfig)
    run: RunConfig = field(default_factory=RunConfig)
    site: SiteConfig = field(default_factory=SiteConfig)

    def __post_init__(self) -> None:
        self._check_loop_rate()
        if self.site.emulated_round_trip_ms:
            require(
                self.run.mode == "lockstep",
                "site.emulated_round_trip_ms: lockstep runs only (in realtime, run two sites "
                "with teleop.bench.netem between their routers: docs/sites.md)",
            )
            require(
                self.run.operator == SCRIPTED,
                "site.emulated_round_trip_ms: the scripted operator only (a person's screen "
                "would show the scene undelayed)",
            )
            ticks = self.site.emulated_round_trip_ms / (self.tick_s * 1e3)
            require(
                abs(ticks - round(ticks)) < 1e-6,
                f"site.emulated_round_trip_ms: a whole number of bus periods "
                f"({self.tick_s * 1e3:g} ms each at loop.rate_hz = {self.loop.rate_hz:g})",
            )

        if self.run.robots > 1:
            self._check_robots()

    @property
    def tick_s(self) -> float:
        """The bus period (s): one tick of the run, one plant state, command, handle
        sample and feedback (``1 / loop.rate_hz``)."""
        return 1.0 / self.loop.rate_hz

    @property
    def renders_per_tick(self) -> int:
        """Servo periods (``haptic.render_period_s``) the haptic device renders per bus
        period from one local contact model."""
        return round(self.tick_s / self.haptic.render_period_s)

    @property
    def physics_steps_per_tick(self) -> int:
        """Physics steps (``plant.timestep_s``) the plant takes per bus period."""
        return round(self.tick_s / self.plant.timestep_s)

    def _check_loop_rate(self) -> None:
        """``loop.rate_hz``: a whole number of physics steps per bus period, and no
        stream that runs per tick asked to run faster than the ticks come."""
        rate = self.loop.rate_hz
        physics_hz = 1.0 / self.plant.timestep_s
        steps = physics_hz / rate
        require(
            rate <= physics_hz * (1 + 1e-9) and abs(steps - round(steps)) < 1e-6,
            f"loop.rate_hz = {rate:g}: must divide the physics rate {physics_hz:g} Hz "
            f"(plant.timestep_s = {self.plant.timestep_s:g}) into a whole number of steps, "
            f"e.g. {', '.join(f'{physics_hz / n:g}' for n in (1, 2, 4, 5, 10))}",
        )
        for name, value in (
            ("plant.scene_rate_hz", self.plant.scene_rate_hz),
            ("control.status_rate_hz", self.control.status_rate_hz),
            ("operator.decision_rate_hz", self.operator.decision_rate_hz),
            ("hmd.rate_hz", self.hmd.rate_hz),
        ):
            require(
                value <= rate * (1 + 1e-9), f"{name} = {value:g}: at most loop.rate_hz ({rate:g})"
            )
        renders = self.tick_s / self.haptic.render_period_s
        require(
            renders >= 1 - 1e-9 and abs(renders - round(renders)) < 1e-6,
            f"haptic.render_period_s = {self.haptic.render_period_s:g}: a bus period "
            f"({self.tick_s:g} s) must be a whole number of them",
        )
        watchdog_ticks = self.plant.watchdog_s * rate
        require(
            watchdog_ticks >= 2 - 1e-9,
            f"plant.watchdog_s = {self.plant.watchdog_s:g}: at least two bus periods "
            f"({2 / rate:g} s at loop.rate_hz = {rate:g})",
        )

    def _check_robots(self) -> None:
        """What a run of several robots (``run.robots``) supports: the scripted operator
        drives them in turn, or a person with a robot switch (tab on the keyboard and the
        web page, a device's switch_buttons), in the teleoperation scenario, on one host
        or a robot site each (site.name), each with its own model of the operator's
        link."""
        many = f"run.robots={self.run.robots}"
        require(self.run.teleoperated, f"{many}: a teleoperated scenario (grasp)")
        if self.run.operator in INPUT_DEVICE_OPERATORS:
            device = self.gamepad if self.run.operator == "gamepad" else self.spacemouse
            section = self.run.operator
            require(
                len(device.switch_buttons) > 0,
                f"{many}: {section}.switch_buttons is empty: name the button that drives "
                "the next robot (a SpaceMouse's two are the gripper's and the clutch's by "
                f"default: e.g. --set '{section}.switch_buttons=[\"BTN_1\"]' "
                f"--set '{section}.clutch_buttons=[]')",
            )
        require(
            not self.site.emulated_round_trip_ms,
            f"{many}: not with site.emulated_round_trip_ms",
        )
        require(
            self.teleop.stabiliser != "wave",
            f"{many}: not with teleop.stabiliser=wave (an idle robot's wave port would "
            "drift on its own resistance)",
        )
        ids = self.robot_ids()
        require(
            all(set(rid) <= ROBOT_ID_ALPHABET for rid in ids),
            f"{many}: robot.robot_id {self.robot.robot_id!r} must be lower-case letters, "
            "digits and _ (it names each robot's services)",
        )

    def robot_ids(self) -> tuple[str, ...]:
        """The id of every robot of the run: ``robot.robot_id`` alone, or with
        ``run.robots`` > 1 its stem numbered from its own number on (``arm0`` -> ``arm0``,
        ``arm1``; ``ur`` -> ``ur0``, ``ur1``)."""
        if self.run.robots == 1:
            return (self.robot.robot_id,)
        stem = self.robot.robot_id.rstrip("0123456789")
        first = int(self.robot.robot_id[len(stem) :] or 0)
        return tuple(f"{stem}{first + i}" for i in range(self.run.robots))

    def site_robot_ids(self) -> tuple[str, ...]:
        """The robots whose processes this host runs: every robot of a one-host run and
        of the operator site (its station drives them all), one robot's for a robot site
        (the first robot's, or ``site.robot``'s)."""
        if self.site.name != ROBOT_SITE:
            return self.robot_ids()
        return (self.site.robot or self.robot_ids()[0],)

    def link_delay_ticks(self) -> tuple[int, int]:
        """The emulated link's delay (plant ticks) from the operator's site to the
        robot's and back (``site.emulated_round_trip_ms``; (0, 0): none)."""
        round_trip = round(self.site.emulated_round_trip_ms / (self.tick_s * 1e3))
        return round_trip // 2, round_trip - round_trip // 2
