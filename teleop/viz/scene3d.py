"""The 3D scene for Rerun, drawn from the MuJoCo model itself (no second description).

The recorder holds its own :class:`~teleop.sim.plant.Plant` (the same scene file and scene
overrides as the plant service), turns every visual geom into a Rerun primitive once,
and moves the bodies by transforms computed with ``mj_kinematics`` from the received
joint state. Works for any scene the plant accepts (``scene_arm6.xml``, ``scene_arm7.xml``).

Bodies fall in three groups:

- objects (``robot.object_bodies`` and their subtrees): their geoms sit under
  ``world/objects/<body>``, which OBJECT_POSES already moves;
- moving bodies (a joint on the way to the world body): ``world/scene/<body>`` gets a
  world-frame Transform3D per scene frame;
- fixed bodies (the world body's own geoms, welded bodies): ``world/scene/<body>`` gets
  one static transform.

Each geom is an entity ``.../<geom name>`` holding one primitive, its local pose baked
into the primitive's centre and rotation (Rerun quaternions are x, y, z, w).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
import rerun as rr

from teleop.core.config import Config
from teleop.sim.plant import Plant

ENTITY_SCENE = "world/scene"  # + /<body>/<geom>
ENTITY_GHOSTS = "world/ghosts"  # + /<index>/<primitive kind>, stroboscopic arm poses
GHOST_SKELETON = "skeleton"  # child of a ghost: LineStrips3D through the arm's body origins

# MuJoCo shows geom groups 0, 1 and 2 by default; higher groups are hidden helpers.
VISIBLE_GEOM_GROUPS = 3
# A plane of size 0 is infinite in MuJoCo: draw this half extent instead (m).
INFINITE_PLANE_HALF_SIZE_M = 2.0
# Planes are drawn as thin boxes this thick (m), their top face on the plane.
PLANE_THICKNESS_M = 0.002
# Alpha (0..255) of the virtual obstacles: drawn translucent whatever the model says.
OBSTACLE_ALPHA = 90
# Ghost poses: alpha (0..255), and the grey level (0..255) of the first and the last
# ghost (early poses light, late poses dark, as in a stroboscopic photograph).
GHOST_ALPHA = 110
GHOST_GREY_FIRST = 215
GHOST_GREY_LAST = 70
# Width of the ghost skeleton lines (m).
GHOST_SKELETON_RADIUS_M = 0.004


def body_name(model: mujoco.MjModel, body: int) -> str:
    """The body's name, or ``body_<id>`` when the model leaves it unnamed."""
    return mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body) or f"body_{body}"


def geom_name(model: mujoco.MjModel, geom: int) -> str:
    """The geom's name, or ``geom_<id>`` when the model leaves it unnamed."""
    return mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, geom) or f"geom_{geom}"


def mat_to_xyzw(mat: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4), Rerun's x, y, z, w order, of rotation matrices (N, 9) or (N, 3, 3)."""
    mats = np.asarray(mat, dtype=float).reshape(-1, 9)
    out = np.empty((len(mats), 4))
    quat = np.empty(4)
    for i, m in enumerate(mats):
        mujoco.mju_mat2Quat(quat, m)
        out[i] = quat[[1, 2, 3, 0]]
    return out


def geom_rgba_u8(model: mujoco.MjModel, geom: int) -> np.ndarray:
    """The geom's colour as RGBA bytes: its material's when it has one, else its own."""
    material = int(model.geom_matid[geom])
    rgba = model.mat_rgba[material] if material >= 0 else model.geom_rgba[geom]
    return np.clip(np.round(np.asarray(rgba) * 255.0), 0, 255).astype(np.uint8)


