"""One model file for both: Pinocchio's kinematics and dynamics agree with MuJoCo's."""

from __future__ import annotations

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from teleop.control.kinematics import (
    ModelError,
    build_arm_model,
    joint_space_dynamics,
    manipulability,
    manipulability_and_gradient,
    tool_jacobian,
    tool_pose_and_jacobian,
    tool_position_and_jacobian,
)
from teleop.control.path import compensation_terms, velocity_reference
from teleop.sim.plant import Plant

N_CONFIGURATIONS = 50
TOLERANCE = 1e-9


def random_configurations(plant: Plant, count: int, seed: int) -> np.ndarray:
    """Uniform samples inside each arm joint's range (a wide box for unlimited joints)."""
    rng = np.random.default_rng(seed)
    joint_ids = plant.model.dof_jntid[plant.dof_index]
    low = np.where(plant.model.jnt_limited[joint_ids], plant.model.jnt_range[joint_ids, 0], -np.pi)
    high = np.where(plant.model.jnt_limited[joint_ids], plant.model.jnt_range[joint_ids, 1], np.pi)
    return rng.uniform(low, high, size=(count, len(low)))


def test_tool_position_and_jacobian_match_mujoco(any_arm_config):
    plant = Plant(any_arm_config)
    arm = build_arm_model(any_arm_config.robot)
    for q in random_configurations(plant, N_CONFIGURATIONS, seed=1):
        plant.set_arm_configuration(q)
        position, jacobian = tool_position_and_jacobian(arm, q)
        np.testing.assert_allclose(position, plant.tool_pose()[0], atol=TOLERANCE, rtol=0)
        np.testing.assert_allclose(jacobian[:3], plant.tool_jacobian(), atol=TOLERANCE, rtol=0)


def test_tool_pose_and_jacobian_variants_agree(any_arm_config):
    """The teleoperation cycle's cheaper queries give the same pose and Jacobian."""
    plant = Plant(any_arm_config)
    arm = build_arm_model(any_arm_config.robot)
    for q in random_configurations(plant, 10, seed=3):
        position, jacobian = tool_position_and_jacobian(arm, q)
        rotation = arm.data.oMf[arm.tool_frame_id].rotation.copy()
        jacobian = jacobian.copy()
        fast_position, fast_rotation, fast_jacobian = tool_pose_and_jacobian(arm, q)
        np.testing.assert_array_equal(fast_position, position)
        np.testing.assert_array_equal(fast_rotation, rotation)
        np.testing.assert_array_equal(fast_jacobian, jacobian)
        np.testing.assert_array_equal(tool_jacobian(arm, q), jacobian)


def test_dynamics_match_mujoco(any_arm_config):
    """M0 (with armature) and g0 from Pinocchio equal MuJoCo's, fingers closed."""
    plant = Plant(any_arm_config)
    arm = build_arm_model(any_arm_config.robot)
    model, data = plant.model, plant.data
    dofs = plant.dof_index
    for q in random_configurations(plant, 10, seed=2):
        mujoco.mj_resetData(model, data)
        data.qpos[plant.qpos_index] = q
        mujoco.mj_forward(model, data)
        full_mass = np.zeros((model.nv, model.nv))
        mujoco.mj_fullM(model, data, full_mass)
        mass, coriolis, gravity = joint_space_dynamics(arm, q, np.zeros_like(q))
        np.testing.assert_allclose(mass, full_mass[np.ix_(dofs, dofs)], atol=1e-9, rtol=1e-9)
        np.testing.assert_allclose(gravity, data.qfrc_bias[dofs], atol=1e-9, rtol=1e-9)
        np.testing.assert_allclose(coriolis, 0.0, atol=1e-12)
        qd = np.linspace(-1.0, 1.0, len(q))
        qdd = np.linspace(0.5, -0.5, len(q))
        mass, coriolis, gravity = joint_space_dynamics(arm, q, qd)
        np.testing.assert_allclose(  # against one recursive Newton-Euler pass
            pin.rnea(arm.model, arm.data, q, qd, qdd), mass @ qdd + coriolis + gravity, atol=1e-9
        )


def test_prepared_compensation_equals_one_newton_euler_pass(any_arm_config):
    """velocity_reference on the prepared terms (M0 and the bias, ahead of q'_c) gives
    the paper's q'_ref = q' + H^-1 (tau(q, q', q''_ref) + D q'), tau from pin.rnea, with
    q''_ref = (q'_c - previous q'_c) / T + Kd (q'_c - q')."""
    config = any_arm_config
    plant = Plant(config)
    arm = build_arm_model(config.robot)
    servo, control, period_s = arm.servo, config.control, config.plant.timestep_s
    rng = np.random.default_rng(5)
    for q in random_configurations(plant, 10, seed=4):
        qd, qd_c, previous = rng.uniform(-1.0, 1.0, size=(3, len(q)))
        terms = compensation_terms(arm, q, qd)
        got = velocity_reference(control, terms, qd_c.tolist(), previous.tolist(), period_s)
        qdd_ref = (qd_c - previous) / period_s + control.velocity_gain_per_s * (qd_c - qd)
        tau = pin.rnea(arm.model, arm.data, q, qd, qdd_ref)
        expected = qd + (tau + servo.damping_nms_per_rad * qd) / servo.kv_nms_per_rad
        np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-9)
        first = velocity_reference(control, terms, qd_c.tolist(), None, period_s)  # from q'
        qdd_first = (qd_c - qd) / period_s + control.velocity_gain_per_s * (qd_c - qd)
        tau = pin.rnea(arm.model, arm.data, q, qd, qdd_first)
        expected = qd + (tau + servo.damping_nms_per_rad * qd) / servo.kv_nms_per_rad
        np.testing.assert_allclose(first, expected, rtol=1e-9, atol=1e-9)
    assert velocity_reference(control, None, [0.5, -0.5], None, period_s) == [0.5, -0.5]


