"""Force feedback for bilateral teleoperation, one component at a time (paper section 4.3).

Robot-side components are forces ON the gripper/arm in the world frame (N): what the
operator should feel as if holding the tool.

- contact: the plant's measured contact force on the gripper (``Plant.gripper_contact_force``,
  in PLANT_STATE), minus the held object's weight (rendered separately, not twice).
- weight: m g downwards while an object is held. Grasp detection is contact-based
  (:func:`teleop.sim.contact.held_object`): the object is held when BOTH fingers press on it from
  opposite sides. That is the
  physical definition of a pinch grasp and needs no thresholds on the command; the
  alternative (gripper command closed + contact force above a threshold) fires when the
  closed gripper is pushed on the table, and misses a grasp during the closing motion.
  The plant, which has the contacts, runs it and reports the held body's mass.
- obstacle: a fictitious spring F = k (d0 - d) n from a virtual obstacle within the
  influence distance d0, n pointing from the obstacle to the arm.
- workspace: a spring in the device frame that pulls the handle back inside a sphere
  of radius ``workspace_free_m`` (device-side only, not a robot force).
- scene: the table, the bin and the other static geoms of the scene file, within their
  slowdown distance of an arm link (:mod:`teleop.control.clearance`): a spring per pair,
  along the tool motion that opens the pair (computed by the control law, which knows
  the arm's Jacobians: :meth:`teleop.control.teleop.TeleopController.prepare`).
- limits: the arm's own limits, the same way: joints near their limits and links of
  the arm near each other.

:func:`device_force` turns them into the force the haptic device renders, and
:func:`check_stability` keeps the rendered stiffness within Colgate's passivity bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from teleop.core.config import HapticConfig, TeleopConfig

if TYPE_CHECKING:  # the haptic device imports this module without MuJoCo
    from teleop.sim.proximity import ProximitySample

# Gravity (m/s^2) along -z, as in the scene's <option gravity>.
STANDARD_GRAVITY_M_S2 = 9.81


@dataclass(frozen=True)
class FeedbackComponents:
    """The separate feedback forces (N); robot-side ones in the world frame."""

    world_contact_f_n: np.ndarray  # (3,)
    world_weight_f_n: np.ndarray  # (3,)
    world_obstacle_f_n: np.ndarray  # (3,)
    device_workspace_f_n: np.ndarray  # (3,) device frame, rendered unscaled
    world_scene_f_n: np.ndarray  # (3,) table, bin, static geoms near the arm
    world_limits_f_n: np.ndarray  # (3,) joint limits, the arm's links near each other

    @property
    def world_robot_f_n(self) -> np.ndarray:
        """Sum of the robot-side components (world frame, N), before force scaling."""
        return (
            self.world_contact_f_n
            + self.world_weight_f_n
            + self.world_obstacle_f_n
            + self.world_scene_f_n
            + self.world_limits_f_n
        )


def weight_force(mass_kg: float) -> np.ndarray:
    """Weight (3,) in N of a held mass in the world frame: m g pointing down."""
    return np.array([0.0, 0.0, -mass_kg * STANDARD_GRAVITY_M_S2])


def contact_force(world_f_gripper_n: np.ndarray, world_f_weight_n: np.ndarray) -> np.ndarray:
    """Contact component (3,) in N: the measured force on the gripper minus the weight.

    A held object loads the fingers with its weight; that part is rendered by the weight
    component (steady, model-based), so it is removed here. What stays is what the
    environment does to the gripper, directly or through the held object (pressing it on
    the table). Without a held object (zero weight) it is the measured force itself.
    """
    return np.asarray(world_f_gripper_n, dtype=float) - world_f_weight_n


def obstacle_force(sample: ProximitySample | None, cfg: TeleopConfig) -> np.ndarray:
    """Fictitious repulsion (3,) in N: k (d0 - d) n within the influence distance d0.

    n points from the obstacle to the arm point (``sample.world_n_away``), so the force
    pushes the arm, and the operator's hand, out of the obstacle.
    """
    if sample is None or sample.distance_m >= cfg.obstacle_influence_m:
        return np.zeros(3)
    depth_m = cfg.obstacle_influence_m - sample.distance_m
    return cfg.obstacle_stiffness_n_per_m * depth_m * sample.world_n_away


def workspace_force(device_d_m: np.ndarray, cfg: TeleopConfig) -> np.ndarray:
    """Device-frame spring (3,) in N pulling the handle back inside radius workspace_free_m."""
    d = np.asarray(device_d_m, dtype=float)
    norm = math.hypot(*d.tolist())  # np.linalg.norm costs more than the sum at this size
    if norm <= cfg.workspace_free_m:
        return np.zeros(3)
    return -cfg.workspace_stiffness_n_per_m * (norm - cfg.workspace_free_m) * (d / norm)


def workspace_stiffness_n_per_m(device_d_m: np.ndarray, cfg: TeleopConfig) -> np.ndarray:
    """The workspace spring's stiffness about ``device_d_m`` (3, 3), N/m: the Jacobian of
    :func:`workspace_force`, -K ((1 - r / |d|) I + (r / |d|) u u^T) outside the free radius
    r (u = d / |d|), zero inside. The device renders the spring between two feedbacks
    from it (the local contact model of FORCE_FEEDBACK)."""
    d = np.asarray(device_d_m, dtype=float)
    norm = math.hypot(*d.tolist())
    if norm <= cfg.workspace_free_m:
        return np.zeros((3, 3))
    u = d / norm
    inside = cfg.workspace_free_m / norm
    return -cfg.workspace_stiffness_n_per_m * ((1.0 - inside) * np.eye(3) + inside * np.outer(u, u))


def feedback_components(
    world_f_gripper_n: np.ndarray,
    held_mass: float,
    obstacle: ProximitySample | None,
    device_d_m: np.ndarray,
    cfg: TeleopConfig,
    world_scene_f_n: np.ndarray | None = None,
    world_limits_f_n: np.ndarray | None = None,
) -> FeedbackComponents:
    """All the components from what the controller receives each cycle.

    ``world_f_gripper_n`` is the plant's total contact force on the gripper (N, world),
    ``held_mass`` the held object's mass (kg, 0 when nothing is held), ``device_d_m`` the
    handle offset from the device centre (m, device frame); ``world_scene_f_n`` and
    ``world_limits_f_n`` the control law's push-back of the scene and of the arm's own
    limits (N, world; None: zero).
    """
    weight = weight_force(held_mass)
    return FeedbackComponents(
        world_contact_f_n=contact_force(world_f_gripper_n, weight),
        world_weight_f_n=weight,
        world_obstacle_f_n=obstacle_force(obstacle, cfg),
        device_workspace_f_n=workspace_force(device_d_m, cfg),
        world_scene_f_n=np.zeros(3) if world_scene_f_n is None else world_scene_f_n,
        world_limits_f_n=np.zeros(3) if world_limits_f_n is None else world_limits_f_n,
    )


def device_force(
    components: FeedbackComponents,
    yaw_rad: float,
    teleop_cfg: TeleopConfig,
    haptic_cfg: HapticConfig,
) -> np.ndarray:
    """Force (3,) in N for the haptic device, device frame.

    The robot-side sum is rotated world -> view/device (Rz(yaw)^T, the inverse of the
    rate command's rotation, so a force pushing the tool forward pushes the handle
    forward), scaled by ``force_scale``, added to the workspace spring, and saturated in
    norm at the device's ``peak_force_n`` (direction kept). In floats: it runs once per
    plant state (1 kHz), and a numpy call on a 3-vector costs more than its arithmetic.
    """
    fx, fy, fz = components.world_robot_f_n.tolist()
    wx, wy, wz = components.device_workspace_f_n.tolist()
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    scale = teleop_cfg.force_scale
    total = (  # force_scale Rz(yaw)^T f + workspace spring
        scale * (c * fx + s * fy) + wx,
        scale * (c * fy - s * fx) + wy,
        scale * fz + wz,
    )
    norm = math.hypot(*total)
    if norm > haptic_cfg.peak_force_n:
        saturation = haptic_cfg.peak_force_n / norm
        total = tuple(component * saturation for component in total)
    return np.array(total)


@dataclass(frozen=True)
class StabilityMargin:
    """Rendered stiffness against Colgate's bound (N/m)."""

    k_max_n_per_m: float  # 2 b / T
    k_workspace_n_per_m: float  # spring on the handle
    k_obstacle_tool_n_per_m: float  # obstacle_stiffness * force_scale, per m of tool motion
    k_obstacle_handle_n_per_m: float  # the same seen at the handle through rate control
    k_scene_tool_n_per_m: float = 0.0  # scene_stiffness * force_scale, per m of tool motion

    @property
    def k_rendered_n_per_m(self) -> float:
        """Worst case: both springs on the same axis, the stiffest robot-side one."""
        return self.k_workspace_n_per_m + max(
            self.k_obstacle_tool_n_per_m, self.k_obstacle_handle_n_per_m, self.k_scene_tool_n_per_m
        )


