"""The robot's sections: which model file and names (``robot``), the bus rate of the
bilateral loop (``loop``), and the MuJoCo plant's physics, watchdog and protections
(``plant``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from teleop.core.config.base import ASSETS_DIR, REPO_ROOT, require


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
        require(
            bool(self.robot_id) and "/" not in self.robot_id, "robot.robot_id: non-empty, no '/'"
        )
        require(len(self.arm_joints) >= 3, "robot.arm_joints: at least 3 joints")
        require(
            len(self.arm_actuators) == len(self.arm_joints),
            "robot.arm_actuators: one actuator per arm joint",
        )
        require(
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
        require(self.rate_hz >= MIN_LOOP_RATE_HZ, f"loop.rate_hz >= {MIN_LOOP_RATE_HZ:g}")


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
        require(0 < self.timestep_s <= 0.01, "plant.timestep_s in (0, 0.01]")
        require(self.brake_limit_s > self.watchdog_s, "plant.brake_limit_s > plant.watchdog_s")
        require(self.checkpoint_s >= 0, "plant.checkpoint_s >= 0")
        require(
            self.lockstep_timeout_s > LOCKSTEP_RESEND_S,
            f"plant.lockstep_timeout_s > {LOCKSTEP_RESEND_S} (the lockstep re-send period)",
        )
        require(
            0 <= self.lockstep_delay_steps <= MAX_LOCKSTEP_DELAY_STEPS,
            f"plant.lockstep_delay_steps in [0, {MAX_LOCKSTEP_DELAY_STEPS}]",
        )
        require(self.scene_rate_hz > 0, "plant.scene_rate_hz > 0")
        require(self.tool_speed_limit_m_s > 0, "plant.tool_speed_limit_m_s > 0")
        require(self.contact_force_limit_n > 0, "plant.contact_force_limit_n > 0")
        require(
            self.tool_speed_stop_m_s > self.tool_speed_limit_m_s,
            "plant.tool_speed_stop_m_s > plant.tool_speed_limit_m_s",
        )
        require(
            0 <= self.protective_release_m_s < self.tool_speed_limit_m_s,
            "plant.protective_release_m_s in [0, plant.tool_speed_limit_m_s)",
        )
        require(self.protective_release_s >= 0, "plant.protective_release_s >= 0")
        require(self.approach_touch_m_s > 0, "plant.approach_touch_m_s > 0")
        require(self.approach_time_s >= 0, "plant.approach_time_s >= 0")
