"""The operator station's devices: the emulated haptic device (``haptic``), the
head-mounted display (``hmd``), the operator's eye view (``eyeview``), and teleoperation's
rate control and force feedback in the controller (``teleop``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from teleop.core.config.base import require


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
            require(getattr(self, name) > 0, f"haptic.{name} > 0")


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
        require(0 < self.rate_hz <= 1000, "hmd.rate_hz in (0, 1000]")
        require(self.motion_period_s > 0, "hmd.motion_period_s > 0")
        require(0 <= self.prediction_s < 1, "hmd.prediction_s in [0, 1)")


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
    # Shadow mapping costs several times the rest of a software-rendered frame
    # (docs/eye-view.md), so it is off by default.
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
        require(0 < self.rate_hz <= 120, "eyeview.rate_hz in (0, 120]")
        for name in ("width_px", "height_px"):
            require(16 <= getattr(self, name) <= 4096, f"eyeview.{name} in [16, 4096]")
        require(0 < self.fov_y_rad < math.pi, "eyeview.fov_y_rad in (0, pi)")
        require(
            self.state_rate_hz == 0 or self.state_rate_hz >= self.rate_hz,
            "eyeview.state_rate_hz >= eyeview.rate_hz, or 0 (no limit)",
        )
        require(abs(self.fixed_pitch_rad) < math.pi / 2, "eyeview.fixed_pitch_rad in (-pi/2, pi/2)")
        require(0 <= self.nice <= 19, "eyeview.nice in [0, 19]")
        require(0 <= self.jpeg_quality <= 100, "eyeview.jpeg_quality in [0, 100]")


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
        require(
            self.stabiliser in STABILISERS,
            f"teleop.stabiliser: one of {', '.join(STABILISERS)}",
        )
        require(self.tdpa_max_damping_n_s_m > 0, "teleop.tdpa_max_damping_n_s_m > 0")
        require(
            0 < self.wave_impedance_n_s_m <= MAX_WAVE_IMPEDANCE_N_S_M,
            f"teleop.wave_impedance_n_s_m in (0, {MAX_WAVE_IMPEDANCE_N_S_M:g}]",
        )
        require(self.rate_gain_per_s > 0, "teleop.rate_gain_per_s > 0")
        require(self.deadband_m >= 0, "teleop.deadband_m >= 0")
        require(self.max_tool_speed_m_s > 0, "teleop.max_tool_speed_m_s > 0")
        require(
            self.singularity_stop_cond > self.singularity_slowdown_cond > 1,
            "teleop: singularity_stop_cond > singularity_slowdown_cond > 1",
        )
        require(self.force_scale >= 0, "teleop.force_scale >= 0")
        require(self.scene_stiffness_n_per_m >= 0, "teleop.scene_stiffness_n_per_m >= 0")
        require(
            self.joint_limit_stiffness_n_per_rad >= 0, "teleop.joint_limit_stiffness_n_per_rad >= 0"
        )
