"""Contacts on the gripper: which bodies are the fingers, what they pinch, its mass.

The plant owns the contacts (MuJoCo's ``data.contact`` after a step), so grasp
detection runs there and the held body travels in PLANT_STATE; the controller only
reads the result. A grasp is contact-based: the object is held when every finger
presses on it and two of them push from opposite sides (a pinch), which needs no
threshold on the gripper command.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import mujoco
import numpy as np

from teleop.core.config import ModelError, RobotConfig

# A finger touches the object when its contact pushes with at least this normal force (N):
# grazing contacts at the edge of the solver's tolerance are not a grasp.
GRASP_MIN_NORMAL_FORCE_N = 0.2
# Two fingers pinch when they push the object from directions at least this far apart
# (deg); 180 is a perfect antipodal grasp, 0 is two fingertips pressing the same face.
GRASP_MIN_OPPOSITION_DEG = 120.0
_GRASP_MAX_PUSH_COS = math.cos(math.radians(GRASP_MIN_OPPOSITION_DEG))


def finger_bodies(model: mujoco.MjModel, robot: RobotConfig) -> tuple[int, ...]:
    """MuJoCo body ids of the fingers: the bodies that ``robot.gripper_joints`` move."""
    bodies = []
    for name in robot.gripper_joints:
        joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if joint < 0:
            raise ModelError(f"no gripper joint {name!r} in the model")
        bodies.append(int(model.jnt_bodyid[joint]))
    return tuple(bodies)


def held_object(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    fingers: tuple[int, ...],
    objects: Iterable[int],
    min_normal_force_n: float = GRASP_MIN_NORMAL_FORCE_N,
) -> int:
    """Body id of the object pinched by the fingers, or -1 when nothing is held.

    Pinched: every finger presses on the object (normal force of ``mj_contactForce``
    >= ``min_normal_force_n``) and two fingers push from opposite sides (their resultant
    push directions are more than GRASP_MIN_OPPOSITION_DEG apart). The opposition test
    rejects a closed gripper pressing its fingertips on the object's top face. Reads
    ``data.contact`` as left by the last ``mj_step``/``mj_forward``.
    """
    candidates = set(objects)
    # (object, finger) -> resultant normal force (N, world) the finger applies to the object.
    pushes: dict[tuple[int, int], np.ndarray] = {}
    wrench = np.zeros(6)
    body_of = model.geom_bodyid
    for i in range(data.ncon):
        contact = data.contact[i]
        b1, b2 = int(body_of[contact.geom1]), int(body_of[contact.geom2])
        if b1 in fingers and b2 in candidates:
            finger, obj, sign = b1, b2, 1.0  # the frame's normal points from geom1 to geom2
        elif b2 in fingers and b1 in candidates:
            finger, obj, sign = b2, b1, -1.0
        else:
            continue
        mujoco.mj_contactForce(model, data, i, wrench)
        if wrench[0] < min_normal_force_n:
            continue
        push = sign * wrench[0] * contact.frame[:3]
        key = (obj, finger)
        pushes[key] = pushes[key] + push if key in pushes else push
    for obj in candidates:
        if not all((obj, finger) in pushes for finger in fingers):
            continue
        directions = [pushes[obj, f] / np.linalg.norm(pushes[obj, f]) for f in fingers]
        if any(
            float(a @ b) < _GRASP_MAX_PUSH_COS
            for k, a in enumerate(directions)
            for b in directions[k + 1 :]
        ):
            return obj
    return -1


def held_mass_kg(model: mujoco.MjModel, body: int, fallback_kg: float) -> float:
    """Mass (kg) of a held body and everything attached to it; ``fallback_kg`` if unknown."""
    if body < 0:
        return 0.0
    mass = float(model.body_subtreemass[body])
    return mass if mass > 0 else fallback_kg
