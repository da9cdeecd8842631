"""The controller's sections: the paper's desired path (``path``), the kinematic
controller's gains and limits (``control``), the clearance it keeps (``clearance``), and
where the scene's objects are (``scene``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from teleop.core.config.base import require


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
        require(self.radius_m > 0, "path.radius_m > 0")
        require(self.omega_rad > 0, "path.omega_rad > 0")


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
            require(getattr(self, name) > 0, f"control.{name} > 0")
        require(self.speed_error_gain_per_m >= 0, "control.speed_error_gain_per_m >= 0")
        require(self.null_space_gain >= 0, "control.null_space_gain >= 0")
        require(self.damping_m >= 0, "control.damping_m >= 0")
        require(self.singular_manipulability > 0, "control.singular_manipulability > 0")
        require(self.singular_damping_m >= 0, "control.singular_damping_m >= 0")
        require(
            self.singularity_event_manipulability >= 0,
            "control.singularity_event_manipulability >= 0",
        )
        require(self.status_rate_hz > 0, "control.status_rate_hz > 0")


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
            require(getattr(self, name) > 0, f"clearance.{name} > 0")
        for near, far in (("stop_m", "slowdown_m"), ("finger_stop_m", "finger_slowdown_m"),
                          ("self_stop_m", "self_slowdown_m")):  # fmt: skip
            stop, slow = getattr(self, near), getattr(self, far)
            require(
                0 <= stop < slow <= self.influence_m,
                f"clearance: 0 <= {near} < {far} <= influence_m",
            )
        require(self.approach_lookahead_s >= 0, "clearance.approach_lookahead_s >= 0")
        for name in ("null_space_gain_per_s", "joint_limit_margin_rad",
                     "joint_limit_gain_per_s"):  # fmt: skip
            require(getattr(self, name) >= 0, f"clearance.{name} >= 0")
        require(0 < self.stall_progress < 1, "clearance.stall_progress in (0, 1)")


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
        require(len(self.cube_p_m) in (0, 3), "scene.cube_p_m: empty or x, y, z")
        require(len(self.bin_p_m) in (0, 3), "scene.bin_p_m: empty or x, y, z")
        require(all(r > 0 for r in self.obstacle_radius_m), "scene.obstacle_radius_m > 0")
