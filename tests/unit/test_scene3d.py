"""The 3D scene drawn from the MuJoCo model: every visual geom, poses from mj_kinematics,
for both arms (same code for scene_arm6.xml and scene_arm7.xml)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import rerun as rr

from teleop.sim.plant import Plant
from teleop.viz import entities as ent
from teleop.viz import scene3d


def column(archetype: rr.AsComponents, name: str) -> np.ndarray:
    """One component of an archetype as an array, e.g. ``Capsules3D:lengths``."""
    for batch in archetype.as_component_batches():
        if batch.component_descriptor().component == name:
            return np.asarray(batch.as_arrow_array().to_pylist(), dtype=float)
    raise KeyError(name)


def test_every_visual_geom_is_drawn_once(any_arm_config):
    scene = scene3d.SceneModel(any_arm_config, ent.ENTITY_OBJECTS)
    model = scene.model
    visible = [
        g
        for g in range(model.ngeom)
        if model.geom_group[g] < scene3d.VISIBLE_GEOM_GROUPS and model.geom_rgba[g, 3] > 0
    ]
    entities = dict(scene.static_entities())
    assert sorted(g.geom for g in scene.geoms) == visible
    assert all(g.entity in entities for g in scene.geoms)
    # The arm's geoms move with its bodies; objects with their OBJECT_POSES entity.
    for name in any_arm_config.robot.object_bodies:
        assert any(e.startswith(ent.object_entity(name) + "/") for e in entities)
    assert len(scene.moving_bodies) > len(any_arm_config.robot.arm_joints)
    obstacle = next(g for g in scene.geoms if scene.is_obstacle(g.geom))
    colors = column(entities[obstacle.entity], "Ellipsoids3D:colors")
    assert (int(colors[0]) & 0xFF) <= scene3d.OBSTACLE_ALPHA  # translucent (RGBA, A low byte)


def test_body_frames_are_mujocos_own(any_arm_config):
    scene = scene3d.SceneModel(any_arm_config, ent.ENTITY_OBJECTS)
    rng = np.random.default_rng(0)
    home = np.asarray(any_arm_config.robot.home_q_rad)
    q = home + rng.normal(0.0, 0.3, (4, home.size))
    opening = np.array([0.0, 0.01, 0.02, 0.03])
    p_m, q_xyzw = scene.frames(q, opening)
    plant = Plant(any_arm_config)
    for i in range(len(q)):
        plant.data.qpos[plant.finger_qpos_index] = opening[i]
        plant.set_arm_configuration(q[i])
        bodies = list(scene.moving_bodies)
        np.testing.assert_allclose(p_m[i], plant.data.xpos[bodies], atol=1e-12)
        np.testing.assert_allclose(q_xyzw[i], plant.data.xquat[bodies][:, [1, 2, 3, 0]])


def test_ghost_capsules_span_mujocos_capsules(any_arm_config):
    scene = scene3d.SceneModel(any_arm_config, ent.ENTITY_OBJECTS)
    q = np.asarray(any_arm_config.robot.home_q_rad) + 0.2
    parts = dict(scene.ghost(q, 0.02, scene3d.ghost_rgba(0.5)))
    model, data = scene.model, scene.data  # posed by ghost()
    capsules = [
        g.geom for g in scene.arm_geoms if model.geom_type[g.geom] == mujoco.mjtGeom.mjGEOM_CAPSULE
    ]
    assert capsules
    for geom in capsules:
        shape = parts[scene3d.geom_name(model, geom)]
        start = column(shape, "Capsules3D:translations")[0]
        length = column(shape, "Capsules3D:lengths")[0]
        axis = data.geom_xmat[geom].reshape(3, 3)[:, 2]
        half = model.geom_size[geom, 1]
        np.testing.assert_allclose(start, data.geom_xpos[geom] - axis * half, atol=1e-6)
        assert length == pytest.approx(2 * half)
    skeleton = column(parts[scene3d.GHOST_SKELETON], "LineStrips3D:strips")
    np.testing.assert_allclose(
        skeleton.reshape(-1, 3)[-1], data.site_xpos[scene.plant.tool_site], atol=1e-6
    )


def test_quaternion_of_a_rotation_matrix():
    angle = 0.7
    mat = np.array(
        [[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0, 0, 1]]
    )
    expected_wxyz = np.zeros(4)
    mujoco.mju_axisAngle2Quat(expected_wxyz, np.array([0.0, 0.0, 1.0]), angle)
    np.testing.assert_allclose(scene3d.mat_to_xyzw(mat)[0], expected_wxyz[[1, 2, 3, 0]])
