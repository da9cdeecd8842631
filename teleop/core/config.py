"""Typed configuration, loaded from a TOML file in ``deploy/`` with ``--set`` overrides.

Every service receives one :class:`Config`. Each section is a frozen dataclass that
validates itself at construction, so a bad value fails at start-up with a message
that names the key, never later inside a control loop.

Overrides use dotted keys and TOML literals: ``control.compensation=false``,
``path.center_m=[0.1, 0.0, 0.35]``, ``robot.robot_id="arm1"``. A value that is not
a TOML literal is taken as a string.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import tomllib
import types
import typing
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

REPO_ROOT = Path(__file__).resolve().parents[2]
DEPLOY_DIR = REPO_ROOT / "deploy"
ASSETS_DIR = Path(__file__).resolve().parents[1] / "assets"
DEFAULT_CONFIG_FILE = DEPLOY_DIR / "teleop.toml"

_T = TypeVar("_T")


class ConfigError(ValueError):
    """A configuration value is missing, mistyped or out of range."""


class ModelError(ValueError):
    """The model file does not contain what the configuration names."""


# How close a misspelt key must be to a real one to be suggested (difflib ratio, 0-1).
SUGGESTION_CUTOFF = 0.6
# First characters of a --set value meant as a TOML literal (list, table, string).
TOML_OPENERS = ("[", "{", '"', "'")


def _require(ok: bool, message: str) -> None:
    if not ok:
        raise ConfigError(message)


@dataclass(frozen=True)
class RobotConfig:
    """Which model file to load and which of its names the code relies on.

    Nothing else in the code assumes a particular arm: point ``scene_file`` at another
    MJCF scene and list its joint, actuator and site names here.
    """

    robot_id: str = "arm0"
    # A file name inside teleop/assets/, or a path (absolute, or relative to the repo root).
    scene_file: str = "scene_arm6.xml"
    arm_joints: tuple[str, ...] = (
        "shoulder_pan",
        "shoulder_lift",
        "elbow",
        "wrist_1",
        "wrist_2",
        "wrist_3",
    )
    # Velocity actuators (the arm's low-level joint velocity loops), same order as arm_joints.
    arm_actuators: tuple[str, ...] = (
        "shoulder_pan_vel",
        "shoulder_lift_vel",
        "elbow_vel",
        "wrist_1_vel",
        "wrist_2_vel",
        "wrist_3_vel",
    )
    tool_site: str = "tool"
    # Start configuration (rad), arm_joints order: tool 0.4 m above the table, pointing down.
    home_q_rad: tuple[float, ...] = (0.0, -0.25, 1.75, 0.05, -1.5708, -1.5708)
    gripper_actuator: str = "gripper"
    # Joints that are not part of the arm chain (fingers): locked in the Pinocchio model.
    gripper_joints: tuple[str, ...] = ("finger_left", "finger_right")
    # Names of scene bodies whose poses the plant publishes (graspable objects).
    object_bodies: tuple[str, ...] = ("cube", "bin")
    # Prefix of the non-colliding geoms that are virtual obstacles.
    obstacle_prefix: str = "obstacle"

    def __post_init__(self) -> None:
        _require(
            bool(self.robot_id) and "/" not in self.robot_id, "robot.robot_id: non-empty, no '/'"
        )
        _require(len(self.arm_joints) >= 3, "robot.arm_joints: at least 3 joints")
        _require(
            len(self.arm_actuators) == len(self.arm_joints),
            "robot.arm_actuators: one actuator per arm joint",
        )
        _require(
            len(self.home_q_rad) == len(self.arm_joints),
            "robot.home_q_rad: one angle per arm joint",
        )

    @property
    def scene_path(self) -> Path:
        """The scene MJCF as an absolute path."""
        candidate = Path(self.scene_file)
        if candidate.is_absolute():
            return candidate
        if (ASSETS_DIR / candidate).exists():
            return ASSETS_DIR / candidate
        return REPO_ROOT / candidate


# The lowest bus rate a run may use (Hz): the operator's 100 Hz decisions and the scene
# streams run no faster than the bus.
MIN_LOOP_RATE_HZ = 100.0


@dataclass(frozen=True)
class LoopConfig:
    """The bilateral loop's bus rate: one plant state, one joint command, one handle sample
    and one force feedback (with its local contact model) cross the bus per period.

    Physics and the arm's drives (``plant.timestep_s``, 1 kHz) and the haptic device's
    force rendering (``haptic.render_period_s``, 1 kHz) stay inside their processes: the
    plant takes ``1 / (rate_hz * plant.timestep_s)`` physics steps per exchange, the
    device renders as many times from the newest local contact model. 1000 Hz exchanges
    every physics step (for comparisons); the default is the rate the rate sweep picked
    (docs/realtime.md, "Two rates").
    """

    rate_hz: float = 250.0

    def __post_init__(self) -> None:
        _require(self.rate_hz >= MIN_LOOP_RATE_HZ, f"loop.rate_hz >= {MIN_LOOP_RATE_HZ:g}")


# More states in flight than this gains nothing (two stages: plant and controller).
MAX_LOCKSTEP_DELAY_STEPS = 4
# Lockstep: the plant re-sends a state left unanswered this long (s).
LOCKSTEP_RESEND_S = 1.0


@dataclass(frozen=True)
class PlantConfig:
    """The MuJoCo plant: physics period and command watchdog."""

    timestep_s: float = 0.001
    # The plant brakes (holds the arm where it is) when the newest command answers a state
    # that was superseded more than this long ago, on the plant's own clock.
    watchdog_s: float = 0.020
    # The tool point's commanded speed is cut to this whatever a command asks (the plant
    # owns the robot's limits; each joint is also held to its drive's range). A safety
    # limit above the controllers' own caps (teleop.max_tool_speed_m_s,
    # control.max_tool_speed_m_s): the cut scales a command's whole motion, orientation
    # and clearance corrections included, so it must not act on a well-behaved command
    # whose velocity loops lag a little behind it.
    tool_speed_limit_m_s: float = 0.30
    # The protective stop (teleop/sim/protective.py), on the plant's own measurements
    # after each step: a contact force of the scene (table, bin, arm; not a held cube's)
    # on the gripper above contact_force_limit_n (a grasp touches the scene with none),
    # or a measured tool speed above tool_speed_stop_m_s (the
    # commands are cut to tool_speed_limit_m_s: faster means pushed, or not following),
    # brakes and holds the arm until the commands have asked for a tool motion of at
    # most protective_release_m_s for protective_release_s in a row.
    contact_force_limit_n: float = 8.0
    tool_speed_stop_m_s: float = 0.33
    protective_release_m_s: float = 0.005
    protective_release_s: float = 0.02
    # Speed and separation (teleop/sim/protective.py, allowed_approach_m_s): the gripper
    # may close in on the scene (table, bin, arm; not a free object) at most at
    # approach_touch_m_s + separation / approach_time_s, so it meets it at
    # approach_touch_m_s, slow enough for the contact-force stop to catch the press
    # within its limit. The plant sees the scene within tool_speed_limit_m_s *
    # approach_time_s of the gripper (MuJoCo contacts in the geoms' margin, inactive).
    # approach_time_s = 0: no approach limit.
    approach_touch_m_s: float = 0.004
    approach_time_s: float = 0.1
    # Rate of the scene streams (tool pose, object poses) and, outside teleoperation, of the
    # contact and proximity fields of the plant state (one per step; teleoperation: fresh
    # every step).
    scene_rate_hz: float = 100.0
    # Realtime teleoperation: a command enters a physics step the moment it arrives (one
    # step per haptic device period, on the device's clock: see DeviceClockGrid) instead
    # of waiting for the plant's next 1 kHz tick; without commands the plant still steps
    # once per period. Path following always uses the tick.
    # What it gains: docs/realtime.md ("old timing" in `teleop latency`). false: apply the
    # newest command at each tick of the plant's own clock.
    apply_on_arrival: bool = True
    # Lockstep and the in-process run: step k applies the command that answers state
    # k - lockstep_delay_steps (before that: hold still, gripper open). 1: the controller's
    # one-sample computation delay, as in realtime (a command reaches the plant during
    # the period after the state it answers); plant and controller then work at the same
    # time on two states in flight (tests/benchmarks/lockstep_speed.py). 0: each step
    # waits for the answer to its own state, so plant and controller take turns.
    lockstep_delay_steps: int = 1
    # The plant checkpoints its whole state (MuJoCo's, its loop's) to the run directory
    # every this much sim time; a restarted plant goes on from the newest checkpoint
    # (teleop/sim/checkpoint.py). 0: no checkpoints (a restarted plant fails the run).
    checkpoint_s: float = 0.1
    # Lockstep: a pending state left unanswered this long (wall clock) ends the run with
    # an ABORTED event instead of waiting for ever. Above a controller's restart time.
    lockstep_timeout_s: float = 15.0
    # Realtime: a watchdog brake that lasts this long (no fresh command at all: the
    # controller, or the operator's site behind it, gone; the link between the sites cut)
    # ends the run with an ABORTED event instead of holding the arm for ever. Above a
    # service's restart time and a link cut the run rides out (docs/sites.md).
    brake_limit_s: float = 15.0

    @property
    def lockstep_states_in_flight(self) -> int:
        """Lockstep: the states the plant has sent and not yet had answered, at most (the
        ones it sends again when no answer comes)."""
        return self.lockstep_delay_steps + 1

    def __post_init__(self) -> None:
        _require(0 < self.timestep_s <= 0.01, "plant.timestep_s in (0, 0.01]")
        _require(self.brake_limit_s > self.watchdog_s, "plant.brake_limit_s > plant.watchdog_s")
        _require(self.checkpoint_s >= 0, "plant.checkpoint_s >= 0")
        _require(
            self.lockstep_timeout_s > LOCKSTEP_RESEND_S,
            f"plant.lockstep_timeout_s > {LOCKSTEP_RESEND_S} (the lockstep re-send period)",
        )
        _require(
            0 <= self.lockstep_delay_steps <= MAX_LOCKSTEP_DELAY_STEPS,
            f"plant.lockstep_delay_steps in [0, {MAX_LOCKSTEP_DELAY_STEPS}]",
        )
        _require(self.scene_rate_hz > 0, "plant.scene_rate_hz > 0")
        _require(self.tool_speed_limit_m_s > 0, "plant.tool_speed_limit_m_s > 0")
        _require(self.contact_force_limit_n > 0, "plant.contact_force_limit_n > 0")
        _require(
            self.tool_speed_stop_m_s > self.tool_speed_limit_m_s,
            "plant.tool_speed_stop_m_s > plant.tool_speed_limit_m_s",
        )
        _require(
            0 <= self.protective_release_m_s < self.tool_speed_limit_m_s,
            "plant.protective_release_m_s in [0, plant.tool_speed_limit_m_s)",
        )
        _require(self.protective_release_s >= 0, "plant.protective_release_s >= 0")
        _require(self.approach_touch_m_s > 0, "plant.approach_touch_m_s > 0")
        _require(self.approach_time_s >= 0, "plant.approach_time_s >= 0")


@dataclass(frozen=True)
class PathConfig:
    """The paper's experiment-1 path, in the world frame (z up, origin at the arm base).

    P(s) = (r sin(w s) + c_x, r cos(w s) + c_y, c_z + a sin(w_z s)).
    The default centre puts the whole circle 0.25-0.45 m from the base axis at
    0.30-0.40 m height, inside the reach of the 6-DOF arm with a good margin.
    """

    center_m: tuple[float, float, float] = (0.10, 0.0, 0.35)
    radius_m: float = 0.35
    omega_rad: float = 0.2  # angular rate of the circle per unit of path parameter s
    z_amplitude_m: float = 0.05
    z_omega_rad: float = 0.1  # rate of the slow vertical sinusoid per unit of s

    def __post_init__(self) -> None:
        _require(self.radius_m > 0, "path.radius_m > 0")
        _require(self.omega_rad > 0, "path.omega_rad > 0")


@dataclass(frozen=True)
class ControlConfig:
    """Gains and limits of the kinematic controller and its dynamic compensation."""

    # Path speed v_P and its slow-down with error: |v_hd| = v_P / (1 + k |h~|).
    path_speed_m_s: float = 0.10
    speed_error_gain_per_m: float = 50.0
    # K in J# (v_d + K tanh(h~ / e0)) e0: position error gain and its saturation length.
    position_gain_per_s: float = 20.0
    position_saturation_m: float = 0.05
    # L: manipulability ascent gain in the task null space.
    null_space_gain: float = 0.5
    # Dynamic compensation q'_ref = M (q''_c + Kd (q'_c - q')) + C q' + g.
    compensation: bool = True
    velocity_gain_per_s: float = 50.0
    # Joint speed limit applied to every reference sent to the plant.
    max_joint_speed_rad_s: float = math.pi
    # The kinematic command's tool speed is scaled down (whole) to this, below the plant's
    # safety limit (plant.tool_speed_limit_m_s), so the plant never cuts a command that
    # kept its clearance caps (the cut would change the direction they were held on).
    max_tool_speed_m_s: float = 0.25
    # Damping of the pseudo-inverse (m). Near singularities it grows smoothly (Nakamura's
    # variable damping) to singular_damping_m as the manipulability falls below
    # singular_manipulability, so the arm slows down instead of swinging through.
    damping_m: float = 1e-4
    singular_manipulability: float = 0.02
    singular_damping_m: float = 0.04
    # A manipulability below this is a singularity crossing: a run event (SINGULARITY).
    singularity_event_manipulability: float = 0.005
    # Rate of CONTROL_STATUS (plots, recorder); the control cycle itself runs per state.
    status_rate_hz: float = 100.0

    def __post_init__(self) -> None:
        for name in (
            "path_speed_m_s",
            "position_gain_per_s",
            "position_saturation_m",
            "velocity_gain_per_s",
            "max_joint_speed_rad_s",
            "max_tool_speed_m_s",
        ):
            _require(getattr(self, name) > 0, f"control.{name} > 0")
        _require(self.speed_error_gain_per_m >= 0, "control.speed_error_gain_per_m >= 0")
        _require(self.null_space_gain >= 0, "control.null_space_gain >= 0")
        _require(self.damping_m >= 0, "control.damping_m >= 0")
        _require(self.singular_manipulability > 0, "control.singular_manipulability > 0")
        _require(self.singular_damping_m >= 0, "control.singular_damping_m >= 0")
        _require(
            self.singularity_event_manipulability >= 0,
            "control.singularity_event_manipulability >= 0",
        )
        _require(self.status_rate_hz > 0, "control.status_rate_hz > 0")


@dataclass(frozen=True)
class ClearanceConfig:
    """Clearance of the arm and gripper from the scene and from themselves, every control
    cycle, and how both control laws keep it (teleop/control/clearance.py,
    docs/clearance.md).

    Distances are MuJoCo's (``mj_geomDistance``) between the arm's collision geoms and
    every static collision geom of the scene file (table, floor, base, bin), and between
    arm links two or more joints apart that can come within ``self_slowdown_m`` of each
    other somewhere in the joint range. The free objects (the cube) are not obstacles:
    the fingers are meant to touch them. Below ``slowdown_m`` the speed at which a link
    approaches what is near falls linearly, to zero at ``stop_m`` (the margin kept); the
    fingers and pairs within the arm have their own, smaller pair of thresholds. Inside
    ``influence_m`` the link is also pushed away in the null space of the tool task.
    """

    # false: the unguarded law (no avoidance); clearance is still measured and reported.
    avoid: bool = True
    # Pairs closer than this (m) are computed, avoided in the null space and reported;
    # farther ones count as this far (min_clearance_m is capped here).
    influence_m: float = 0.08
    # Arm and gripper vs the scene (m): approach slowed below the first, stopped at the second.
    slowdown_m: float = 0.05
    stop_m: float = 0.02
    # The fingers vs the scene (m): a top grasp puts the fingertips 5 mm above the table.
    finger_slowdown_m: float = 0.012
    finger_stop_m: float = 0.002
    # Links of the arm vs each other (m).
    self_slowdown_m: float = 0.015
    self_stop_m: float = 0.005
    # Largest approach speed allowed at the slowdown distance (m/s); it falls linearly
    # to 0 at the stop distance.
    approach_speed_m_s: float = 0.25
    # The approach caps act on the distance a pair will have this far ahead (s) at its
    # measured closing speed: the velocity loops reach a command after about
    # 1 / control.velocity_gain_per_s (20 ms), so a pair closing fast starts braking that
    # much earlier instead of coasting that lag's travel past its stop distance. 0: the
    # distance now.
    approach_lookahead_s: float = 0.02
    # Null space: a link inside influence_m is pushed away at gain * (influence - d) m/s.
    null_space_gain_per_s: float = 4.0
    # Joint limits: pushed back in the null space within this margin (rad), and the
    # approach to a limit stopped at the limit.
    joint_limit_margin_rad: float = 0.3
    joint_limit_gain_per_s: float = 2.0
    # Run events and verdict: a stall is this long without progress (s) while the path
    # advances less than stall_progress of what the commanded speed would cover.
    stall_window_s: float = 0.5
    stall_progress: float = 0.2

    def __post_init__(self) -> None:
        for name in ("influence_m", "approach_speed_m_s", "stall_window_s"):
            _require(getattr(self, name) > 0, f"clearance.{name} > 0")
        for near, far in (("stop_m", "slowdown_m"), ("finger_stop_m", "finger_slowdown_m"),
                          ("self_stop_m", "self_slowdown_m")):  # fmt: skip
            stop, slow = getattr(self, near), getattr(self, far)
            _require(
                0 <= stop < slow <= self.influence_m,
                f"clearance: 0 <= {near} < {far} <= influence_m",
            )
        _require(self.approach_lookahead_s >= 0, "clearance.approach_lookahead_s >= 0")
        for name in ("null_space_gain_per_s", "joint_limit_margin_rad",
                     "joint_limit_gain_per_s"):  # fmt: skip
            _require(getattr(self, name) >= 0, f"clearance.{name} >= 0")
        _require(0 < self.stall_progress < 1, "clearance.stall_progress in (0, 1)")


@dataclass(frozen=True)
class SceneConfig:
    """Where things are in the scene, applied by the plant over the MJCF's own values.

    Empty tuples keep the model file's values. Positions are world frame (m).
    """

    cube_p_m: tuple[float, ...] = ()
    bin_p_m: tuple[float, ...] = ()
    # One (x, y, z) per obstacle geom, in the order of their names (obstacle_0, ...).
    obstacle_p_m: tuple[tuple[float, float, float], ...] = ()
    obstacle_radius_m: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        _require(len(self.cube_p_m) in (0, 3), "scene.cube_p_m: empty or x, y, z")
        _require(len(self.bin_p_m) in (0, 3), "scene.bin_p_m: empty or x, y, z")
        _require(all(r > 0 for r in self.obstacle_radius_m), "scene.obstacle_radius_m > 0")


@dataclass(frozen=True)
class HapticConfig:
    """The emulated Falcon-like 3-DOF device (paper notes: ~0.1 m cube, ~8 N, 1 kHz)."""

    handle_mass_kg: float = 0.15
    # Physical viscous damping b of the handle; bounds the stiffness it can render stably.
    damping_n_s_per_m: float = 3.0
    workspace_half_m: float = 0.05  # the handle moves within +-this per axis (end stops)
    peak_force_n: float = 8.0
    encoder_resolution_m: float = 2e-5  # position quantisation of the encoders
    # Kalman velocity estimate: white-acceleration process noise (m/s^2) of the model.
    kf_accel_noise_m_s2: float = 3.0  # 30 made it noisier than finite differences (tested)
    # The device's servo period (s): it renders the newest local contact model this often,
    # whatever the bus rate (loop.rate_hz; a bus period is a whole number of these).
    render_period_s: float = 0.001
    # The rendered force changes at most this fast (N/s): a new local model ramps in
    # instead of knocking the handle once per bus period (teleop.devices.haptic.device.ForceSlew).
    max_force_rate_n_per_s: float = 2000.0
    # Feedback older than this is stale: the rendered force fades to zero over fade_s.
    stale_feedback_s: float = 0.020
    fade_s: float = 0.020
    # Realtime: hand a feedback force to the motors the moment it arrives (as a driver
    # does) instead of at the device loop's next 1 ms step; see docs/realtime.md.
    render_on_arrival: bool = True
    # The operator's hand, a spring-damper pulling the handle to the hand's target.
    hand_stiffness_n_per_m: float = 200.0
    hand_damping_n_s_per_m: float = 8.0
    # A hand input this far (s of sim time) behind the tick it is used at, with no newer
    # one, is a hand that stopped moving (its operator was starved, frozen or is being
    # restarted): the emulated hand eases the handle back to the centre, so the rate
    # control holds the tool still, and keeps the buttons it held, so a held object is
    # not dropped. A live operator sends each input ahead of the tick it applies from.
    hand_input_stale_s: float = 0.1

    def __post_init__(self) -> None:
        for name in (
            "handle_mass_kg",
            "damping_n_s_per_m",
            "workspace_half_m",
            "peak_force_n",
            "encoder_resolution_m",
            "kf_accel_noise_m_s2",
            "stale_feedback_s",
            "fade_s",
            "hand_input_stale_s",
            "render_period_s",
            "max_force_rate_n_per_s",
        ):
            _require(getattr(self, name) > 0, f"haptic.{name} > 0")


@dataclass(frozen=True)
class HmdConfig:
    """The emulated head-mounted display: scripted head motion, noise, filter, prediction."""

    rate_hz: float = 90.0
    # Where the operator's head is (world frame) and the yaw it faces (rad, 0 = +x).
    head_p_m: tuple[float, float, float] = (-0.45, 0.0, 0.65)
    head_yaw_rad: float = 0.0
    # Scripted motion: slow yaw sway and a small sideways sway.
    yaw_amplitude_rad: float = 0.25
    sway_amplitude_m: float = 0.03
    motion_period_s: float = 7.0
    # Sensor noise (standard deviations) of the tracker.
    position_noise_m: float = 0.002
    yaw_noise_rad: float = 0.004
    # Prediction horizon: the measured motion-to-use latency (s); 0 = none.
    prediction_s: float = 0.020

    def __post_init__(self) -> None:
        _require(0 < self.rate_hz <= 1000, "hmd.rate_hz in (0, 1000]")
        _require(self.motion_period_s > 0, "hmd.motion_period_s > 0")
        _require(0 <= self.prediction_s < 1, "hmd.prediction_s in [0, 1)")


@dataclass(frozen=True)
class EyeViewConfig:
    """The operator's eye view: the scene rendered from the HMD's predicted pose.

    A service of its own (``services/eyeview.py``, renderer in ``teleop/viz/eyeview.py``)
    renders with MuJoCo's offscreen renderer at ``rate_hz`` and publishes EYE_VIEW frames
    (over shared memory: a frame is far above the SHM threshold). Without an HMD (path
    following) it renders from the fixed viewpoint below. Defaults are sized for 2 busy
    cores (docs/eye-view.md).
    """

    enabled: bool = True
    # Also in lockstep runs (tests, batch experiments)? Frames are paced on wall-clock
    # time, so a lockstep run gets few per simulated second, and the renderer's CPU
    # would slow a run that is meant to go as fast as the machine allows.
    in_lockstep: bool = False
    rate_hz: float = 5.0
    width_px: int = 320
    height_px: int = 240
    # Vertical field of view (rad): a headset's, about 90 degrees.
    fov_y_rad: float = 1.5707963267948966
    # Shadow mapping costs about 10x the rest of a software-rendered frame (60-67 ms
    # against 6.5 ms at 320x240 with software GL), so it is off by default.
    shadows: bool = False
    # PLANT_STATE batches are taken at most this often (Zenoh ingress downsampling): the
    # renderer needs one state per frame, not the plant's 1 kHz. 0: take every one.
    state_rate_hz: float = 100.0
    # Fixed viewpoint when no HEAD_POSE arrives (world frame): where the operator's head
    # is (as hmd.head_p_m), looking along yaw (0 = +x) and down by pitch (rad).
    fixed_p_m: tuple[float, float, float] = (-0.45, 0.0, 0.65)
    fixed_yaw_rad: float = 0.0
    fixed_pitch_rad: float = 0.5
    # Scheduling niceness of the renderer process: below the control loops. (Not
    # SCHED_IDLE: starved, its Zenoh threads would stop draining the plant's PLANT_STATE,
    # whose BLOCK publisher would then stall the plant.)
    nice: int = 10
    # Recorder: JPEG quality of the logged frames (1-100); 0 logs raw RGB.
    jpeg_quality: int = 80

    def __post_init__(self) -> None:
        _require(0 < self.rate_hz <= 120, "eyeview.rate_hz in (0, 120]")
        for name in ("width_px", "height_px"):
            _require(16 <= getattr(self, name) <= 4096, f"eyeview.{name} in [16, 4096]")
        _require(0 < self.fov_y_rad < math.pi, "eyeview.fov_y_rad in (0, pi)")
        _require(
            self.state_rate_hz == 0 or self.state_rate_hz >= self.rate_hz,
            "eyeview.state_rate_hz >= eyeview.rate_hz, or 0 (no limit)",
        )
        _require(
            abs(self.fixed_pitch_rad) < math.pi / 2, "eyeview.fixed_pitch_rad in (-pi/2, pi/2)"
        )
        _require(0 <= self.nice <= 19, "eyeview.nice in [0, 19]")
        _require(0 <= self.jpeg_quality <= 100, "eyeview.jpeg_quality in [0, 100]")


# Force feedback stabilisers under delay (TeleopConfig.stabiliser).
STABILISERS = ("none", "tdpa", "wave")
# Wave impedances above this make a wave in flight a wall (N s/m; the record's bounds).
MAX_WAVE_IMPEDANCE_N_S_M = 1000.0


@dataclass(frozen=True)
class TeleopConfig:
    """Teleoperation in the controller: rate control, limits and force feedback."""

    # Handle offset from the device centre (m) -> tool velocity (m/s): v = gain (x - deadband).
    rate_gain_per_s: float = 6.0
    deadband_m: float = 0.004
    max_tool_speed_m_s: float = 0.25
    # Slow down near singularities (MoveIt Servo): full speed below the first condition
    # number of the position Jacobian, stop at the second.
    singularity_slowdown_cond: float = 17.0
    singularity_stop_cond: float = 30.0
    # Slow down within this distance of a joint limit (rad), stop at the limit.
    joint_limit_margin_rad: float = 0.15
    # Robot-side force (N) -> device force (N).
    force_scale: float = 0.5
    # Virtual obstacles: repulsion within the influence distance, felt and obeyed.
    obstacle_influence_m: float = 0.08
    obstacle_stiffness_n_per_m: float = 60.0
    obstacle_avoid_gain_per_s: float = 4.0
    # The table, the bin and the arm's own links (clearance.*): a spring felt per m a pair
    # is inside its slowdown distance, along the tool motion that opens the pair
    # (clearance.slowdown_m - clearance.stop_m = 0.03 m gives 4.5 N at the stop distance).
    scene_stiffness_n_per_m: float = 150.0
    # Joint limits: a spring felt per rad a joint is inside clearance.joint_limit_margin_rad,
    # along the tool motion that moves it away from the limit.
    joint_limit_stiffness_n_per_rad: float = 10.0
    # Workspace spring of the handle (device frame): pulls it back beyond this radius.
    workspace_free_m: float = 0.04
    workspace_stiffness_n_per_m: float = 300.0
    # Grasp detection: both fingers touch the object.
    object_mass_kg: float = 0.2
    # Hold the tool pointing straight down (top grasps), keeping its start heading;
    # false: hold whatever orientation the tool has when teleoperation starts.
    approach_down: bool = True
    # Force feedback under delay (teleop/devices/haptic/passivity.py): "none" renders the force
    # as it comes (the energy it exchanges is observed and reported all the same);
    # "tdpa": the time-domain passivity controller at the handle damps what the delayed
    # channel would give out, at most tdpa_max_damping_n_s_m (and what the handle renders
    # stably). "wave": the handle's rate and the robot's resistance cross as wave
    # variables of impedance wave_impedance_n_s_m (teleop/control/wave.py): passive under
    # any constant delay, a damper of that impedance felt while a wave is in flight.
    stabiliser: str = "none"
    tdpa_max_damping_n_s_m: float = 20.0
    wave_impedance_n_s_m: float = 10.0

    def __post_init__(self) -> None:
        _require(
            self.stabiliser in STABILISERS,
            f"teleop.stabiliser: one of {', '.join(STABILISERS)}",
        )
        _require(self.tdpa_max_damping_n_s_m > 0, "teleop.tdpa_max_damping_n_s_m > 0")
        _require(
            0 < self.wave_impedance_n_s_m <= MAX_WAVE_IMPEDANCE_N_S_M,
            f"teleop.wave_impedance_n_s_m in (0, {MAX_WAVE_IMPEDANCE_N_S_M:g}]",
        )
        _require(self.rate_gain_per_s > 0, "teleop.rate_gain_per_s > 0")
        _require(self.deadband_m >= 0, "teleop.deadband_m >= 0")
        _require(self.max_tool_speed_m_s > 0, "teleop.max_tool_speed_m_s > 0")
        _require(
            self.singularity_stop_cond > self.singularity_slowdown_cond > 1,
            "teleop: singularity_stop_cond > singularity_slowdown_cond > 1",
        )
        _require(self.force_scale >= 0, "teleop.force_scale >= 0")
        _require(self.scene_stiffness_n_per_m >= 0, "teleop.scene_stiffness_n_per_m >= 0")
        _require(
            self.joint_limit_stiffness_n_per_rad >= 0, "teleop.joint_limit_stiffness_n_per_rad >= 0"
        )


@dataclass(frozen=True)
class OperatorConfig:
    """The scripted operator: what it does, how fast it reacts, how it moves its hand."""

    # Task file: a name in deploy/scenarios/, or a path.
    scenario_file: str = "grasp.toml"
    reaction_delay_s: float = 0.2
    decision_rate_hz: float = 100.0
    # The largest offset the hand gives the handle (m); the operator's gain follows from
    # reaction_delay_s (no overshoot for a delayed P loop, see teleop/devices/scripted/operator.py).
    max_hand_offset_m: float = 0.045

    def __post_init__(self) -> None:
        _require(self.reaction_delay_s >= 0, "operator.reaction_delay_s >= 0")
        _require(0 < self.decision_rate_hz <= 1000, "operator.decision_rate_hz in (0, 1000]")

    @property
    def scenario_path(self) -> Path:
        candidate = Path(self.scenario_file)
        if candidate.is_absolute():
            return candidate
        if (DEPLOY_DIR / "scenarios" / candidate).exists():
            return DEPLOY_DIR / "scenarios" / candidate
        return REPO_ROOT / candidate


# Who drives the emulated haptic handle (RunConfig.operator): the scripted operator, or a
# person through one of the human input devices (teleop/devices/person/intent.py).
SCRIPTED = "scripted"
OPERATORS = (SCRIPTED, "keyboard", "gamepad", "spacemouse", "web")
# The person's devices read in the launcher's terminal (the launcher runs them in the
# foreground); the others run under supervisord like every service.
TERMINAL_OPERATORS = ("keyboard",)
# The person's devices that show the operator's eye view (the web page): their runs have
# the eye view in lockstep too.
VIEWING_OPERATORS = ("web",)
# The person's devices read from Linux input (evdev, hidraw):
# teleop/devices/person/input_devices.py.
INPUT_DEVICE_OPERATORS = ("gamepad", "spacemouse")


@dataclass(frozen=True)
class KeyboardConfig:
    """A person at the terminal's keyboard (``--operator keyboard``,
    teleop/devices/person/intent.py): how long a key press moves and the speed steps."""

    # A motion key moves its axis this long after its last press (s): longer than the
    # terminal's key-repeat delay, so a held key moves on without a stutter.
    hold_s: float = 0.6
    # Speed steps, fractions of teleop.max_tool_speed_m_s (+ and - step through them).
    speed_steps: tuple[float, ...] = (0.1, 0.2, 0.4, 0.7, 1.0)
    start_speed_step: int = 2
    # The screen is redrawn this often (Hz).
    screen_rate_hz: float = 10.0

    def __post_init__(self) -> None:
        _require(self.hold_s > 0, "keyboard.hold_s > 0")
        _require(
            len(self.speed_steps) > 0 and all(0 < v <= 1 for v in self.speed_steps),
            "keyboard.speed_steps: fractions in (0, 1]",
        )
        _require(
            0 <= self.start_speed_step < len(self.speed_steps),
            "keyboard.start_speed_step: an index into keyboard.speed_steps",
        )
        _require(0 < self.screen_rate_hz <= 60, "keyboard.screen_rate_hz in (0, 60]")


# A human device's axis map entry: "<view axis>=<sign><device axis>", the view axis x
# (forward), y (left) or z (up), the device axis by its kernel name without the ABS_/REL_
# prefix (X, Y, Z, RX, RY, RZ, HAT0X, ...). Entries for one view axis add up.
_AXIS_MAP_ENTRY = re.compile(r"[xyz]=[+-]?[A-Z][A-Z0-9]*")
_DEVICE_AXIS_NAME = re.compile(r"[A-Z][A-Z0-9]*")
_BUTTON_NAME = re.compile(r"BTN_[A-Z0-9]+")  # a kernel button name, linux/input-event-codes.h
# How a button role acts: "toggle" flips on each press, "hold" is on while a button is held.
BUTTON_MODES = ("toggle", "hold")


def _check_human_device(section: str, axes: tuple[str, ...], dead_zone_fraction: float,
                        gain: float, gripper_buttons: tuple[str, ...],
                        clutch_buttons: tuple[str, ...], gripper_mode: str,
                        clutch_mode: str, switch_buttons: tuple[str, ...]) -> None:  # fmt: skip
    """The checks a gamepad's and a SpaceMouse's sections share (names checked against the
    kernel's tables when the device opens, teleop/devices/person/input_events.py)."""
    _require(
        len(axes) > 0 and all(_AXIS_MAP_ENTRY.fullmatch(a) for a in axes),
        f'{section}.axes: entries like "x=-Y" (view axis x/y/z = sign, device axis name)',
    )
    _require(0 <= dead_zone_fraction < 1, f"{section}.dead_zone_fraction in [0, 1)")
    _require(gain > 0, f"{section}.gain > 0")
    _require(len(gripper_buttons) > 0, f"{section}.gripper_buttons: at least one button")
    roles = {"gripper_buttons": gripper_buttons, "clutch_buttons": clutch_buttons,
             "switch_buttons": switch_buttons}  # fmt: skip
    for name, buttons in roles.items():
        _require(
            all(_BUTTON_NAME.fullmatch(b) for b in buttons),
            f"{section}.{name}: kernel button names like BTN_SOUTH, BTN_0",
        )
    for name, buttons in roles.items():  # one role per button
        for other, others in roles.items():
            shared = sorted(set(buttons) & set(others)) if name < other else []
            _require(not shared, f"{section}.{name} and {section}.{other} share {shared}")
    for name, mode in (("gripper_mode", gripper_mode), ("clutch_mode", clutch_mode)):
        _require(mode in BUTTON_MODES, f"{section}.{name}: one of {', '.join(BUTTON_MODES)}")


@dataclass(frozen=True)
class GamepadConfig:
    """A person with a gamepad (``--operator gamepad``, teleop/devices/person/input_devices.py):
    which stick drives which view axis, the dead zone, the buttons and the rumble.

    Defaults fit the kernel's gamepad layout (xpad, hid-playstation, hid-nintendo): left
    stick forward/back and left/right (a stick pushed up or left reads negative), right
    stick up/down; the triggers are the alternative for z: ``axes = ["x=-Y", "y=-X",
    "z=+RZ", "z=-Z"]`` (right trigger up, left trigger down)."""

    # "auto": the first /dev/input/by-id/*-event-joystick, else the first event device with
    # a gamepad's sticks and buttons; or the path of its event device (/dev/input/eventN).
    device: str = "auto"
    axes: tuple[str, ...] = ("x=-Y", "y=-X", "z=-RY")
    # Axes at rest at their minimum (analogue triggers): read 0..1 from the minimum up;
    # every other axis reads -1..1 about the middle of its range.
    trigger_axes: tuple[str, ...] = ("Z", "RZ")
    # Per axis: deflections below this fraction of full scale read 0, and the rest is
    # rescaled so the output starts at 0 at its edge (the kernel's "flat", if larger, wins).
    dead_zone_fraction: float = 0.15
    # Velocity fraction per unit of deflection beyond the dead zone (1: full deflection is
    # the top speed, teleop.max_tool_speed_m_s).
    gain: float = 1.0
    # Any of these closes / opens the gripper (gripper_mode) and clutches (clutch_mode):
    # toggle, so a held object needs no held button; a clutch held only while pressed.
    gripper_buttons: tuple[str, ...] = ("BTN_SOUTH",)
    gripper_mode: str = "toggle"
    clutch_buttons: tuple[str, ...] = ("BTN_TL", "BTN_TR")
    clutch_mode: str = "hold"
    # A press of any of these drives the next robot (a run of several robots).
    switch_buttons: tuple[str, ...] = ("BTN_NORTH",)
    # Rumble (where the pad has it, FF_RUMBLE): the feedback force's magnitude as strength,
    # 0 below rumble_min_force_n, full at rumble_full_force_n (N).
    rumble: bool = True
    rumble_min_force_n: float = 0.5
    rumble_full_force_n: float = 8.0
    # Each strength plays this long (s), renewed at most every rumble_period_s while the
    # force lasts, so a stopped service stops the rumble within rumble_length_s.
    rumble_length_s: float = 0.2
    rumble_period_s: float = 0.05

    def __post_init__(self) -> None:
        _check_human_device("gamepad", self.axes, self.dead_zone_fraction, self.gain,
                            self.gripper_buttons, self.clutch_buttons, self.gripper_mode,
                            self.clutch_mode, self.switch_buttons)  # fmt: skip
        _require(
            all(_DEVICE_AXIS_NAME.fullmatch(a) for a in self.trigger_axes),
            "gamepad.trigger_axes: axis names like Z, RZ",
        )
        _require(self.device != "", 'gamepad.device: "auto" or a path')
        _require(
            0 <= self.rumble_min_force_n < self.rumble_full_force_n,
            "gamepad: 0 <= rumble_min_force_n < rumble_full_force_n",
        )
        _require(
            0 < self.rumble_period_s <= self.rumble_length_s <= 1,
            "gamepad: 0 < rumble_period_s <= rumble_length_s <= 1",
        )


@dataclass(frozen=True)
class SpaceMouseConfig:
    """A person with a 3Dconnexion SpaceMouse (``--operator spacemouse``,
    teleop/devices/person/input_devices.py): which of its six axes drive the view axes, its
    full scale, the dead zone and the buttons. Rotation is not mapped by default.

    The device's own axes (HID reports and the kernel's events alike): X right, Y towards
    the user, Z down, each positive; so pushing the cap forward, left and up reads -Y,
    -X and -Z, and the defaults map those to x, y and z."""

    # "auto": the first 3Dconnexion hidraw device, else its event device; or a path
    # (/dev/hidrawN or /dev/input/eventN).
    device: str = "auto"
    # Counts of a full deflection (the devices report about +-350).
    full_scale_counts: float = 350.0
    axes: tuple[str, ...] = ("x=-Y", "y=-X", "z=-Z")
    dead_zone_fraction: float = 0.1
    gain: float = 1.0
    # BTN_0 is the left (or menu) button, BTN_1 the right (or fit) button.
    gripper_buttons: tuple[str, ...] = ("BTN_0",)
    gripper_mode: str = "toggle"
    clutch_buttons: tuple[str, ...] = ("BTN_1",)
    clutch_mode: str = "hold"
    # A press of any of these drives the next robot (a run of several robots). None by
    # default: the two buttons of most SpaceMice are the gripper's and the clutch's.
    switch_buttons: tuple[str, ...] = ()
    # Through the kernel's relative axes (REL_X..REL_RZ) a return to 0 is never reported
    # (the kernel drops zero relative events): an axis not reported for this long (s)
    # reads 0. The devices report about every 8-16 ms while deflected.
    rel_hold_s: float = 0.1

    def __post_init__(self) -> None:
        _check_human_device("spacemouse", self.axes, self.dead_zone_fraction, self.gain,
                            self.gripper_buttons, self.clutch_buttons, self.gripper_mode,
                            self.clutch_mode, self.switch_buttons)  # fmt: skip
        _require(self.device != "", 'spacemouse.device: "auto" or a path')
        _require(self.full_scale_counts > 0, "spacemouse.full_scale_counts > 0")
        _require(0 < self.rel_hold_s <= 1, "spacemouse.rel_hold_s in (0, 1]")


@dataclass(frozen=True)
class WebConfig:
    """A person at a web page (``--operator web``, services/web.py): the page's port on
    127.0.0.1, the run's token, and how often the page and the service talk.

    The launcher takes a free loopback port and writes a fresh token to a 0600 file
    under ``<run_dir>/auth`` (teleop/run/web_operator.py); only the file's path is on a
    command line, since other users can read every process's command line."""

    # HTTP port on 127.0.0.1 (the launcher takes a free one); 0: any free port (logged).
    port: int = 0
    # The file holding the run's token: every request must carry it (empty: refused).
    token_file: str = ""
    # The page's state stream (tick, tool, phase, force, ...) is sent this often (Hz).
    state_rate_hz: float = 20.0
    # While it asks for motion, the page repeats its input this often (Hz), and sends a
    # change at once.
    input_rate_hz: float = 20.0
    # This long (s) after the page's newest input, its motion falls back to none (the
    # buttons stay as they were: a held object is not dropped): a closed tab, a lost
    # link or a frozen browser stops the arm.
    input_expiry_s: float = 0.5
    # JPEG quality (1-100) of the eye-view frames the page shows.
    jpeg_quality: int = 80

    def __post_init__(self) -> None:
        _require(0 <= self.port <= 65535, "web.port in [0, 65535]")
        _require(0 < self.state_rate_hz <= 60, "web.state_rate_hz in (0, 60]")
        _require(0 < self.input_rate_hz <= 100, "web.input_rate_hz in (0, 100]")
        _require(
            2 / self.input_rate_hz <= self.input_expiry_s <= 5,
            "web.input_expiry_s in [2 / web.input_rate_hz, 5]: two of the page's inputs fit in it",
        )
        _require(1 <= self.jpeg_quality <= 100, "web.jpeg_quality in [1, 100]")


@dataclass(frozen=True)
class CpuConfig:
    """CPU affinity of the services (CPU numbers; empty = let the kernel choose).

    The default is laid out for the 2-core target: the plant alone on CPU 0 (warm
    caches, no migrations, nothing waking up on its core), controller, recorder and eye
    view on CPU 1; haptic, HMD and operator free. Pinned, the realtime plant keeps time
    closer and overruns less than unpinned; lockstep speed is the same either way.
    CPUs the machine does not have are ignored (a warning says so); on a machine with
    more cores give each loop its own.
    """

    plant: tuple[int, ...] = (0,)
    controller: tuple[int, ...] = (1,)
    haptic: tuple[int, ...] = ()
    hmd: tuple[int, ...] = ()
    operator: tuple[int, ...] = ()
    recorder: tuple[int, ...] = (1,)
    eyeview: tuple[int, ...] = (1,)
    # Lockstep: the recorder shares the plant's CPU instead. With the lockstep delay the
    # controller is the busier of the two (the plant waits for it part of each cycle).
    recorder_lockstep: tuple[int, ...] = (0,)
    # Realtime runs: SCHED_FIFO priority (1-99) of the bilateral loop's processes; 0 =
    # normal scheduling. A FIFO thread that wakes runs at once, ahead of every normal
    # process (recorder, eye view, HMD, operator, anything else on the host), so a
    # message waits for a core only while another loop service is working: on a 2-core
    # machine the round trip's p99 and the samples shed while behind fall several-fold
    # (tests/benchmarks/latency_stack_variants.py measures it). The loops are event
    # driven (no busy wait), and the kernel's RT throttling (sched_rt_runtime_us) keeps
    # 5 % of each CPU for normal tasks in any case. Not in lockstep: there plant and
    # controller run flat out and would starve the recorder. Needs CAP_SYS_NICE (root
    # has it); without it a warning says so and the service runs normally scheduled.
    fifo_priority: int = 40
    # Which processes get it: the loop services, and the operator that feeds them (its
    # hand; 100 light decisions a second). Normally scheduled, or below the loops, the
    # operator waits behind them, and on 2 cores they can keep both busy: its hand
    # inputs then come late (haptic.hand_input_stale_s), and a recorder or eye view
    # restarting (seconds of imports) takes the CPU it needs.
    fifo_services: tuple[str, ...] = ("plant", "controller", "haptic", "operator")
    # A restart of one of fifo_services (killed, crashed) runs its start-up (imports,
    # model loading: seconds of CPU) under SCHED_FIFO at this priority, in both timing
    # modes: below the loops, above every normally scheduled process. Realtime loops
    # leave a small share of 2 cores to everything else, and a normally scheduled
    # restart shares it with whatever else runs on the host (teleop.run.restart_priority).
    # 0: restarts start normally scheduled. Must be below fifo_priority when that is set.
    restart_fifo_priority: int = 1
    # Realtime runs: one spinner per CPU (teleop/run/idle_poll.py: SCHED_IDLE in a CPU
    # cgroup marked idle) so the idle CPUs poll instead of halting. On a KVM guest a
    # halted vCPU leaves its host core (cold caches, a hypervisor exit on every wake-up);
    # polling shortens the round trip and the services' own CPU time. Anything else that
    # wants a CPU preempts its spinner at once; the cost is CPUs that read 100 % busy
    # while the stack runs. The floor's relay chain polls alike.
    idle_poll: bool = True
    # Which CPUs poll (empty: every CPU the launching process may use). On a machine
    # with more cores than the stack needs, list the loop services' CPUs only.
    idle_poll_cpus: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        names = ("plant", "controller", "haptic", "hmd", "operator", "recorder", "eyeview",
                 "recorder_lockstep", "idle_poll_cpus")  # fmt: skip
        for name in names:
            _require(all(c >= 0 for c in getattr(self, name)), f"cpu.{name}: CPU numbers >= 0")
        _require(0 <= self.fifo_priority <= 99, "cpu.fifo_priority in [0, 99]")
        _require(
            0 <= self.restart_fifo_priority <= 99
            and (not self.fifo_priority or self.restart_fifo_priority < self.fifo_priority),
            "cpu.restart_fifo_priority in [0, 99] and below cpu.fifo_priority",
        )

    def for_service(self, service: str, mode: str) -> tuple[int, ...]:
        """The CPUs of ``service`` in timing ``mode`` (empty: the kernel's choice)."""
        if service == "recorder" and mode == "lockstep":
            return self.recorder_lockstep
        return tuple(getattr(self, service, ()))

    def polls_idle(self, mode: str) -> bool:
        """Whether a stack in timing ``mode`` keeps its idle CPUs polling."""
        return self.idle_poll and mode == "realtime"

    def fifo_priority_for(self, service: str, mode: str) -> int:
        """SCHED_FIFO priority of ``service`` in timing ``mode``; 0: normal scheduling."""
        if mode != "realtime" or service not in self.fifo_services:
            return 0
        return self.fifo_priority


@dataclass(frozen=True)
class BusConfig:
    """How services reach each other over Zenoh."""

    # Zenoh json5 config: a file name inside deploy/zenoh/, or a path.
    zenoh_config: str = "local.json5"
    # Where the run's first service listens and every other connects (loopback only).
    endpoint: str = "tcp/127.0.0.1:7447"
    shm: bool = True
    shm_pool_bytes: int = 16 * 1024 * 1024
    # With shm: Zenoh's low-latency unicast transport (a put writes to the link itself,
    # no TX pipeline thread to hand it to; it has no QoS, so no priorities, and cannot
    # fragment: every payload over the SHM threshold then goes through shared memory,
    # which never falls back to the socket; without shm the default transport is kept,
    # as TCP must fragment an eye-view frame). It shortens the round trip by about a
    # third (tests/benchmarks/latency_stack_variants.py). With it, two peers that connect
    # to each other at once may never link: local.json5 lets only one of a pair connect
    # (gossip autoconnect_strategy "greater-zid"), and the launchers link the services
    # by an explicit mesh (see gossip below). Service.become_ready reports a pair that
    # never links (unlinked_peers).
    lowlatency: bool = True
    # How the peers of a run find each other. With gossip (the default), every process
    # connects to the run's listener (``endpoint``) and learns the others from it, then
    # links to them itself. A launcher instead gives every service the whole mesh
    # (teleop.run.stack.peer_mesh): its own listening endpoint and those of the peers it
    # connects to, with gossip off. Why: with the low-latency transport, a Zenoh 1.10.2
    # receive thread that handles gossip's link states holds the routing lock while it
    # blocks on a send, and a session declaring a subscriber meanwhile waits for that
    # lock for ever (a known class of upstream deadlocks under peer churn, zenoh issue
    # 2581): at start-up a service stuck in declare_subscriber, never alive, deaf to
    # SIGINT, in a few stacks of a hundred; none with the mesh.
    gossip: bool = True
    # This process's own listening endpoint when it is not the run's listener; empty:
    # an ephemeral loopback port (the peers learn it through gossip).
    peer_listen_endpoint: str = ""
    # Peers this process connects to besides ``endpoint`` (the launcher's mesh).
    peer_connect_endpoints: tuple[str, ...] = ()
    # Zenoh config entries set over the file, last: "path=json5", e.g.
    # 'transport/shared_memory/mode="lazy"' (the tuning benchmark tries variants this way).
    zenoh_overrides: tuple[str, ...] = ()
    # Launchers (teleop run / up / latency) give every process of a run its own user,
    # password and Zenoh id and an access-control list from the graph
    # (teleop/bus/access.py): only this run's processes can link, each may publish only
    # what the graph lets it. false: an open bus (any local process can join).
    secure: bool = True
    # With secure: the launchers make a certificate authority for the run and one
    # certificate per process (teleop/bus/tls.py) and link the run over tls/ endpoints
    # only, mutual TLS: both ends of every link are authenticated, each process's file
    # holds its own key only, and the access-control list knows a process by its
    # certificate's name and its session's Zenoh id together. Encrypts the bus; shared
    # memory and the low-latency transport work over TLS links as over TCP. false:
    # user/password authentication, where every service's file names the run's password
    # dictionary (see teleop/bus/access.py). Ignored without secure. Cost: see
    # docs/protocol.md, "TLS cost".
    tls: bool = True
    # This process's credentials file (written by its launcher; empty: no authentication).
    credentials_file: str = ""
    # Records per message on the observers' copies of the fast streams (recorder, eye
    # view; topics.plant_state_batch, ...): one message instead of 10 saves the recorder ~9
    # wake-ups per 10 ms at 1 kHz. Fewer when a message would reach the shared-memory
    # threshold (teleop.bus.session.batch_records: 6 plant states of 483 B).
    observer_batch_records: int = 10

    def __post_init__(self) -> None:
        _require("/" in self.endpoint, "bus.endpoint like tcp/127.0.0.1:7447")
        _require(
            all("/" in e for e in (*self.peer_connect_endpoints, self.peer_listen_endpoint or "/")),
            "bus.peer_listen_endpoint and bus.peer_connect_endpoints like tcp/127.0.0.1:7448",
        )
        _require(self.observer_batch_records >= 1, "bus.observer_batch_records >= 1")
        _require(
            all("=" in entry for entry in self.zenoh_overrides),
            "bus.zenoh_overrides: entries like path=json5value",
        )
        _require(self.shm_pool_bytes >= 1 << 16, "bus.shm_pool_bytes >= 65536")

    @property
    def mutual_tls(self) -> bool:
        """Whether a launcher's run links over mutual TLS (``tls`` on a ``secure`` bus)."""
        return self.secure and self.tls

    @property
    def zenoh_config_path(self) -> Path:
        candidate = Path(self.zenoh_config)
        if candidate.is_absolute():
            return candidate
        if (DEPLOY_DIR / "zenoh" / candidate).exists():
            return DEPLOY_DIR / "zenoh" / candidate
        return REPO_ROOT / candidate


# The two sites of a run split across hosts (docs/sites.md): the robot's (plant,
# controller, recorder, eye view) and the operator's (haptic device, HMD, operator).
ROBOT_SITE = "robot"
OPERATOR_SITE = "operator"
SITES = (ROBOT_SITE, OPERATOR_SITE)
# Longest round trip a lockstep run emulates (ms): ten times a transatlantic link's.
MAX_EMULATED_ROUND_TRIP_MS = 2000.0


@dataclass(frozen=True)
class SiteConfig:
    """Which site of a two-host run this process belongs to, and how the two sites'
    routers link (docs/sites.md). Empty ``name``: the whole stack on one host."""

    name: str = ""  # "" (one host), "robot" or "operator"
    # A run of several robots (run.robots): the robot a robot site runs, when not the
    # first. The first robot's site ("") is the hub: it makes the run's identities, runs
    # the recorder, and its router is the one every other site's router connects to.
    robot: str = ""
    # The hub's router listens here for the other sites' routers: tls/ADDR:PORT with an
    # address of this host the others can reach.
    listen: str = ""
    # The operator site's router, and another robot's site's, connect here: the hub's
    # ``listen``.
    connect: str = ""
    # A round trip between the two sites emulated in sim time (ms; lockstep runs with the
    # scripted operator): what one site sends, the other takes this much simulated time
    # later, half each way (an odd number of ticks: the extra one on the way back). The
    # controller then sees the handle, and the handle feels the force, as they were then;
    # the operator sees the scene that much later too. What a distance does to the
    # bilateral loop, on any machine (docs/sites.md); a real network's delay is emulated
    # between two sites' routers by teleop.bench.netem.
    emulated_round_trip_ms: float = 0.0

    def __post_init__(self) -> None:
        _require(self.name in ("", *SITES), f"site.name: empty or one of {', '.join(SITES)}")
        _require(
            0.0 <= self.emulated_round_trip_ms <= MAX_EMULATED_ROUND_TRIP_MS,
            f"site.emulated_round_trip_ms in [0, {MAX_EMULATED_ROUND_TRIP_MS:g}]",
        )
        for key, endpoint in (("listen", self.listen), ("connect", self.connect)):
            _require(
                not endpoint or endpoint.startswith("tls/"),
                f"site.{key}: tls/ADDRESS:PORT (sites link over mutual TLS only)",
            )
        hub = self.name == ROBOT_SITE and not self.robot
        _require(not self.robot or self.name == ROBOT_SITE, "site.robot: a robot site's only")
        _require(not self.listen or hub, "site.listen: the first robot's site's only")
        _require(
            not self.connect or not hub, "site.connect: the operator site's or another robot's"
        )


@dataclass(frozen=True)
class RecorderConfig:
    """The Rerun recorder service."""

    # Recording file; empty = <run dir>/recording.rrd.
    rrd_path: str = ""
    # Also open the native Rerun viewer (never in tests or CI).
    spawn: bool = False
    # Also stream to this Rerun gRPC server (``rerun+http://127.0.0.1:PORT/proxy``); empty:
    # none. ``teleop run --web`` starts a web viewer and sets it.
    grpc_url: str = ""
    # Draw the scene in 3D from the MuJoCo model (arm, gripper, table, bin, cube, obstacles).
    scene3d: bool = True
    # Rate of the 3D arm pose (Hz of sim time): the plant state is 1 kHz, a view needs less.
    scene_rate_hz: float = 30.0
    # A ghost pose of the arm (stroboscopic view, paper Fig. 7) every this much sim time (s).
    ghost_period_s: float = 3.0
    # Loop rates are counted over windows of this much of the producer's clock (s).
    rate_window_s: float = 1.0
    # Buffered samples are sent to Rerun in columns this often (s). Each flush costs about
    # the same whatever it carries (a send per entity): measured, a lockstep grasp's
    # recorder took 18.4 CPU s at 0.1 s and 10.2 at 0.5 s, and its run 62 -> 51 s.
    flush_period_s: float = 0.5
    # The same while a live viewer watches (``spawn`` or ``grpc_url``): its plots move on
    # at every flush.
    live_flush_period_s: float = 0.1
    # A segment's file is closed, its footer written, once it holds this much (MB), and
    # the recording goes on in the next (teleop.viz.recording_file): Rerun keeps a
    # file's chunk index, about as large as the file, in memory until its footer, so
    # this bounds the recorder's memory whatever the run's length.
    segment_mb: float = 16.0
    # The recording's segments on disk at most (MB; 0: every one kept): past it the
    # oldest closed segments are deleted, never the one being written, so a stack kept
    # up for a day holds its newest hours. At least two segments.
    keep_mb: float = 0.0
    # Scheduling niceness (0 normal .. 19 lowest): a logger must not delay the loops.
    # Measured, realtime grasp on 2 cores: 10 gave realtime factor 0.82-0.87 and 40-45 %
    # plant overruns against 0.61-0.79 and 55-73 % at 0; lockstep unchanged (1.8x).
    nice: int = 10

    @property
    def flush_every_s(self) -> float:
        """How often the buffered samples go out: ``live_flush_period_s`` while a live
        viewer watches, ``flush_period_s`` for the file alone."""
        live = self.spawn or bool(self.grpc_url)
        return self.live_flush_period_s if live else self.flush_period_s

    def __post_init__(self) -> None:
        _require(0 < self.flush_period_s <= 5, "recorder.flush_period_s in (0, 5]")
        _require(0 < self.live_flush_period_s <= 5, "recorder.live_flush_period_s in (0, 5]")
        _require(0 <= self.nice <= 19, "recorder.nice in [0, 19]")
        _require(0 < self.segment_mb <= 4096, "recorder.segment_mb in (0, 4096]")
        _require(
            self.keep_mb == 0 or self.keep_mb >= 2 * self.segment_mb,
            "recorder.keep_mb: 0 (keep every segment) or at least two segments "
            f"(2 x recorder.segment_mb = {2 * self.segment_mb:g})",
        )
        _require(self.scene_rate_hz > 0, "recorder.scene_rate_hz > 0")
        _require(self.ghost_period_s > 0, "recorder.ghost_period_s > 0")
        _require(self.rate_window_s > 0, "recorder.rate_window_s > 0")
        _require(
            not self.grpc_url or self.grpc_url.startswith(("rerun://", "rerun+http")),
            "recorder.grpc_url: empty or a rerun:// / rerun+http(s):// URL",
        )


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
        _require(self.duration_s > 0, "run.duration_s > 0")
        _require(self.mode in TIMING_MODES, f"run.mode: one of {', '.join(TIMING_MODES)}")
        _require(self.scenario in SCENARIOS, f"run.scenario: one of {', '.join(SCENARIOS)}")
        _require(0 <= self.settle_s, "run.settle_s >= 0")
        _require(self.initial_q_noise_rad >= 0, "run.initial_q_noise_rad >= 0")
        _require(self.operator in OPERATORS, f"run.operator: one of {', '.join(OPERATORS)}")
        _require(1 <= self.robots <= MAX_ROBOTS, f"run.robots in [1, {MAX_ROBOTS}]")


@dataclass(frozen=True)
class Config:
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
            _require(
                self.run.mode == "lockstep",
                "site.emulated_round_trip_ms: lockstep runs only (in realtime, run two sites "
                "with teleop.bench.netem between their routers: docs/sites.md)",
            )
            _require(
                self.run.operator == SCRIPTED,
                "site.emulated_round_trip_ms: the scripted operator only (a person's screen "
                "would show the scene undelayed)",
            )
            ticks = self.site.emulated_round_trip_ms / (self.tick_s * 1e3)
            _require(
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
        _require(
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
            _require(
                value <= rate * (1 + 1e-9), f"{name} = {value:g}: at most loop.rate_hz ({rate:g})"
            )
        renders = self.tick_s / self.haptic.render_period_s
        _require(
            renders >= 1 - 1e-9 and abs(renders - round(renders)) < 1e-6,
            f"haptic.render_period_s = {self.haptic.render_period_s:g}: a bus period "
            f"({self.tick_s:g} s) must be a whole number of them",
        )
        watchdog_ticks = self.plant.watchdog_s * rate
        _require(
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
        _require(self.run.teleoperated, f"{many}: a teleoperated scenario (grasp)")
        if self.run.operator in INPUT_DEVICE_OPERATORS:
            device = self.gamepad if self.run.operator == "gamepad" else self.spacemouse
            section = self.run.operator
            _require(
                len(device.switch_buttons) > 0,
                f"{many}: {section}.switch_buttons is empty: name the button that drives "
                "the next robot (a SpaceMouse's two are the gripper's and the clutch's by "
                f"default: e.g. --set '{section}.switch_buttons=[\"BTN_1\"]' "
                f"--set '{section}.clutch_buttons=[]')",
            )
        _require(
            not self.site.emulated_round_trip_ms,
            f"{many}: not with site.emulated_round_trip_ms",
        )
        _require(
            self.teleop.stabiliser != "wave",
            f"{many}: not with teleop.stabiliser=wave (an idle robot's wave port would "
            "drift on its own resistance)",
        )
        ids = self.robot_ids()
        _require(
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


def _coerce(value: Any, annotation: Any, key: str) -> Any:
    """Convert a TOML value to the field's annotated type, or raise ConfigError."""
    origin = typing.get_origin(annotation)
    if dataclasses.is_dataclass(annotation):
        _require(isinstance(value, Mapping), f"{key}: expected a table")
        return _build(annotation, value, key)
    if annotation is bool:
        _require(isinstance(value, bool), f"{key}: expected true or false, got {value!r}")
        return value
    if annotation is int:
        _require(
            isinstance(value, int) and not isinstance(value, bool), f"{key}: expected an integer"
        )
        return value
    if annotation is float:
        _require(
            isinstance(value, int | float) and not isinstance(value, bool),
            f"{key}: expected a number, got {value!r}",
        )
        _require(math.isfinite(value), f"{key}: must be finite")
        return float(value)
    if annotation is str:
        _require(isinstance(value, str), f"{key}: expected a string, got {value!r}")
        return value
    if origin is tuple:
        _require(isinstance(value, list | tuple), f"{key}: expected a list")
        args = typing.get_args(annotation)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{key}[{i}]") for i, v in enumerate(value))
        _require(len(value) == len(args), f"{key}: expected {len(args)} items")
        return tuple(
            _coerce(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True))
        )
    if origin in (typing.Union, types.UnionType):
        raise ConfigError(f"{key}: unsupported union type")
    return value


def _fields(cls: type, table: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    """The constructor arguments of dataclass ``cls`` from ``table``: no unknown key, no
    missing key without a default, every value coerced to its field's type."""
    hints = typing.get_type_hints(cls)
    fields = dataclasses.fields(cls)
    where = prefix or "config"
    names = [f.name for f in fields]
    unknown = sorted(set(table) - set(names))
    _require(
        not unknown, f"{where}: unknown key(s) {', '.join(map(_with_suggestion(names), unknown))}"
    )
    missing = [
        f.name
        for f in fields
        if f.name not in table
        and f.default is dataclasses.MISSING
        and f.default_factory is dataclasses.MISSING
    ]
    _require(not missing, f"{where}: missing key(s) {', '.join(missing)}")
    return {
        name: _coerce(value, hints[name], f"{prefix}.{name}" if prefix else name)
        for name, value in table.items()
    }


def _with_suggestion(names: Sequence[str]) -> Callable[[str], str]:
    """``key`` -> ``key (did you mean X?)`` when one of ``names`` is close to it."""

    def suggest(key: str) -> str:
        close = difflib.get_close_matches(key, names, n=1, cutoff=SUGGESTION_CUTOFF)
        return f"{key} (did you mean {close[0]}?)" if close else key

    return suggest


# A value shown in an error message: scalars and short lists, not whole sections.
_SHOWN_VALUE_TYPES = (bool, int, float, str, tuple)


def _with_value(message: str, kwargs: Mapping[str, Any]) -> str:
    """Append the offending value to a range error that starts with the field's dotted
    name (``run.duration_s > 0`` -> ``... (got -3.0)``), when it was given."""
    match = re.match(r"([A-Za-z_][\w.]*)", message)
    if match is None or "got " in message:
        return message
    name = match.group(1).rsplit(".", 1)[-1]
    value = kwargs.get(name, _MISSING)
    if value is _MISSING or not isinstance(value, _SHOWN_VALUE_TYPES):
        return message
    return f"{message} (got {value!r})"


_MISSING = object()


def _build(cls: type, table: Mapping[str, Any], prefix: str) -> Any:
    kwargs = _fields(cls, table, prefix)
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(_with_value(str(exc), kwargs)) from None


def build(cls: type[_T], table: Mapping[str, Any], prefix: str) -> _T:
    """A ``cls`` dataclass from a parsed TOML table, checked as the config's sections are.

    Unknown keys, missing keys (fields without a default) and mistyped values are errors
    naming ``prefix.key``; a value the dataclass itself refuses (its ``__post_init__``) is
    an error prefixed with ``prefix``. Other TOML files (scenarios) load through this.
    """
    kwargs = _fields(cls, table, prefix)
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(f"{prefix}: {_with_value(str(exc), kwargs)}") from exc


def _parse_override(text: str) -> tuple[list[str], Any]:
    key, sep, raw = text.partition("=")
    _require(bool(sep) and bool(key.strip()), f"--set {text!r}: expected dotted.key=value")
    raw = raw.strip()
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError as exc:
        if raw[:1] in TOML_OPENERS:  # meant as a TOML literal: say what is wrong with it
            raise ConfigError(
                f"--set {key.strip()}={raw}: not valid TOML ({exc}); e.g. [0.1, 0.0, 0.3], "
                '"text", true'
            ) from None
        value = raw  # a bare word: taken as a string
    return key.strip().split("."), value


def _merge_override(table: dict[str, Any], path: list[str], value: Any) -> None:
    node = table
    for part in path[:-1]:
        node = node.setdefault(part, {})
        _require(isinstance(node, dict), f"--set {'.'.join(path)}: {part} is not a table")
    node[path[-1]] = value


def read_toml(path: Path, error: type[ConfigError] = ConfigError) -> dict[str, Any]:
    """A TOML file as a table; ``error`` (a ConfigError) names the file on any problem."""
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError as exc:
        raise error(f"{path.name} not found: {path}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: {exc}") from exc


def load_config(path: str | Path | None = None, overrides: Iterable[str] = ()) -> Config:
    """Read a TOML config (default ``deploy/teleop.toml``), apply ``--set`` overrides.

    Missing keys take the dataclass defaults; unknown keys are an error, so a typo in
    a key never passes silently.
    """
    config_path = Path(path) if path is not None else DEFAULT_CONFIG_FILE
    table: dict[str, Any] = {}
    if path is not None or config_path.exists():
        table = read_toml(config_path)
    for text in overrides:
        keys, value = _parse_override(text)
        _merge_override(table, keys, value)
    try:
        return _build(Config, table, "")
    except TypeError as exc:
        raise ConfigError(str(exc)) from exc
