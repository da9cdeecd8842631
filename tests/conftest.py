"""Shared fixtures: the default config and the second (7-DOF) arm's overrides."""

from __future__ import annotations

import os

import pytest

from teleop.core.config import Config, load_config

# No telemetry from Rerun, no window from MuJoCo, in every test process and its children.
os.environ.setdefault("RERUN_ANALYTICS", "0")
os.environ.setdefault("MUJOCO_GL", "egl")

ARM7_OVERRIDES = (
    'robot.scene_file="scene_arm7.xml"',
    'robot.arm_joints=["j1","j2","j3","j4","j5","j6","j7"]',
    'robot.arm_actuators=["a1","a2","a3","a4","a5","a6","a7"]',
    'robot.tool_site="ee"',
    'robot.gripper_actuator="hand"',
    'robot.gripper_joints=["fl","fr"]',
    "robot.home_q_rad=[0.0,-0.25,0.0,1.75,0.05,-1.5708,-1.5708]",
)


@pytest.fixture
def config() -> Config:
    return load_config()


@pytest.fixture(params=["arm6", "arm7"])
def any_arm_config(request) -> Config:
    return load_config(None, ARM7_OVERRIDES if request.param == "arm7" else ())
