"""Typed configuration, loaded from a TOML file in ``deploy/`` with ``--set`` overrides.

Every service receives one :class:`Config`. Each section is a frozen dataclass that
validates itself at construction, so a bad value fails at start-up with a message
that names the key, never later inside a control loop.

Overrides use dotted keys and TOML literals: ``control.compensation=false``,
``path.center_m=[0.1, 0.0, 0.35]``, ``robot.robot_id="arm1"``. A value that is not
a TOML literal is taken as a string.

This package's modules, one topic each, bottom up: ``base`` (directories, errors, the
range check), ``robot`` (robot, loop, plant), ``control`` (path, control, clearance,
scene), ``devices`` (haptic, hmd, eyeview, teleop), ``operators`` (operator, keyboard,
gamepad, spacemouse, web), ``system`` (cpu, bus, site, recorder), ``run`` (timing modes,
scenarios, run), ``whole`` (:class:`Config`, the checks across sections) and ``loading``
(TOML to typed sections, overrides, :func:`load_config`). Import from here: this module
is the package's public face.
"""

from teleop.core.config.base import (
    ASSETS_DIR,
    DEFAULT_CONFIG_FILE,
    DEPLOY_DIR,
    REPO_ROOT,
    ConfigError,
    ModelError,
)
from teleop.core.config.control import (
    ClearanceConfig,
    ControlConfig,
    PathConfig,
    SceneConfig,
)
from teleop.core.config.devices import (
    MAX_WAVE_IMPEDANCE_N_S_M,
    STABILISERS,
    EyeViewConfig,
    HapticConfig,
    HmdConfig,
    TeleopConfig,
)
from teleop.core.config.loading import (
    SUGGESTION_CUTOFF,
    TOML_OPENERS,
    build,
    load_config,
    read_toml,
)
from teleop.core.config.operators import (
    BUTTON_MODES,
    INPUT_DEVICE_OPERATORS,
    OPERATORS,
    SCRIPTED,
    TERMINAL_OPERATORS,
    VIEWING_OPERATORS,
    GamepadConfig,
    KeyboardConfig,
    OperatorConfig,
    SpaceMouseConfig,
    WebConfig,
)
from teleop.core.config.robot import (
    LOCKSTEP_RESEND_S,
    MAX_LOCKSTEP_DELAY_STEPS,
    MIN_LOOP_RATE_HZ,
    LoopConfig,
    PlantConfig,
    RobotConfig,
)
from teleop.core.config.run import (
    AUTONOMOUS,
    MAX_ROBOTS,
    ROBOT_ID_ALPHABET,
    SCENARIO_SPECS,
    SCENARIOS,
    TELEOPERATED,
    TIMING_MODES,
    RunConfig,
    ScenarioSpec,
    scenario_spec,
)
from teleop.core.config.system import (
    MAX_EMULATED_ROUND_TRIP_MS,
    OPERATOR_SITE,
    ROBOT_SITE,
    SITES,
    BusConfig,
    CpuConfig,
    RecorderConfig,
    SiteConfig,
)
from teleop.core.config.whole import (
    Config,
)

__all__ = [
    "REPO_ROOT",
    "DEPLOY_DIR",
    "ASSETS_DIR",
    "DEFAULT_CONFIG_FILE",
    "ConfigError",
    "ModelError",
    "RobotConfig",
    "MIN_LOOP_RATE_HZ",
    "LoopConfig",
    "MAX_LOCKSTEP_DELAY_STEPS",
    "LOCKSTEP_RESEND_S",
    "PlantConfig",
    "PathConfig",
    "ControlConfig",
    "ClearanceConfig",
    "SceneConfig",
    "HapticConfig",
    "HmdConfig",
    "EyeViewConfig",
    "STABILISERS",
    "MAX_WAVE_IMPEDANCE_N_S_M",
    "TeleopConfig",
    "OperatorConfig",
    "SCRIPTED",
    "OPERATORS",
    "TERMINAL_OPERATORS",
    "VIEWING_OPERATORS",
    "INPUT_DEVICE_OPERATORS",
    "KeyboardConfig",
    "BUTTON_MODES",
    "GamepadConfig",
    "SpaceMouseConfig",
    "WebConfig",
    "CpuConfig",
    "BusConfig",
    "ROBOT_SITE",
    "OPERATOR_SITE",
    "SITES",
    "MAX_EMULATED_ROUND_TRIP_MS",
    "SiteConfig",
    "RecorderConfig",
    "TIMING_MODES",
    "ScenarioSpec",
    "SCENARIO_SPECS",
    "SCENARIOS",
    "TELEOPERATED",
    "AUTONOMOUS",
    "scenario_spec",
    "ROBOT_ID_ALPHABET",
    "MAX_ROBOTS",
    "RunConfig",
    "Config",
    "SUGGESTION_CUTOFF",
    "TOML_OPENERS",
    "build",
    "read_toml",
    "load_config",
]
