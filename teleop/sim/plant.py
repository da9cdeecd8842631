"""The simulated plant: a MuJoCo model of the arm and its scene, stepped at 1 kHz.

The plant knows nothing about controllers or the bus: it takes joint velocity
references for the arm's velocity loops (and a gripper opening), advances physics
one tick (one bus period, ``Config.physics_steps_per_tick`` physics steps of
``plant.timestep_s``: the drives hold the reference in between, the robot's limits and
the protective stop act on every physics step), and exposes what a real robot's drives
and sensors would report. The
plant service and the in-process runner both drive it through the same methods,
which is what makes their results bit-identical.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import mujoco
import numpy as np

from teleop.core.config import Config, ModelError, RobotConfig
from teleop.sim.checkpoint import get_state, set_state
from teleop.sim.protective import ProtectiveStop, allowed_approach_m_s
from teleop.sim.proximity import apply_scene_overrides

# Hold mode of the drives (the "brake"): stiffness of the position hold, per second.
# q'_ref = HOLD_GAIN_PER_S (q_hold - q) + gravity / kv keeps the arm where it stopped.
HOLD_GAIN_PER_S = 20.0
# The contact force while nothing touches the gripper (most steps), shared: read-only.
_NO_FORCE_N = np.zeros(3)
_NO_FORCE_N.flags.writeable = False


def _as_slice(index: np.ndarray) -> slice | np.ndarray:
    """``index`` as the equal slice when it counts up by one, else ``index`` itself."""
    if len(index) and np.array_equal(index, np.arange(index[0], index[0] + len(index))):
        return slice(int(index[0]), int(index[0]) + len(index))
    return index


@dataclass(frozen=True)
class JointSample:
    """What the drives report after a physics step (arm joints only, config order)."""

    step: int
    sim_time_ns: int
    q_rad: np.ndarray  # (n,)
    qd_rad_s: np.ndarray  # (n,)
    gripper_opening_m: float


def gripper_bodies(model: mujoco.MjModel, tool_site: int) -> set[int]:
    """The gripper: every body in the subtree of the tool site's body (palm, fingers)."""
    root = model.site_bodyid[tool_site]

    def in_subtree(body: int) -> bool:
        while body != 0:
            if body == root:
                return True
            body = model.body_parentid[body]
        return root == 0

    return {b for b in range(model.nbody) if in_subtree(b)}


def _load_scene(path: Path, tool_site: str, gap_m: float) -> mujoco.MjModel:
    """The scene's model, the gripper's geoms given a collision gap of ``gap_m``: MuJoCo
    then reports their contacts up to that far (``exclude`` 1: out of the constraint
    solver, the physics unchanged). Set in the spec before compiling: a compiled model's
    collision bounds do not follow a later change of ``geom_gap``."""
    spec = mujoco.MjSpec.from_file(str(path))
    model = spec.compile()
    if gap_m <= 0:
        return model
    site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, tool_site)
    if site < 0:
        raise ModelError(f"{path}: no site {tool_site!r}")
    bodies = gripper_bodies(model, site)
    for g in range(model.ngeom):
        if model.geom_bodyid[g] in bodies:
            geom = spec.geoms[g]  # the spec lists the geoms in the model's order
            if geom.name != model.geom(g).name:
                raise ModelError(f"{path}: geom {g} is {geom.name!r} in the spec")
            geom.gap = gap_m
    return spec.compile()


class GripperContact(NamedTuple):
    """One of MuJoCo's contacts between the gripper and something else."""

    index: int  # in data.contact
    on_geom2: bool  # the gripper is the contact's geom2 (the normal points towards it)
    with_object: bool  # the other geom is a free object's (the cube)
    active: bool  # touching (in the physics); else only within the approach range