def test_manipulability_gradient_matches_finite_differences(any_arm_config):
    arm = build_arm_model(any_arm_config.robot)
    step = 1e-6
    rng = np.random.default_rng(3)
    for q in rng.uniform(-2.0, 2.0, size=(10, arm.n_joints)):
        _, jacobian = tool_position_and_jacobian(arm, q)
        w, analytic = manipulability_and_gradient(jacobian)
        assert w == pytest.approx(manipulability(jacobian[:3]), rel=1e-12)
        numeric = np.empty(arm.n_joints)
        for k in range(arm.n_joints):
            dq = np.zeros(arm.n_joints)
            dq[k] = step
            w_plus = manipulability(tool_position_and_jacobian(arm, q + dq)[1][:3])
            w_minus = manipulability(tool_position_and_jacobian(arm, q - dq)[1][:3])
            numeric[k] = (w_plus - w_minus) / (2 * step)
        np.testing.assert_allclose(analytic, numeric, atol=1e-7)


def test_servo_parameters_come_from_the_mjcf(config):
    arm = build_arm_model(config.robot)
    plant = Plant(config)
    np.testing.assert_array_equal(arm.servo.kv_nms_per_rad, plant.kv)
    assert np.all(arm.servo.max_speed_rad_s == pytest.approx(np.pi, abs=1e-4))


def test_unknown_names_fail_clearly(config):
    from dataclasses import replace

    with pytest.raises(ModelError, match="no joint"):
        names = tuple(f"missing_{i}" for i in range(6))
        build_arm_model(replace(config.robot, arm_joints=names, arm_actuators=names))
    with pytest.raises(ModelError, match="tool"):
        build_arm_model(replace(config.robot, tool_site="nope"))


def test_prepared_steps_equal_mujoco_steps_bit_for_bit(config):
    """Plant.prepare_step (mj_step1 ahead of the command) changes no bit of the motion:
    a tick of the plant is its physics steps, each one mj_step with the command held."""
    from dataclasses import replace

    # No tool-speed cut or approach limit (Plant.limit) and no protective stop, so the
    # plants step the same references. The approach range's collision gap stays (0.1 m:
    # an approach time that allows any speed): a third plant without it steps the same
    # bits, the contacts the gap adds are out of the physics.
    no_limits = dict(
        tool_speed_limit_m_s=1e9, approach_time_s=1e-10, approach_touch_m_s=1e9,
        tool_speed_stop_m_s=2e9, contact_force_limit_n=1e9,
    )  # fmt: skip
    config = replace(config, plant=replace(config.plant, **no_limits))
    prepared, plain = Plant(config), Plant(config)
    no_gap = Plant(replace(config, plant=replace(config.plant, approach_time_s=0.0)))
    assert prepared.model.geom_gap.max() > 0 and no_gap.model.geom_gap.max() == 0
    q0 = random_configurations(prepared, 1, seed=5)[0]
    for plant in (prepared, plain, no_gap):
        plant.reset(q0)
    rng = np.random.default_rng(6)
    for k in range(600):
        qd_ref = rng.normal(0.0, 0.5, prepared.n_joints)
        gripper = float(k // 200 % 2)
        prepared.prepare_step()
        prepared.prepare_step()  # twice: still one mj_step1
        prepared.step(qd_ref, gripper)
        for plant in (plain, no_gap):
            plant.data.ctrl[plant.actuator_index] = qd_ref
            plant.data.ctrl[plant.gripper_actuator] = plant._gripper_ctrl(gripper)
            for _ in range(config.physics_steps_per_tick):
                mujoco.mj_step(plant.model, plant.data)
        assert np.array_equal(no_gap.data.qpos, plain.data.qpos), k
        assert np.array_equal(no_gap.data.qvel, plain.data.qvel), k
        assert np.array_equal(prepared.data.qpos, plain.data.qpos), k
        assert np.array_equal(prepared.data.qvel, plain.data.qvel), k
    assert prepared.step_count == 600
    assert prepared.physics_steps == 600 * config.physics_steps_per_tick


def test_the_tool_speed_limit_cuts_the_motion_not_what_holds_the_arm(config):
    """At full reach (a sweep task's cube 0.79 m out, tool down, lifting) the references
    of a velocity servo carry bias / kv that only holds the arm's weight: worth a
    0.17 m/s tool speed there. A command lifting the tool at 0.8 of the limit passes
    unchanged; one asking for twice that is cut to the limit, straight up still (cutting
    the holding part too let the arm sag)."""
    plant = Plant(config)
    cap_m_s = config.plant.tool_speed_limit_m_s
    plant.reset(np.array([-0.49, 0.77, 0.99, -0.22, -1.57, -2.03]), gripper_open=0.0)
    plant.prepare_step()
    hold = plant.data.qfrc_bias[plant.dof_index] / plant.kv
    jacobian = plant.tool_jacobian()
    up = np.linalg.pinv(jacobian) @ np.array([0.0, 0.0, 0.8 * cap_m_s])
    lift = hold + up
    assert np.linalg.norm(jacobian @ lift) > cap_m_s  # the references alone look too fast
    assert np.array_equal(plant.limit(lift), lift)
    assert plant.clamped_steps == 0
    fast = plant.limit(hold + 2.0 * up)
    assert plant.clamped_steps == 1
    np.testing.assert_allclose(jacobian @ (fast - hold), [0.0, 0.0, cap_m_s], atol=1e-9)
