"""Rate control's mapping: the handle's offset as a tool-velocity command.

The handle offset ``d_m`` (device frame, m) commands a tool velocity: a radial deadband,
a gain and a speed cap give the rate in the device/view frame (:func:`device_rate`,
what the device side and the wave transform need); rotated by the HMD yaw it is the
world tool-velocity reference the controller tracks (:func:`rate_to_world`). Pure
floats and numpy: the haptic device imports it without the robot model.
"""

from __future__ import annotations

import math

import numpy as np

from teleop.core.config import TeleopConfig


def view_to_world(yaw_rad: float) -> np.ndarray:
    """Rz(yaw) (3, 3): maps view/device-frame vectors to the world frame."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def device_rate(d_m: np.ndarray, cfg: TeleopConfig) -> tuple[float, float, float]:
    """The handle's rate command (m/s, device/view frame) from its offset ``d_m`` (3,) in m.

    Radial deadband, continuous at its edge: v = gain (|d| - deadband) d/|d| beyond it,
    zero inside (the hand's tremor and the handle's rest offset command nothing), capped
    in norm at ``max_tool_speed_m_s``. In floats: it runs once per haptic sample (1 kHz),
    and the numpy form (norm, product) costs several times more.
    """
    dx, dy, dz = np.asarray(d_m, dtype=float).tolist()
    norm = math.hypot(dx, dy, dz)
    if norm <= cfg.deadband_m:
        return 0.0, 0.0, 0.0
    speed = min(cfg.rate_gain_per_s * (norm - cfg.deadband_m), cfg.max_tool_speed_m_s)
    gain = speed / norm
    return dx * gain, dy * gain, dz * gain


def rate_to_world(vx: float, vy: float, vz: float, yaw_rad: float, cfg: TeleopConfig) -> np.ndarray:
    """A device/view-frame rate (m/s) as the world tool-velocity reference (3,): capped in
    norm at ``max_tool_speed_m_s`` and rotated by Rz(yaw)."""
    speed = math.hypot(vx, vy, vz)
    if speed > cfg.max_tool_speed_m_s:
        cap = cfg.max_tool_speed_m_s / speed
        vx, vy, vz = vx * cap, vy * cap, vz * cap
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array((c * vx - s * vy, s * vx + c * vy, vz))  # Rz(yaw) v


def rate_command(d_m: np.ndarray, yaw_rad: float, cfg: TeleopConfig) -> np.ndarray:
    """World tool-velocity reference (3,) in m/s from the handle offset ``d_m`` (3,) in m:
    :func:`device_rate` rotated to the world (:func:`rate_to_world`)."""
    return rate_to_world(*device_rate(d_m, cfg), yaw_rad, cfg)


def teleop_reference(
    d_m: np.ndarray, yaw_rad: float, clutch: bool, cfg: TeleopConfig
) -> np.ndarray:
    """:func:`rate_command`, or zero while the clutch is held (the operator re-centres)."""
    return np.zeros(3) if clutch else rate_command(d_m, yaw_rad, cfg)
