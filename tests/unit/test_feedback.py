"""Force feedback: each component, the device mapping, saturation and the stability bound.

The contact and weight tests grasp the cube for real: the MuJoCo plant in process with
the teleoperation controller, driven by a simple proportional "operator" (no bus).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from teleop.control.feedback import (
    STANDARD_GRAVITY_M_S2,
    FeedbackComponents,
    check_stability,
    contact_force,
    device_force,
    feedback_components,
    obstacle_force,
    weight_force,
    workspace_force,
)
from teleop.control.kinematics import build_arm_model
from teleop.control.teleop import TeleopController
from teleop.core.config import Config, HapticConfig, TeleopConfig, load_config
from teleop.sim.contact import finger_bodies, held_mass_kg, held_object
from teleop.sim.plant import Plant
from teleop.sim.proximity import ProximitySample

# The tool site is this far (m) above the fingertips along the approach axis.
TOOL_TO_FINGERTIP_M = 0.02
# "Operator": tool velocity reference (m/s) per m of position error.
OPERATOR_GAIN_PER_S = 4.0
ZERO = np.zeros(3)


class GraspRig:
    """Plant + teleoperation controller + a proportional operator that moves the tool."""

    def __init__(self, cfg: Config) -> None:
        self.plant = Plant(cfg)
        self.plant.reset(np.array(cfg.robot.home_q_rad), gripper_open=1.0)
        self.ctl = TeleopController(build_arm_model(cfg.robot), cfg.teleop, cfg.control, cfg.tick_s)
        self.fingers = finger_bodies(self.plant.model, cfg.robot)
        self.cube = int(self.plant.object_bodies[0])
        self.cube_p = self.plant.object_poses()[0][0].copy()

    def move(self, target: np.ndarray, gripper_cmd: float, steps: int) -> None:
        for _ in range(steps):
            sample = self.plant.sample()
            v_ref = OPERATOR_GAIN_PER_S * (target - self.plant.tool_pose()[0])
            out = self.ctl.update(sample.q_rad, sample.qd_rad_s, v_ref, None, gripper_cmd)
            self.plant.step(out.qd_ref_rad_s, out.gripper_cmd)

    def held(self) -> int:
        return held_object(self.plant.model, self.plant.data, self.fingers, [self.cube])


@pytest.fixture(scope="module")
def cfg() -> Config:
    return load_config()


def test_closed_gripper_pressing_the_cube_is_pushed_up(cfg):
    # Pressed 1 cm into the cube the force passes the protective stop's limit: off here,
    # this is about the force's direction (tests/unit/test_protective.py has the stop).
    rig = GraspRig(replace(cfg, plant=replace(cfg.plant, contact_force_limit_n=1e9)))
    top = rig.cube_p + [0.0, 0.0, 0.025 + TOOL_TO_FINGERTIP_M]  # fingertips on the top face
    rig.move(top + [0.0, 0.0, 0.05], 0.0, 2500)
    force, contacts = rig.plant.gripper_contact_force()
    assert contacts == 0 and np.all(force == 0)
    rig.move(top - [0.0, 0.0, 0.01], 0.0, 800)  # 1 cm into the cube: pressing
    force, contacts = rig.plant.gripper_contact_force()
    assert contacts > 0
    assert force[2] > 1.0  # the cube pushes the gripper UP
    assert force[2] > 3 * np.linalg.norm(force[:2])
    assert rig.held() == -1  # pressing with the fingertips is not a grasp


def test_grasp_detection_and_weight_of_the_held_cube(cfg):
    rig = GraspRig(cfg)
    rig.move(rig.cube_p + [0.0, 0.0, 0.12], 1.0, 1500)  # above, open
    rig.move(rig.cube_p.copy(), 1.0, 1000)  # descend around it
    assert rig.held() == -1  # fingers open: not touching
    rig.move(rig.cube_p.copy(), 0.0, 500)  # close
    assert rig.held() == rig.cube
    rig.move(rig.cube_p + [0.0, 0.0, 0.15], 0.0, 1500)  # lift (at the tool speed limit), settle
    assert rig.held() == rig.cube
    assert rig.plant.object_poses()[0][0][2] > rig.cube_p[2] + 0.1  # it came along

    mass = held_mass_kg(rig.plant.model, rig.held(), cfg.teleop.object_mass_kg)
    assert mass == pytest.approx(0.2)  # the MJCF cube
    mg = mass * STANDARD_GRAVITY_M_S2
    measured, _ = rig.plant.gripper_contact_force()
    # The measured force on the gripper IS the cube's weight (within 10 %), pointing down...
    assert measured[2] == pytest.approx(-mg, rel=0.10)
    assert np.linalg.norm(measured[:2]) < 0.1 * mg
    # ...so the components split it: weight = m g down, contact ~ 0 (not counted twice).
    parts = feedback_components(measured, mass, None, ZERO, cfg.teleop)
    np.testing.assert_allclose(parts.world_weight_f_n, [0.0, 0.0, -mg])
    assert np.linalg.norm(parts.world_contact_f_n) < 0.1 * mg
    np.testing.assert_allclose(parts.world_robot_f_n, measured)

    rig.move(rig.cube_p + [0.0, 0.0, 0.15], 1.0, 300)  # release
    assert rig.held() == -1


def test_closing_on_an_off_centre_cube_does_not_slam_it(cfg):
    """The fingers close on a cube 4 mm off the middle between them: the first finger
    meets it and slides it over to the other. At a gripper's speed that is a push of a
    few newtons; fast enough to strike it, the cube wedged against the table puts tens of
    newtons on the gripper, more than the handle can render at force_scale (a run would
    saturate the device at every grasp)."""
    rig = GraspRig(cfg)
    data = rig.plant.data
    fingers = [int(b) for b in rig.fingers]
    rig.move(rig.cube_p + [0.0, 0.0, 0.12], 1.0, 1500)  # above, open
    across = data.xpos[fingers[0]] - data.xpos[fingers[1]]
    across[2] = 0.0
    across /= np.linalg.norm(across)
    rig.move(rig.cube_p + 0.004 * across, 1.0, 1500)  # around it, off the middle
    assert rig.plant.gripper_contact_force()[1] == 0  # open: not touching yet
    peak_n = 0.0
    for _ in range(600):  # close
        rig.move(rig.cube_p + 0.004 * across, 0.0, 1)
        peak_n = max(peak_n, float(np.linalg.norm(rig.plant.gripper_contact_force()[0])))
    assert rig.held() == rig.cube
    assert peak_n > 0.5  # the first finger did push the cube over
    # below what saturates the handle (measured: 7 N; 48 N without the fingers' damping)
    assert peak_n < cfg.haptic.peak_force_n / cfg.teleop.force_scale


def test_weight_and_contact_components():
    np.testing.assert_allclose(weight_force(0.5), [0.0, 0.0, -0.5 * STANDARD_GRAVITY_M_S2])
    np.testing.assert_allclose(weight_force(0.0), ZERO)
    pressed = np.array([0.1, 0.0, 4.0])
    np.testing.assert_allclose(contact_force(pressed, weight_force(0.0)), pressed)


def sample_at(distance_m: float, n=(0.0, 0.0, 1.0)) -> ProximitySample:
    n = np.asarray(n, dtype=float)
    return ProximitySample(distance_m, n * distance_m, ZERO, n, 3, 2)


def test_obstacle_force_is_a_spring_within_the_influence_distance():
    cfg = TeleopConfig()
    d0, k = cfg.obstacle_influence_m, cfg.obstacle_stiffness_n_per_m
    np.testing.assert_allclose(obstacle_force(sample_at(d0), cfg), ZERO)
    np.testing.assert_allclose(obstacle_force(sample_at(d0 + 0.01), cfg), ZERO)
    np.testing.assert_allclose(obstacle_force(None, cfg), ZERO)
    n = np.array([0.0, 0.6, 0.8])
    np.testing.assert_allclose(obstacle_force(sample_at(0.03, n), cfg), k * (d0 - 0.03) * n)
    # Penetration (negative distance) keeps pushing out, harder.
    assert obstacle_force(sample_at(-0.01), cfg)[2] == pytest.approx(k * (d0 + 0.01))


def test_workspace_spring_pulls_the_handle_back_beyond_the_free_radius():
    cfg = TeleopConfig()
    inside = np.array([cfg.workspace_free_m * 0.99, 0.0, 0.0])
    np.testing.assert_allclose(workspace_force(inside, cfg), ZERO)
    out = np.array([0.0, -(cfg.workspace_free_m + 0.005), 0.0])
    np.testing.assert_allclose(
        workspace_force(out, cfg), [0.0, cfg.workspace_stiffness_n_per_m * 0.005, 0.0]
    )


def components(world_f, device_ws=ZERO) -> FeedbackComponents:
    return FeedbackComponents(np.asarray(world_f, dtype=float), ZERO, ZERO, device_ws, ZERO, ZERO)


def test_device_force_rotates_into_the_view_and_scales():
    tcfg, hcfg = TeleopConfig(), HapticConfig()
    # The operator looks along world +y: a world +y force pushes the handle forward (+x).
    f = device_force(components([0.0, 2.0, 0.0]), math.pi / 2, tcfg, hcfg)
    np.testing.assert_allclose(f, [tcfg.force_scale * 2.0, 0.0, 0.0], atol=1e-12)
    # The workspace spring is added unscaled, already in the device frame.
    f = device_force(components(ZERO, np.array([0.0, 0.0, -1.5])), 0.3, tcfg, hcfg)
    np.testing.assert_allclose(f, [0.0, 0.0, -1.5])


def test_device_force_saturates_at_the_peak_force():
    tcfg, hcfg = TeleopConfig(), HapticConfig()
    world = np.array([30.0, -40.0, 0.0])
    f = device_force(components(world), 0.0, tcfg, hcfg)
    assert np.linalg.norm(f) == pytest.approx(hcfg.peak_force_n) == pytest.approx(8.0)
    np.testing.assert_allclose(f / np.linalg.norm(f), world / np.linalg.norm(world))


def test_device_force_matches_the_rotation_matrix_formula():
    """The float form against force_scale Rz(yaw)^T f + spring, saturated in norm."""
    tcfg, hcfg = TeleopConfig(), HapticConfig()
    rng = np.random.default_rng(10)
    for _ in range(200):
        world_f = rng.normal(size=3) * rng.uniform(0.0, 40.0)
        spring = rng.normal(size=3) * rng.uniform(0.0, 3.0)
        yaw = rng.uniform(-math.pi, math.pi)
        c, s = math.cos(yaw), math.sin(yaw)
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        expected = tcfg.force_scale * rz.T @ world_f + spring
        norm = np.linalg.norm(expected)
        if norm > hcfg.peak_force_n:
            expected *= hcfg.peak_force_n / norm
        f = device_force(components(world_f, spring), yaw, tcfg, hcfg)
        np.testing.assert_allclose(f, expected, rtol=0, atol=1e-13)


def test_stability_defaults_pass_and_stiff_springs_are_rejected():
    cfg = load_config()
    margin = check_stability(cfg.teleop, cfg.haptic, cfg.plant.timestep_s)
    assert margin.k_max_n_per_m == pytest.approx(2 * 3.0 / 0.001)
    # The workspace spring and the stiffest robot-side one: the scene's 150 N/m x 0.5
    # (the obstacle's: 60 x 0.5 per m of tool motion, 45 N/m at the handle).
    assert margin.k_rendered_n_per_m == pytest.approx(300.0 + 75.0)
    stiff = TeleopConfig(workspace_stiffness_n_per_m=7000.0)
    with pytest.raises(ValueError, match=r"K_max = 2 b / T"):
        check_stability(stiff, cfg.haptic, cfg.plant.timestep_s)
    weakly_damped = HapticConfig(damping_n_s_per_m=0.1)  # K_max = 200 N/m
    with pytest.raises(ValueError, match="unstable"):
        check_stability(cfg.teleop, weakly_damped, cfg.plant.timestep_s)