def primitive(
    model: mujoco.MjModel,
    geom: int,
    p_m: np.ndarray,
    mat: np.ndarray,
    rgba: np.ndarray,
) -> tuple[str, rr.AsComponents] | None:
    """One geom as a Rerun primitive at pose (p_m (3,), mat (3, 3)) in its parent frame.

    Returns (kind, archetype), kind naming the primitive ("boxes", "capsules", ...), or
    None for geoms Rerun has no primitive for (height fields, SDFs).
    """
    kind = int(model.geom_type[geom])
    size = model.geom_size[geom]
    mat = np.asarray(mat, dtype=float).reshape(3, 3)
    quat = mat_to_xyzw(mat)
    solid = rr.components.FillMode.Solid
    if kind in (mujoco.mjtGeom.mjGEOM_SPHERE, mujoco.mjtGeom.mjGEOM_ELLIPSOID):
        half = [size[0]] * 3 if kind == mujoco.mjtGeom.mjGEOM_SPHERE else size[:3]
        shape = rr.Ellipsoids3D(
            half_sizes=[half], centers=[p_m], quaternions=quat, colors=[rgba], fill_mode=solid
        )
        return "ellipsoids", shape
    if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
        # Rerun's capsule runs from its origin along +z; MuJoCo's is centred.
        start = p_m - mat[:, 2] * size[1]
        shape = rr.Capsules3D(
            lengths=[2.0 * size[1]],
            radii=[size[0]],
            translations=[start],
            quaternions=quat,
            colors=[rgba],
        )
        return "capsules", shape
    if kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
        shape = rr.Cylinders3D(
            lengths=[2.0 * size[1]],
            radii=[size[0]],
            centers=[p_m],
            quaternions=quat,
            colors=[rgba],
            fill_mode=solid,
        )
        return "cylinders", shape
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        shape = rr.Boxes3D(
            half_sizes=[size[:3]], centers=[p_m], quaternions=quat, colors=[rgba], fill_mode=solid
        )
        return "boxes", shape
    if kind == mujoco.mjtGeom.mjGEOM_PLANE:
        half = [s if s > 0 else INFINITE_PLANE_HALF_SIZE_M for s in size[:2]]
        centre = p_m - mat[:, 2] * (0.5 * PLANE_THICKNESS_M)
        shape = rr.Boxes3D(
            half_sizes=[[half[0], half[1], 0.5 * PLANE_THICKNESS_M]],
            centers=[centre],
            quaternions=quat,
            colors=[rgba],
            fill_mode=solid,
        )
        return "boxes", shape
    if kind == mujoco.mjtGeom.mjGEOM_MESH:
        mesh = int(model.geom_dataid[geom])
        vert0, nvert = int(model.mesh_vertadr[mesh]), int(model.mesh_vertnum[mesh])
        face0, nface = int(model.mesh_faceadr[mesh]), int(model.mesh_facenum[mesh])
        vertices = model.mesh_vert[vert0 : vert0 + nvert] @ mat.T + p_m
        shape = rr.Mesh3D(
            vertex_positions=vertices,
            triangle_indices=model.mesh_face[face0 : face0 + nface],
            albedo_factor=rgba,
        )
        return "meshes", shape
    return None


@dataclass(frozen=True)
class SceneGeom:
    """One visual geom: its id, the body it moves with, and its entity path."""

    geom: int
    body: int
    entity: str


