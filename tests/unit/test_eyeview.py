"""The operator's eye view renderer: it mirrors the plant and looks where the head does;
which stacks run the eye view service, and the fixed viewpoint's limits."""

from __future__ import annotations

import math

import numpy as np
import pytest

from teleop.core.config import load_config
from teleop.run.stack import EYEVIEW, scenario_services
from teleop.viz.eyeview import EyeRenderer, camera_forward

# Mean absolute pixel difference (0-255) above which two renders show different scenes;
# identical inputs give exactly 0.
CHANGED_MEAN_ABS_DIFF = 1.0


@pytest.fixture(scope="module")
def renderer():
    eye = EyeRenderer(load_config())
    yield eye
    eye.close()


def _view(eye: EyeRenderer, config_yaw: float = 0.0) -> np.ndarray:
    cfg = load_config().eyeview
    return eye.render(np.array(cfg.fixed_p_m), config_yaw, cfg.fixed_pitch_rad).copy()


def _diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(np.int16) - b.astype(np.int16)).mean())


@pytest.mark.parametrize(("yaw_rad", "pitch_rad"), [(0.0, 0.5), (0.7, -0.2), (-2.5, 0.1)])
def test_the_camera_sits_at_the_head_and_looks_along_yaw_and_pitch(renderer, yaw_rad, pitch_rad):
    p_m = np.array([-0.4, 0.1, 0.6])
    renderer.render(p_m, yaw_rad, pitch_rad)
    np.testing.assert_allclose(renderer.eye_position_m(), p_m, atol=1e-6)
    forward = np.array(renderer.renderer.scene.camera[0].forward)
    np.testing.assert_allclose(forward, camera_forward(yaw_rad, pitch_rad), atol=1e-6)
    assert camera_forward(0.0, 0.3)[2] < 0  # positive pitch looks down


def test_the_mirror_follows_joints_gripper_and_objects(renderer):
    config = load_config()
    home = np.array(config.robot.home_q_rad)
    cube_p = np.array([[0.45, -0.25, 0.025], [0.35, 0.35, 0.0]])
    cube_q = np.array([[1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
    renderer.set_state(home, 0.02, cube_p, cube_q)
    base = _view(renderer)
    assert base.shape == (config.eyeview.height_px, config.eyeview.width_px, 3)
    assert _diff(base, _view(renderer)) == 0.0  # same inputs, same picture
    turned = home.copy()
    turned[0] += 0.8
    renderer.set_state(turned, 0.02, cube_p, cube_q)
    assert _diff(base, _view(renderer)) > CHANGED_MEAN_ABS_DIFF
    moved = cube_p.copy()
    moved[0] = [0.2, 0.1, 0.3]  # the cube lifted into view
    renderer.set_state(home, 0.02, moved, cube_q)
    cube_moved = _view(renderer)
    assert _diff(base, cube_moved) > 0.0
    renderer.set_state(home, 0.02, cube_p, cube_q)
    assert _diff(base, _view(renderer)) == 0.0


def test_the_stack_runs_the_eye_view_only_when_enabled():
    grasp = load_config(None, ['run.scenario="grasp"'])
    assert EYEVIEW in scenario_services(grasp)
    assert EYEVIEW in scenario_services(load_config())
    assert EYEVIEW not in scenario_services(load_config(None, ["eyeview.enabled=false"]))
    lockstep = 'run.mode="lockstep"'
    assert EYEVIEW not in scenario_services(load_config(None, [lockstep]))
    assert EYEVIEW in scenario_services(load_config(None, [lockstep, "eyeview.in_lockstep=true"]))


def test_fixed_viewpoint_pitch_is_refused_beyond_straight_down():
    with pytest.raises(ValueError, match="fixed_pitch_rad"):
        load_config(None, [f"eyeview.fixed_pitch_rad={math.pi / 2}"])