def check_stability(
    teleop_cfg: TeleopConfig, haptic_cfg: HapticConfig, timestep_s: float
) -> StabilityMargin:
    """Raise ValueError unless the rendered stiffness is below K_max = 2 b / T.

    Colgate and Schenkel: a virtual spring K sampled with period T on a device with
    physical damping b is passive when b > K T / 2, i.e. K < K_max = 2 b / T
    (b = ``haptic.damping_n_s_per_m``, T = ``plant.timestep_s``; the defaults give
    2 * 3 / 0.001 = 6000 N/m). Rendered stiffnesses:

    - workspace spring: acts on the handle directly, ``workspace_stiffness_n_per_m``.
    - obstacle spring: ``obstacle_stiffness * force_scale`` N per m of TOOL motion. Rate
      control maps handle offset to tool velocity, and the avoidance pushes the tool out
      at ``obstacle_avoid_gain (d0 - d)``: with the handle held at offset x the tool settles
      where gain_rate x = avoid_gain depth, so the handle feels
      ``obstacle_stiffness * force_scale * rate_gain / avoid_gain`` N/m (45 N/m by default).
    - scene spring (table, bin, the arm's own links): ``scene_stiffness * force_scale`` N
      per m of tool motion (75 N/m by default); the approach cap stops the tool at the
      stop distance whatever the handle's offset, so it renders no more at the handle.

    The workspace spring and the stiffest robot-side one may act on the same axis, so
    their sum is checked against K_max.
    """
    if timestep_s <= 0:
        raise ValueError("plant.timestep_s must be > 0 for the stability bound")
    k_obstacle_tool = teleop_cfg.obstacle_stiffness_n_per_m * teleop_cfg.force_scale
    k_obstacle_handle = (
        k_obstacle_tool * teleop_cfg.rate_gain_per_s / teleop_cfg.obstacle_avoid_gain_per_s
        if teleop_cfg.obstacle_avoid_gain_per_s > 0
        else float("inf")
    )
    margin = StabilityMargin(
        k_max_n_per_m=2.0 * haptic_cfg.damping_n_s_per_m / timestep_s,
        k_workspace_n_per_m=teleop_cfg.workspace_stiffness_n_per_m,
        k_obstacle_tool_n_per_m=k_obstacle_tool,
        k_obstacle_handle_n_per_m=k_obstacle_handle,
        k_scene_tool_n_per_m=teleop_cfg.scene_stiffness_n_per_m * teleop_cfg.force_scale,
    )
    if not margin.k_rendered_n_per_m < margin.k_max_n_per_m:
        raise ValueError(
            f"haptic rendering unstable: rendered stiffness {margin.k_rendered_n_per_m:.1f} N/m "
            f"(workspace {margin.k_workspace_n_per_m:.1f} + max(obstacle {k_obstacle_tool:.1f}, "
            f"{k_obstacle_handle:.1f}, scene {margin.k_scene_tool_n_per_m:.1f})) must be below "
            f"Colgate's K_max = 2 b / T = 2 * {haptic_cfg.damping_n_s_per_m} / {timestep_s} = "
            f"{margin.k_max_n_per_m:.1f} N/m"
        )
    return margin