class Plant:
    """MuJoCo model + data, with name lookups resolved once from the config."""

    def __init__(self, config: Config) -> None:
        path = config.robot.scene_path
        self._load_model(config, path)
        self._resolve_names(config.robot, path)
        self._init_limits(config)
        self._init_measurements()

    def _load_model(self, config: Config, path: Path) -> None:
        """The scene's model (the gripper's contacts reported within the approach range)
        and data, checked against the config's physics period, with its overrides."""
        if not path.exists():
            raise ModelError(f"scene file not found: {path}")
        # Speed and separation: MuJoCo reports the gripper's contacts up to
        # approach_range_m away but keeps those at a distance out of the physics.
        plant = config.plant
        self.approach_touch_m_s = plant.approach_touch_m_s
        self.approach_time_s = plant.approach_time_s
        self.approach_range_m = plant.tool_speed_limit_m_s * plant.approach_time_s
        self.model = _load_scene(path, config.robot.tool_site, self.approach_range_m)
        if not np.isclose(self.model.opt.timestep, config.plant.timestep_s):
            raise ModelError(
                f"{path}: timestep {self.model.opt.timestep} s differs from "
                f"plant.timestep_s {config.plant.timestep_s} s"
            )
        apply_scene_overrides(self.model, config.scene, config.robot)
        self.data = mujoco.MjData(self.model)
        self.timestep_ns = round(self.model.opt.timestep * 1e9)  # one physics step
        self.steps_per_tick = config.physics_steps_per_tick
        self.tick_ns = self.steps_per_tick * self.timestep_ns  # one bus period
        self._config = config

    def _resolve_names(self, robot: RobotConfig, path: Path) -> None:
        """The config's joint, actuator, site and body names as the model's indices, once
        (a missing one: ModelError naming the file), and what follows from them."""

        def lookup(kind: mujoco.mjtObj, name: str) -> int:
            index = mujoco.mj_name2id(self.model, kind, name)
            if index < 0:
                raise ModelError(f"{path}: no {kind.name.removeprefix('mjOBJ_').lower()} {name!r}")
            return index

        joints = [lookup(mujoco.mjtObj.mjOBJ_JOINT, n) for n in robot.arm_joints]
        self.joint_ids = np.array(joints)  # the arm's joints in the model
        self.qpos_index = np.array([self.model.jnt_qposadr[j] for j in joints])
        self.dof_index = np.array([self.model.jnt_dofadr[j] for j in joints])
        self.actuator_index = np.array(
            [lookup(mujoco.mjtObj.mjOBJ_ACTUATOR, n) for n in robot.arm_actuators]
        )
        self.kv = self.model.actuator_gainprm[self.actuator_index, 0].copy()
        self.gripper_actuator = lookup(mujoco.mjtObj.mjOBJ_ACTUATOR, robot.gripper_actuator)
        # (low, high) as Python floats: _gripper_ctrl runs every step, and arithmetic on
        # numpy scalars costs many times that on floats.
        self.gripper_range_m = tuple(
            float(x) for x in self.model.actuator_ctrlrange[self.gripper_actuator]
        )
        self.finger_qpos_index = np.array(
            [
                self.model.jnt_qposadr[lookup(mujoco.mjtObj.mjOBJ_JOINT, n)]
                for n in robot.gripper_joints
            ]
        )
        self.tool_site = lookup(mujoco.mjtObj.mjOBJ_SITE, robot.tool_site)
        self.object_bodies = np.array(
            [lookup(mujoco.mjtObj.mjOBJ_BODY, n) for n in robot.object_bodies], dtype=int
        )
        self.gripper_bodies = gripper_bodies(self.model, self.tool_site)
        self._gripper_geoms = frozenset(
            g for g in range(self.model.ngeom) if self.model.geom_bodyid[g] in self.gripper_bodies
        )
        # The objects that move freely (the cube; not the bin, welded to the world): the
        # gripper may hold them, and what they push is not a press on the scene.
        free = {b for b in self.object_bodies.tolist() if self.model.body_weldid[b] != 0}
        self._object_geoms = frozenset(
            g for g in range(self.model.ngeom) if self.model.geom_bodyid[g] in free
        )
        # The arm's joints as slices when contiguous (they are in the shipped model): a
        # slice reads a view, an index array makes numpy gather into a new array.
        self._q_at = _as_slice(self.qpos_index)
        self._qd_at = _as_slice(self.dof_index)
        self._ctrl_at = _as_slice(self.actuator_index)
        self._fingers_at = _as_slice(self.finger_qpos_index)
        self.ctrl_low = self.model.actuator_ctrlrange[self.actuator_index, 0].copy()
        self.ctrl_high = self.model.actuator_ctrlrange[self.actuator_index, 1].copy()

    def _init_limits(self, config: Config) -> None:
        """The robot's own limits on every command (the approach limit, the drives'
        ranges, the tool's speed), and their counters."""
        self.approach_slowed_steps = 0  # steps whose command the approach limit slowed
        self._limit_slowed = False  # the last limit() slowed it for the approach
        self._jac_other = np.zeros((3, self.model.nv))
        # The robot's own limits, enforced on every command whatever sent it: each joint
        # within its drive's range, the tool point's commanded speed within this.
        self.tool_speed_limit_m_s = config.plant.tool_speed_limit_m_s
        self.clamped_steps = 0  # steps whose command was cut down to the limits
        # ... by reason: a joint beyond its drive's range, the tool's speed over its limit
        self.joint_range_steps = 0
        self.tool_speed_steps = 0
        self._limit_cuts = (False, False)  # the last limit()'s (joint range, tool speed)
        # The tool speed the last command asked for (m/s, its motion before any cut).
        self.commanded_tool_speed_m_s = 0.0

    def _init_measurements(self) -> None:
        """What each step measures and keeps: the gripper's contacts and forces, the tool's
        speed, the protective stop, the step counts and the gripper's and brake's state."""
        self._step1_done = False  # prepare_step ran for the next step
        # prepare_step's gripper contacts (see _find_gripper_contacts); None: not known.
        self._gripper_contacts: list[GripperContact] | None = None
        # Measured after every step (what the state reports and the protective stop
        # judges): the net contact force on the gripper (N, world), its contacts, the part
        # of that force from everything but the free objects (the scene, the arm), and
        # the tool point's speed (m/s).
        self._site_velocity = np.zeros(6)  # tool_speed_m_s's buffer
        self.contact_force_n = np.zeros(3)
        self.n_contacts = 0
        self.scene_contact_force_n = np.zeros(3)
        self.measured_tool_speed_m_s = 0.0
        self.protective = self._new_protective_stop()
        self._jacp = np.zeros((3, self.model.nv))
        self.step_count = 0  # ticks (bus periods) stepped
        self.physics_steps = 0  # physics steps taken (steps_per_tick per tick)
        # The tick's extremes over its physics steps (the state after a tick reports its
        # last step; a contact peak inside it must not go unseen): the largest net contact
        # force on the gripper (N) and tool speed (m/s).
        self.tick_peak_contact_force_n = 0.0
        self.tick_peak_tool_speed_m_s = 0.0
        self.gripper_cmd = 1.0  # the gripper command in effect (0 closed .. 1 open)
        self._hold_q_rad: np.ndarray | None = None

    def _new_protective_stop(self) -> ProtectiveStop:
        plant = self._config.plant
        return ProtectiveStop(
            plant.contact_force_limit_n,
            plant.tool_speed_stop_m_s,
            plant.protective_release_m_s,
            max(1, round(plant.protective_release_s / plant.timestep_s)),
        )

    @property
    def n_joints(self) -> int:
        return len(self.qpos_index)

    def reset(self, q_rad: np.ndarray, gripper_open: float = 1.0) -> None:
        """Put the arm at ``q_rad`` at rest, the gripper at the given opening fraction."""
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self.qpos_index] = q_rad
        opening = self._gripper_ctrl(gripper_open)
        self.data.qpos[self.finger_qpos_index] = opening
        self.data.ctrl[self.gripper_actuator] = opening
        mujoco.mj_forward(self.model, self.data)
        self._step1_done = False
        self._gripper_contacts = None
        self.gripper_cmd = min(max(gripper_open, 0.0), 1.0)
        self.step_count = 0
        self.physics_steps = 0
        self._hold_q_rad = None
        self.protective = self._new_protective_stop()
        self._measure()
        self._start_tick()

    def integration_state(self) -> np.ndarray:
        """MuJoCo's full integration state now (teleop.sim.checkpoint.get_state)."""
        return get_state(self.model, self.data)

    def restore(
        self,
        mujoco_state: np.ndarray,
        step: int,
        gripper_cmd: float,
        hold_q_rad: np.ndarray | None = None,
    ) -> None:
        """Continue from a checkpoint: ``mujoco_state`` (:meth:`integration_state` of this
        model), the tick count at ``step`` (sim time ``step`` ticks), the gripper
        command and the brake's hold (None: not braking) as they were. The next steps
        are those the checkpointed plant would have taken (same state, same warm start)."""
        set_state(self.model, self.data, mujoco_state)
        self.physics_steps = step * self.steps_per_tick
        self.data.time = self.physics_steps * self.model.opt.timestep
        mujoco.mj_forward(self.model, self.data)  # poses and contacts for the next sample
        self._step1_done = False
        self._gripper_contacts = None
        self.step_count = step
        self.gripper_cmd = min(max(gripper_cmd, 0.0), 1.0)
        self._hold_q_rad = None if hold_q_rad is None else np.array(hold_q_rad, dtype=float)
        self._measure()
        self._start_tick()

    @property
    def hold_q_rad(self) -> np.ndarray | None:
        """Where the brake holds the arm (n,), rad; None when not braking."""
        return self._hold_q_rad

    def _gripper_ctrl(self, gripper_cmd: float) -> float:
        low, high = self.gripper_range_m
        fraction = min(max(gripper_cmd, 0.0), 1.0)  # scalar clip: np.clip costs 10x here
        return low + fraction * (high - low)

    def prepare_step(self) -> None:
        """Compute now the part of the next step that no control affects: MuJoCo's
        ``mj_step1`` (kinematics, collision detection, velocity-dependent forces), so a
        command that arrives later costs only ``mj_step2`` (actuation, constraint solve,
        integration). Call it while waiting for the command; a step runs it itself if
        nobody did. ``mj_step1`` + ``mj_step2`` equal ``mj_step`` bit for bit with this
        model's implicitfast integrator (checked over 3000 steps with contacts), so runs
        that prepare and runs that do not stay identical.

        After it, positions-dependent data (``geom_xpos``, contacts) describe the state
        the last step reached, exactly as during the next ``mj_step``.
        """
        if not self._step1_done:
            mujoco.mj_step1(self.model, self.data)
            # The contacts are found here (collision detection): which of them touch the
            # gripper is control-free too, ready for gripper_contact_force after the step.
            self._gripper_contacts = self._find_gripper_contacts()
            self._step1_done = True

    def _advance(self) -> None:
        """Finish the step with the controls set (``mj_step2``), after ``mj_step1``."""
        self.prepare_step()
        mujoco.mj_step2(self.model, self.data)
        self._step1_done = False
        self.physics_steps += 1
        self._measure()
        scene_n = self.scene_contact_force_n.tolist()
        self.protective.measure(
            self.physics_steps, math.hypot(*scene_n), self.measured_tool_speed_m_s
        )
        self.tick_peak_contact_force_n = max(
            self.tick_peak_contact_force_n, math.hypot(*self.contact_force_n.tolist())
        )
        self.tick_peak_tool_speed_m_s = max(
            self.tick_peak_tool_speed_m_s, self.measured_tool_speed_m_s
        )

    def _start_tick(self) -> None:
        """The next tick's extremes start from the state now."""
        self.tick_peak_contact_force_n = math.hypot(*self.contact_force_n.tolist())
        self.tick_peak_tool_speed_m_s = self.measured_tool_speed_m_s

    def _measure(self) -> None:
        """The contact forces on the gripper and the tool's speed in the state now."""
        self.contact_force_n, self.n_contacts, self.scene_contact_force_n = self._contact_forces()
        self.measured_tool_speed_m_s = self.tool_speed_m_s()

    def limit(self, qd_ref_rad_s: np.ndarray) -> np.ndarray:
        """``qd_ref_rad_s`` within the robot's limits: each joint clipped to its drive's
        range (the velocity actuator's ctrlrange), then the motion it asks for scaled
        down (the direction kept) so the tool point's commanded speed is at most
        ``plant.tool_speed_limit_m_s``. Counts the steps it cut (``clamped_steps``; by
        reason ``joint_range_steps`` and ``tool_speed_steps``).

        A velocity servo's reference also carries the torque that holds the arm: its
        drive settles where kv (q'_ref - q') = the bias forces (gravity, Coriolis), so
        the joints move at q'_ref - bias / kv, and a reference with the paper's dynamic
        compensation holds bias / kv on top of the motion it asks for (at full reach
        with a held cube, as much as a 0.17 m/s tool speed). The speed limited is that of
        the motion: MuJoCo's site Jacobian at the state the step starts from times
        (q'_ref - qfrc_bias / kv); cutting the holding part too would let the arm sag
        and bend the tool's path while it is commanded up."""
        qd = np.minimum(np.maximum(qd_ref_rad_s, self.ctrl_low), self.ctrl_high)
        range_cut = qd.tolist() != qd_ref_rad_s.tolist()  # np.array_equal costs 10x
        self.prepare_step()  # positions-dependent data of the state the step starts from
        mujoco.mj_jacSite(self.model, self.data, self._jacp, None, self.tool_site)
        hold = self.data.qfrc_bias[self.dof_index] / self.kv  # references that hold still
        motion = qd - hold
        speed_m_s = math.hypot(*(self._jacp[:, self.dof_index] @ motion).tolist())
        self.commanded_tool_speed_m_s = speed_m_s
        scale = 1.0
        speed_cut = speed_m_s > self.tool_speed_limit_m_s
        if speed_cut:
            scale = self.tool_speed_limit_m_s / speed_m_s
        approach_scale = self._approach_scale(motion * scale)
        self._limit_slowed = approach_scale < 1.0
        if self._limit_slowed:
            scale *= approach_scale
            self.approach_slowed_steps += 1
        if scale < 1.0:
            qd = hold + motion * scale
            qd = np.minimum(np.maximum(qd, self.ctrl_low), self.ctrl_high)
        self._limit_cuts = (range_cut, speed_cut)
        self._count_cuts()
        return qd

    def joint_reach_m(self) -> np.ndarray:
        """For each arm joint, the farthest the tool point can be from its axis (m), in
        any configuration: the joint's anchor offset in its body plus every rigid offset
        down the chain to the tool site (the triangle inequality; rotations keep
        lengths). A joint turning at q'_i moves the tool at most |q'_i| times this, so

            tool speed <= sum_i |q'_i| reach_i

        is a bound a controller without the robot's model can keep under
        ``plant.tool_speed_limit_m_s``."""
        model = self.model
        site_body = int(model.site_bodyid[self.tool_site])
        reach = []
        for joint in self.joint_ids.tolist():
            body = int(model.jnt_bodyid[joint])
            length = float(np.linalg.norm(model.jnt_pos[joint]))
            length += float(np.linalg.norm(model.site_pos[self.tool_site]))
            chain = site_body
            while chain != body:  # the site's body up to the joint's own
                length += float(np.linalg.norm(model.body_pos[chain]))
                chain = int(model.body_parentid[chain])
            reach.append(length)
        return np.array(reach)

    def clamped_by_reason(self) -> dict[str, int]:
        """Physics steps whose command the plant cut or slowed, by reason (a step may
        count under several): a joint beyond its drive's range, the tool's commanded
        speed over ``plant.tool_speed_limit_m_s``, the approach to the scene."""
        return {
            "joint_range": self.joint_range_steps,
            "tool_speed": self.tool_speed_steps,
            "approach": self.approach_slowed_steps,
        }

    def _count_cuts(self) -> None:
        """Count the last :meth:`limit`'s cuts for one more physics step."""
        range_cut, speed_cut = self._limit_cuts
        self.clamped_steps += range_cut or speed_cut
        self.joint_range_steps += range_cut
        self.tool_speed_steps += speed_cut

    def _approach_scale(self, motion_rad_s: np.ndarray) -> float:
        """How much ``motion_rad_s`` (the arm's joint velocities) must be slowed (a
        factor in (0, 1]) so that no point of the gripper closes in on the scene (not a
        free object) faster than :func:`allowed_approach_m_s` at its separation: over
        the gripper's contacts of the state the step starts from, touching or within
        ``approach_range_m``, the relative speed of the contact point along the normal."""
        if self.approach_time_s <= 0:
            return 1.0
        contacts = self._gripper_contacts or ()
        scale = 1.0
        dofs = self.dof_index
        model, data = self.model, self.data
        for contact in contacts:
            if contact.with_object:
                continue
            i = contact.index
            point = data.contact.pos[i]
            gripper_geom, other_geom = data.contact.geom[i][:: -1 if contact.on_geom2 else 1]
            mujoco.mj_jac(model, data, self._jacp, None, point, model.geom_bodyid[gripper_geom])
            relative = self._jacp[:, dofs] @ motion_rad_s
            other_body = model.geom_bodyid[other_geom]
            if model.body_weldid[other_body] != 0:  # a moving body (the arm): relative speed
                mujoco.mj_jac(model, data, self._jac_other, None, point, other_body)
                relative -= self._jac_other[:, dofs] @ motion_rad_s
            # The normal points from geom1 to geom2: from the scene towards the gripper
            # when the gripper is geom2. Closing in = moving against it.
            normal = data.contact.frame[i][:3]
            closing_m_s = float(-(normal @ relative) if contact.on_geom2 else normal @ relative)
            allowed = allowed_approach_m_s(
                float(data.contact.dist[i]), self.approach_touch_m_s, self.approach_time_s
            )
            if closing_m_s > allowed:
                scale = min(scale, allowed / closing_m_s)
        return scale

    def step(self, qd_ref_rad_s: np.ndarray, gripper_cmd: float) -> None:
        """Apply velocity references (rad/s) for one tick: each physics step holds them,
        within :meth:`limit` at the state it starts from; while a protective stop holds
        (teleop.sim.protective) the gripper follows the command and the arm is held,
        until a command asks for no motion."""
        self._start_tick()
        self.gripper_cmd = min(max(gripper_cmd, 0.0), 1.0)
        gripper_ctrl = self._gripper_ctrl(gripper_cmd)
        qd = None
        for _ in range(self.steps_per_tick):
            self.prepare_step()  # this step's contacts (collision detection)
            if qd is None or self._gripper_contacts:
                # The tick's first step, or the gripper near something (the approach
                # limit's contacts, a held object's): the limits at this step's own state.
                qd = self.limit(qd_ref_rad_s)
            else:
                # Free of everything: the limited command holds (the tool-speed limit on
                # the motion it asks for; the arm moves well under a millimetre per step,
                # and the protective stop judges the measured speed after every step).
                self._count_cuts()
                self.approach_slowed_steps += self._limit_slowed
            self.data.ctrl[self.gripper_actuator] = gripper_ctrl
            if self.protective.holds(self.physics_steps + 1, self.commanded_tool_speed_m_s):
                self._brake()
                continue
            self._hold_q_rad = None
            self.data.ctrl[self._ctrl_at] = qd
            self._advance()
        self.step_count += 1

    def step_before_commands(self) -> None:
        """A tick before the first command applies (lockstep delay): the drives are asked
        for zero joint velocity, the gripper keeps its opening from :meth:`reset`."""
        self._start_tick()
        self._hold_q_rad = None
        for _ in range(self.steps_per_tick):
            self.data.ctrl[self.actuator_index] = 0.0
            self._advance()
        self.step_count += 1

    def step_braking(self) -> None:
        """A tick holding the arm where braking began (watchdog): no drift, gravity held
        by the drives."""
        self._start_tick()
        for _ in range(self.steps_per_tick):
            self.protective.held()
            self._brake()
        self.step_count += 1

    def _brake(self) -> None:
        self.prepare_step()  # the bias forces of the state now, however the caller got here
        q = self.data.qpos[self.qpos_index]
        if self._hold_q_rad is None:
            self._hold_q_rad = q.copy()
        gravity_nm = self.data.qfrc_bias[self.dof_index]  # at rest the bias is gravity
        qd_ref = HOLD_GAIN_PER_S * (self._hold_q_rad - q) + gravity_nm / self.kv
        self.data.ctrl[self.actuator_index] = qd_ref
        self._advance()

    def applied_qd_ref_rad_s(self) -> np.ndarray:
        """Joint velocity references the drives got in the last step (n,), rad/s: the
        command, or the brake's hold references, clipped to the actuators' range as
        MuJoCo applies them."""
        return np.minimum(np.maximum(self.data.ctrl[self._ctrl_at], self.ctrl_low), self.ctrl_high)

    @property
    def braking(self) -> bool:
        return self._hold_q_rad is not None

    def sample(self) -> JointSample:
        fingers_m = self.data.qpos[self._fingers_at].tolist()  # a numpy sum costs more, cold
        return JointSample(
            step=self.step_count,
            sim_time_ns=self.physics_steps * self.timestep_ns,
            q_rad=self.data.qpos[self._q_at].copy(),
            qd_rad_s=self.data.qvel[self._qd_at].copy(),
            gripper_opening_m=sum(fingers_m) / len(fingers_m),
        )

    def tool_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """world_p_tool (3,) in m and world_q_tool as a wxyz quaternion (4,)."""
        position = self.data.site_xpos[self.tool_site].copy()
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, self.data.site_xmat[self.tool_site])
        return position, quat

    def gripper_contact_force(self) -> tuple[np.ndarray, int]:
        """Total contact force on the gripper (N, world frame) and the number of contacts."""
        total, count, _ = self._contact_forces()
        return total, count

    def _contact_forces(self) -> tuple[np.ndarray, int, np.ndarray]:
        """The total contact force on the gripper (N, world frame), its number of
        contacts, and the part of the total from contacts with anything but a free object
        (the table, the bin, the arm): a held cube's weight and inertia (a sharp stop
        with the cube in hand) are no press on the scene.

        MuJoCo's contact frame has its normal pointing from geom1 to geom2 and
        ``mj_contactForce`` gives the force geom1 exerts on geom2 in that frame.
        """
        contacts = self._gripper_contacts
        if contacts is None:  # no step since reset: the contacts of mj_forward
            contacts = self._find_gripper_contacts()
        if not any(contact.active for contact in contacts):  # most steps: nothing touches
            return _NO_FORCE_N, 0, _NO_FORCE_N
        total, scene = np.zeros(3), np.zeros(3)
        wrench = np.zeros(6)
        touching = 0
        for i, on_geom2, with_object, active in contacts:
            if not active:
                continue  # only near: no force
            touching += 1
            mujoco.mj_contactForce(self.model, self.data, i, wrench)
            force_world = self.data.contact.frame[i].reshape(3, 3).T @ wrench[:3]
            on_gripper = force_world if on_geom2 else -force_world
            total += on_gripper
            if not with_object:
                scene += on_gripper
        return total, touching, scene

    def _find_gripper_contacts(self) -> list[GripperContact]:
        """The contacts between the gripper and anything else, in ``data.contact``
        order: touching, or only near (within the approach range, out of the physics).

        Geom pairs as Python ints: a pass over them costs half of one MjContact per
        contact, or of numpy masks (cold caches included).
        """
        found = []
        gripper, objects = self._gripper_geoms, self._object_geoms
        contact = self.data.contact  # a new view of the contact array at each access
        excluded = contact.exclude.tolist()
        for i, (geom1, geom2) in enumerate(contact.geom.tolist()):
            on_geom2 = geom2 in gripper
            if (geom1 in gripper) != on_geom2:  # not itself against itself
                other_is_object = (geom1 if on_geom2 else geom2) in objects
                found.append(GripperContact(i, on_geom2, other_is_object, excluded[i] == 0))
        return found

    def object_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions (k, 3) in m and wxyz quaternions (k, 4) of RobotConfig.object_bodies."""
        return (
            self.data.xpos[self.object_bodies].copy(),
            self.data.xquat[self.object_bodies].copy(),
        )

    def tool_jacobian(self) -> np.ndarray:
        """MuJoCo's own (3, n) position Jacobian of the tool site, for cross-checks."""
        jacp = np.zeros((3, self.model.nv))
        mujoco.mj_jacSite(self.model, self.data, jacp, None, self.tool_site)
        return jacp[:, self.dof_index]

    def set_arm_configuration(self, q_rad: np.ndarray) -> None:
        """Pose the arm kinematically (no dynamics), for model cross-checks."""
        self.data.qpos[self.qpos_index] = q_rad
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_comPos(self.model, self.data)
        self._step1_done = False
        self._gripper_contacts = None

    def tool_speed_m_s(self) -> float:
        """Linear speed of the tool point (m/s), from MuJoCo's own site velocity."""
        velocity = self._site_velocity  # [angular, linear] in the world frame, overwritten
        mujoco.mj_objectVelocity(
            self.model, self.data, mujoco.mjtObj.mjOBJ_SITE, self.tool_site, velocity, 0
        )
        return math.hypot(*velocity[3:].tolist())  # np.linalg.norm costs several times more

    def object_in_bin(self, object_body: str = "cube", bin_body: str = "bin") -> bool:
        """True when the object's centre lies inside the bin: within its floor's x-y
        extent and below the top of its walls (the bin's geoms, world frame)."""
        return self.object_bin_distance_m(object_body, bin_body) == 0.0

    def object_bin_distance_m(self, object_body: str = "cube", bin_body: str = "bin") -> float:
        """How far (m) the object's centre is from the inside of the bin: 0 within its
        floor's x-y extent and below the top of its walls, else the distance to that box
        (the bin's geoms, axis-aligned boxes in this scene, world frame)."""
        obj = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, object_body)
        container = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, bin_body)
        if obj < 0 or container < 0:
            raise ModelError(f"no body {object_body!r} or {bin_body!r} in the scene")
        geoms = np.flatnonzero(self.model.geom_bodyid == container)
        centres = self.data.geom_xpos[geoms]
        half = self.model.geom_size[geoms]
        low, high = (centres - half).min(axis=0), (centres + half).max(axis=0)
        p = self.data.xpos[obj]
        if bool(np.all((low < p) & (p < high))):
            return 0.0
        outside = np.maximum(low - p, 0.0) + np.maximum(p - high, 0.0)
        # On a face exactly (outside by 0 on every axis): not inside, the least distance.
        return max(float(np.linalg.norm(outside)), float(np.finfo(float).tiny))

    def state_sha256(self) -> str:
        """sha256 of the full qpos and qvel bytes: equal hashes mean identical runs."""
        return hashlib.sha256(self.data.qpos.tobytes() + self.data.qvel.tobytes()).hexdigest()


def initial_configuration(config: Config) -> np.ndarray:
    """Start configuration (rad): the configured one plus seeded noise.

    The same seed always gives the same start, so a run is reproducible bit for bit.
    """
    base = np.array(config.run.initial_q_rad or config.robot.home_q_rad, dtype=float)
    if len(base) != len(config.robot.arm_joints):
        raise ValueError("run.initial_q_rad: one angle per arm joint")
    rng = np.random.default_rng(config.run.seed)
    return base + rng.normal(0.0, config.run.initial_q_noise_rad, size=base.shape)