class SceneModel:
    """The scene's geometry and kinematics, built once from the plant's own model.

    ``frames(q_rad, opening_m)`` gives the world poses of the moving bodies for a batch
    of joint states; ``ghost(q_rad, opening_m)`` the world poses of every arm geom.
    """

    def __init__(self, config: Config, objects_entity: str) -> None:
        self.plant = Plant(config)
        model = self.plant.model
        self.model = model
        self.data = self.plant.data
        mujoco.mj_resetData(model, self.data)
        mujoco.mj_kinematics(model, self.data)
        self._objects_entity = objects_entity
        self._obstacle_prefix = config.robot.obstacle_prefix
        object_roots = {
            mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
            for name in config.robot.object_bodies
        } - {-1}
        self._object_of: dict[int, int] = {}  # body -> its object root body
        moving: list[int] = []
        fixed: list[int] = []
        for body in range(model.nbody):
            root = self._ancestor_in(body, object_roots)
            if root is not None:
                self._object_of[body] = root
            elif self._has_joint_above(body):
                moving.append(body)
            else:
                fixed.append(body)
        self.moving_bodies = tuple(moving)
        self.fixed_bodies = tuple(fixed)
        self.geoms = tuple(
            SceneGeom(g, int(model.geom_bodyid[g]), self._geom_entity(g))
            for g in range(model.ngeom)
            if self._visible(g)
        )
        self.arm_geoms = tuple(g for g in self.geoms if g.body in set(moving))
        # The kinematic chain from the first moving body to the tool site's body.
        chain: list[int] = []
        body = int(model.site_bodyid[self.plant.tool_site])
        while body > 0 and body in set(moving):
            chain.append(body)
            body = int(model.body_parentid[body])
        self.chain_bodies = tuple(reversed(chain))
        self.chain_root = body  # the fixed body the chain hangs from (the arm's base)

    def _ancestor_in(self, body: int, roots: set[int]) -> int | None:
        while body > 0:
            if body in roots:
                return body
            body = int(self.model.body_parentid[body])
        return None

    def _has_joint_above(self, body: int) -> bool:
        while body > 0:
            if self.model.body_jntnum[body] > 0:
                return True
            body = int(self.model.body_parentid[body])
        return False

    def _visible(self, geom: int) -> bool:
        return (
            int(self.model.geom_group[geom]) < VISIBLE_GEOM_GROUPS
            and geom_rgba_u8(self.model, geom)[3] > 0
        )

    def body_entity(self, body: int) -> str:
        """Entity whose transform moves ``body``: its object's or ``world/scene/<body>``."""
        root = self._object_of.get(body)
        if root is not None:
            return f"{self._objects_entity}/{body_name(self.model, root)}"
        return f"{ENTITY_SCENE}/{body_name(self.model, body)}"

    def _geom_entity(self, geom: int) -> str:
        body = int(self.model.geom_bodyid[geom])
        return f"{self.body_entity(body)}/{geom_name(self.model, geom)}"

    def is_obstacle(self, geom: int) -> bool:
        return geom_name(self.model, geom).startswith(self._obstacle_prefix)

    def _local_pose(self, sg: SceneGeom) -> tuple[np.ndarray, np.ndarray]:
        """The geom's pose in the frame of the entity that moves it (3,), (3, 3)."""
        model, data = self.model, self.data
        root = self._object_of.get(sg.body, sg.body)
        if root != sg.body:  # a body inside an object: express it in the object's frame
            body_R = data.xmat[root].reshape(3, 3)
            rel_p = body_R.T @ (data.geom_xpos[sg.geom] - data.xpos[root])
            rel_R = body_R.T @ data.geom_xmat[sg.geom].reshape(3, 3)
            return rel_p, rel_R
        mat = np.empty(9)
        mujoco.mju_quat2Mat(mat, model.geom_quat[sg.geom])
        return model.geom_pos[sg.geom].copy(), mat.reshape(3, 3)

    def static_entities(self) -> list[tuple[str, rr.AsComponents]]:
        """Every geom's primitive and the fixed bodies' transforms, to log once as static."""
        out: list[tuple[str, rr.AsComponents]] = []
        for body in self.fixed_bodies:
            out.append(
                (
                    self.body_entity(body),
                    rr.Transform3D(
                        translation=self.data.xpos[body],
                        quaternion=self.data.xquat[body][[1, 2, 3, 0]],
                    ),
                )
            )
        for sg in self.geoms:
            rgba = geom_rgba_u8(self.model, sg.geom)
            if self.is_obstacle(sg.geom):
                rgba[3] = min(int(rgba[3]), OBSTACLE_ALPHA)
            p_m, mat = self._local_pose(sg)
            made = primitive(self.model, sg.geom, p_m, mat, rgba)
            if made is not None:
                out.append((sg.entity, made[1]))
        return out

    def _pose_arm(self, q_rad: np.ndarray, opening_m: float) -> None:
        n = min(len(q_rad), len(self.plant.qpos_index))
        self.data.qpos[self.plant.qpos_index[:n]] = q_rad[:n]
        self.data.qpos[self.plant.finger_qpos_index] = opening_m
        mujoco.mj_kinematics(self.model, self.data)

    def frames(self, q_rad: np.ndarray, opening_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World poses of the moving bodies for N joint states.

        q_rad (N, n) joint angles, opening_m (N,) gripper opening; returns positions
        (N, B, 3) in m and quaternions (N, B, 4) x, y, z, w, B = len(moving_bodies).
        """
        bodies = list(self.moving_bodies)
        n_rows = len(q_rad)
        p = np.empty((n_rows, len(bodies), 3))
        q = np.empty((n_rows, len(bodies), 4))
        for i in range(n_rows):
            self._pose_arm(q_rad[i], float(opening_m[i]))
            p[i] = self.data.xpos[bodies]
            q[i] = self.data.xquat[bodies][:, [1, 2, 3, 0]]
        return p, q

    def ghost(
        self, q_rad: np.ndarray, opening_m: float, rgba: Sequence[int]
    ) -> list[tuple[str, rr.AsComponents]]:
        """The arm at one joint state as world-frame primitives, one colour for all.

        Returns (child name, archetype) pairs: one per arm geom, plus the skeleton (a
        line from the arm's base through the chain's bodies to the tool site), which the
        report draws in its stroboscopic figure.
        """
        self._pose_arm(q_rad, opening_m)
        colour = np.asarray(rgba, dtype=np.uint8)
        out: list[tuple[str, rr.AsComponents]] = []
        for sg in self.arm_geoms:
            made = primitive(
                self.model,
                sg.geom,
                self.data.geom_xpos[sg.geom],
                self.data.geom_xmat[sg.geom],
                colour,
            )
            if made is not None:
                out.append((geom_name(self.model, sg.geom), made[1]))
        skeleton = np.vstack(
            [
                self.data.xpos[self.chain_root],
                self.data.xpos[list(self.chain_bodies)],
                self.data.site_xpos[self.plant.tool_site],
            ]
        )
        out.append(
            (
                GHOST_SKELETON,
                rr.LineStrips3D([skeleton], colors=[colour[:3]], radii=GHOST_SKELETON_RADIUS_M),
            )
        )
        return out


def ghost_rgba(fraction: float) -> tuple[int, int, int, int]:
    """Colour of a ghost ``fraction`` (0..1) of the way through the run: light early, dark
    late, translucent."""
    fraction = min(max(fraction, 0.0), 1.0)
    grey = round(GHOST_GREY_FIRST + (GHOST_GREY_LAST - GHOST_GREY_FIRST) * fraction)
    return (grey, grey, grey, GHOST_ALPHA)


def ghost_entity(index: int) -> str:
    """Entity of ghost pose ``index``, e.g. ``world/ghosts/003``."""
    return f"{ENTITY_GHOSTS}/{index:03d}"
