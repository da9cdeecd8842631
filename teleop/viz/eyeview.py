"""The operator's eye view renderer: the plant's scene, drawn from a head pose.

:class:`EyeRenderer` is pure (no bus): a MuJoCo model of its own, posed from what the
plant publishes (arm joints, gripper opening, object poses), rendered offscreen
(``MUJOCO_GL=egl``) from a head pose: position (world frame, m), yaw about world z
(0 = looking along +x) and pitch (+ = nose down), the HMD's convention
(:mod:`teleop.devices.hmd`). ``services/eyeview.py`` drives it and publishes the frames.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from teleop.bus.messages import RGB_CHANNELS
from teleop.core.config import Config
from teleop.sim.plant import Plant

# The free camera orbits a point this far ahead of the eye (m); with the camera placed
# at lookat - distance * forward, the eye sits exactly at the head position.
LOOKAT_DISTANCE_M = 1.0


def camera_forward(yaw_rad: float, pitch_rad: float) -> np.ndarray:
    """Unit view direction (world frame) of a head with this yaw and pitch (+ = nose down)."""
    cos_pitch = math.cos(pitch_rad)
    return np.array(
        [cos_pitch * math.cos(yaw_rad), cos_pitch * math.sin(yaw_rad), -math.sin(pitch_rad)]
    )


class EyeRenderer:
    """A mirror of the plant's scene that renders RGB images from a head pose.

    The model is built by :class:`teleop.sim.plant.Plant` from the same config (scene file,
    scene overrides, joint and body names), so the picture is the plant's scene; only
    kinematics run (``mj_kinematics``), never dynamics. Must be used from the thread that
    built it (the GL context is current there).
    """

    def __init__(self, config: Config) -> None:
        eye = config.eyeview
        self.width_px = eye.width_px
        self.height_px = eye.height_px
        self.shadows = eye.shadows
        self.plant = Plant(config)
        model = self.plant.model
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, eye.width_px)
        model.vis.global_.offheight = max(model.vis.global_.offheight, eye.height_px)
        model.vis.global_.fovy = math.degrees(eye.fov_y_rad)
        self.plant.reset(np.asarray(config.robot.home_q_rad, dtype=np.float64))
        # qpos address of each object body's free joint (-1: a fixed body, posed by the model).
        self._object_qpos = []
        for body in self.plant.object_bodies:
            joint = model.body_jntadr[body]
            free = joint >= 0 and model.jnt_type[joint] == mujoco.mjtJoint.mjJNT_FREE
            self._object_qpos.append(int(model.jnt_qposadr[joint]) if free else -1)
        self.renderer = mujoco.Renderer(model, eye.height_px, eye.width_px)
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.distance = LOOKAT_DISTANCE_M
        self._pixels = np.empty((eye.height_px, eye.width_px, RGB_CHANNELS), dtype=np.uint8)

    @property
    def n_joints(self) -> int:
        return self.plant.n_joints

    def set_state(
        self,
        q_rad: np.ndarray,
        gripper_opening_m: float,
        world_p_objects_m: np.ndarray | None = None,
        world_q_objects_wxyz: np.ndarray | None = None,
    ) -> None:
        """Pose the mirror: arm joints (n,), finger opening (m), object poses (k, 3), (k, 4).

        Objects beyond the configured ones are ignored; a body without a free joint keeps
        its model pose.
        """
        data = self.plant.data
        data.qpos[self.plant.qpos_index] = q_rad
        data.qpos[self.plant.finger_qpos_index] = gripper_opening_m
        if world_p_objects_m is not None and world_q_objects_wxyz is not None:
            for adr, p, q in zip(
                self._object_qpos, world_p_objects_m, world_q_objects_wxyz, strict=False
            ):
                if adr >= 0:
                    data.qpos[adr : adr + 3] = p
                    data.qpos[adr + 3 : adr + 7] = q
        mujoco.mj_kinematics(self.plant.model, data)

    def render(self, world_p_eye_m: np.ndarray, yaw_rad: float, pitch_rad: float) -> np.ndarray:
        """The view from the eye at ``world_p_eye_m`` (m), (H, W, 3) uint8, top row first.

        The returned array is reused by the next call: copy it to keep it.
        """
        camera = self.camera
        camera.lookat[:] = np.asarray(world_p_eye_m) + LOOKAT_DISTANCE_M * camera_forward(
            yaw_rad, pitch_rad
        )
        camera.azimuth = math.degrees(yaw_rad)
        camera.elevation = -math.degrees(pitch_rad)
        self.renderer.update_scene(self.plant.data, camera)
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self.shadows
        return self.renderer.render(out=self._pixels)

    def eye_position_m(self) -> np.ndarray:
        """Where the last rendered scene put the eye (world frame, m): MuJoCo's own view."""
        cameras = self.renderer.scene.camera
        return 0.5 * (np.array(cameras[0].pos) + np.array(cameras[1].pos))

    def close(self) -> None:
        self.renderer.close()
