"""The names a recording is made of: Rerun application id, timelines, entity paths.

An API shared by the recorder (which logs them), the blueprint and the report (which
read them) and the tests; nothing here imports Rerun.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from teleop.bus.messages import Stage

APPLICATION_ID = "zenoh-teleop"  # Rerun application id: the viewer groups recordings by it

# --- Timelines ------------------------------------------------------------------------------
TIMELINE_SIM = "sim_time"  # duration timeline from sim_time_ns
TIMELINE_SOURCE = "source_time"  # duration timeline from the header's t_source_ns

# --- Entity paths (an API: the blueprint and tests use these names) -------------------------
ENTITY_JOINT_Q = "robot/joints/q_rad"  # + /<joint name>, Scalars
ENTITY_JOINT_QD = "robot/joints/qd_rad_s"  # + /<joint name>, Scalars
ENTITY_GRIPPER_OPENING = "robot/gripper_opening_m"  # Scalars
# Contact and obstacle proximity (PLANT_STATE): only the rows whose interaction fields
# were computed at that step (every step in teleoperation, else at the plant's scene rate).
ENTITY_CONTACT_FORCE = "robot/contact_force_n"  # + /x, /y, /z, Scalars (world frame)
ENTITY_CONTACT_COUNT = "robot/n_contacts"  # Scalars
# + /<joint name>, Scalars: the references the drives got (PLANT_STATE, not JOINT_COMMAND:
# one fewer 1 kHz stream to receive, and it is what was applied, at the step's sim time).
ENTITY_QD_REF = "control/qd_ref_rad_s"
ENTITY_GRIPPER_CMD = "control/gripper_cmd"  # Scalars, 0 closed .. 1 open
ENTITY_PATH_ERROR = "control/path_error_m"  # Scalars
ENTITY_MANIPULABILITY = "control/manipulability"  # Scalars
ENTITY_PATH_S = "control/path_s"  # Scalars
ENTITY_DESIRED_P = "control/desired_p_m"  # + /x, /y, /z, Scalars (world frame)
ENTITY_TOOL_P = "control/tool_p_m"  # + /x, /y, /z, Scalars (world frame)
ENTITY_TOOL = "world/tool"  # Transform3D: world_T_tool
ENTITY_TOOL_TRACE = "world/tool_trace"  # LineStrips3D of recent tool positions
ENTITY_OBJECTS = "world/objects"  # + /<body name>, Transform3D: world_T_object
ENTITY_EVENTS = "events"  # TextLog, "<EVENT NAME> at step <step>"
ENTITY_RECORDER_EVENTS = "events/recorder"  # TextLog: gaps, restarts, drops, services
ENTITY_WORLD = "world"  # root of the 3D scene (world frame, z up)
ENTITY_DESIRED_PATH = "world/desired_path"  # LineStrips3D, static (path following)
# The operator's eye view (EYE_VIEW): EncodedImage (JPEG) or Image (raw RGB) per frame.
ENTITY_EYE_VIEW = "operator/eye_view"
ENTITY_RATES = "rates"  # + /<stream>, Scalars: records per second of the producer's clock
ENTITY_LATENCY = "latency"  # + /<stream>, Scalars (ms), one series per hop <STAGE>_to_<STAGE>
ENTITY_TELEOP_V_ERROR = "teleop/v_error_m_s"  # + /x, /y, /z: v_ref - v_tool (Fig. 13)
ENTITY_STATS = "recorder/stats"  # TextDocument (JSON), static, written at close
# Haptic device (HAPTIC_STATE), device frame: handle centred in its workspace.
ENTITY_HAPTIC_P = "haptic/device_p_m"  # + /x, /y, /z, Scalars
ENTITY_HAPTIC_V = "haptic/device_v_m_s"  # + /x, /y, /z, Scalars (Kalman estimate)
ENTITY_HAPTIC_F = "haptic/device_f_n"  # + /x, /y, /z, Scalars (force rendered)
ENTITY_HAPTIC_BUTTONS = "haptic/buttons"  # Scalars, the Button bits as a number
# The passivity observer's energy (J) and what its controller dissipated (teleop.stabiliser).
ENTITY_PASSIVITY_OBSERVED = "haptic/passivity/observed_j"  # Scalars
ENTITY_PASSIVITY_DISSIPATED = "haptic/passivity/dissipated_j"  # Scalars
# Scripted operator's hand (HAND_INPUT), device frame.
ENTITY_HAND_TARGET = "operator/hand_target_m"  # + /x, /y, /z, Scalars
ENTITY_HAND_BUTTONS = "operator/buttons"  # Scalars, the Button bits as a number
# Force feedback (FORCE_FEEDBACK): the commanded device force and its components.
ENTITY_FEEDBACK_DEVICE_F = "feedback/device_f_n"  # + /x, /y, /z, Scalars (device frame)
ENTITY_FEEDBACK_CONTACT_F = "feedback/contact_n"  # + /x, /y, /z, Scalars (world frame)
ENTITY_FEEDBACK_WEIGHT_F = "feedback/weight_n"  # + /x, /y, /z, Scalars (world frame)
ENTITY_FEEDBACK_OBSTACLE_F = "feedback/obstacle_n"  # + /x, /y, /z, Scalars (world frame)
ENTITY_FEEDBACK_WORKSPACE_F = "feedback/workspace_n"  # + /x, /y, /z, Scalars (device frame)
# The table, the bin and other static geoms near the arm; joint limits and the arm's links
# near each other (world frame).
ENTITY_FEEDBACK_SCENE_F = "feedback/scene_n"  # + /x, /y, /z, Scalars
ENTITY_FEEDBACK_LIMITS_F = "feedback/limits_n"  # + /x, /y, /z, Scalars
ENTITY_FEEDBACK_NORM = "feedback/norm_n"  # + /<component>, Scalars, |force| (N)
ENTITY_FORCES = "world/forces"  # + /<component>, Arrows3D at the tool, once per flush
# Head-mounted display (HEAD_POSE), world frame.
ENTITY_HMD_MEASURED_YAW = "hmd/measured_yaw_rad"  # Scalars
ENTITY_HMD_PREDICTED_YAW = "hmd/predicted_yaw_rad"  # Scalars
ENTITY_HMD_FILTERED_P = "hmd/filtered_p_m"  # + /x, /y, /z, Scalars
ENTITY_HMD_MEASURED_P = "hmd/measured_p_m"  # + /x, /y, /z, Scalars
ENTITY_HMD = "world/hmd"  # Transform3D: world_T_head (predicted) + static Pinhole
ENTITY_OBSTACLE_DISTANCE = "obstacles/distance_m"  # Scalars, signed (same rows as contact)
# Teleoperation status (TELEOP_STATUS).
ENTITY_TELEOP_V_REF = "teleop/v_ref_m_s"  # + /x, /y, /z, Scalars (world frame)
ENTITY_TELEOP_V_TOOL = "teleop/v_tool_m_s"  # + /x, /y, /z, Scalars (world frame)
ENTITY_TELEOP_SPEED_SCALE = "teleop/speed_scale"  # Scalars, 0 .. 1
ENTITY_TELEOP_GRIPPER_CMD = "teleop/gripper_cmd"  # Scalars, 0 closed .. 1 open
ENTITY_TELEOP_HOLDING = "teleop/holding"  # Scalars, 1 while an object is held
AXES = ("x", "y", "z")  # suffixes of the per-coordinate scalar entities


def entity_roots(robot_ids: Sequence[str]) -> tuple[str, ...]:
    """The entity root of each robot of a recording: the empty root for one robot (its
    entities as named above), each robot's id for several (``arm1/world/tool``)."""
    return ("",) if len(robot_ids) <= 1 else tuple(robot_ids)


def rooted(root: str, entity: str) -> str:
    """``entity`` under a robot's entity root (the empty root: ``entity`` itself)."""
    return f"{root}/{entity}" if root else entity


def joint_entity(base: str, joint_name: str) -> str:
    """Entity of one joint's scalar series, e.g. ``robot/joints/q_rad/elbow``."""
    return f"{base}/{joint_name}"


def axis_entity(base: str, axis: str) -> str:
    """Entity of one coordinate's scalar series, e.g. ``control/tool_p_m/x``."""
    return f"{base}/{axis}"


def rate_entity(stream: str) -> str:
    """Entity of one stream's loop rate, e.g. ``rates/plant_state``."""
    return f"{ENTITY_RATES}/{stream}"


def latency_entity(stream: str) -> str:
    """Entity of one stream's hop latencies (one series per hop), e.g. ``latency/plant_state``."""
    return f"{ENTITY_LATENCY}/{stream}"


def hop_name(first: Stage, second: Stage) -> str:
    """Name of the series of one hop, e.g. ``PLANT_RX_to_PLANT_APPLIED``."""
    return f"{first.name}_to_{second.name}"


def object_entity(body_name: str) -> str:
    """Entity of one object's pose, e.g. ``world/objects/cube``."""
    return f"{ENTITY_OBJECTS}/{body_name}"


# FORCE_FEEDBACK components by name (the suffix of their norm and arrow entities):
# (record field, entity base of its x/y/z scalars).
FEEDBACK_COMPONENTS: Mapping[str, tuple[str, str]] = {
    "device": ("device_f_n", ENTITY_FEEDBACK_DEVICE_F),
    "contact": ("world_f_contact_n", ENTITY_FEEDBACK_CONTACT_F),
    "weight": ("world_f_weight_n", ENTITY_FEEDBACK_WEIGHT_F),
    "obstacle": ("world_f_obstacle_n", ENTITY_FEEDBACK_OBSTACLE_F),
    "workspace": ("device_f_workspace_n", ENTITY_FEEDBACK_WORKSPACE_F),
    "scene": ("world_f_scene_n", ENTITY_FEEDBACK_SCENE_F),
    "limits": ("world_f_limits_n", ENTITY_FEEDBACK_LIMITS_F),
}


def norm_entity(component: str) -> str:
    """Entity of one feedback force's norm, e.g. ``feedback/norm_n/contact``."""
    return f"{ENTITY_FEEDBACK_NORM}/{component}"


def force_arrow_entity(component: str) -> str:
    """Entity of one world-frame force arrow at the tool, e.g. ``world/forces/weight``."""
    return f"{ENTITY_FORCES}/{component}"


# Colour (RGB) of each world-frame force arrow.
FORCE_ARROW_COLORS: Mapping[str, tuple[int, int, int]] = {
    "contact": (230, 60, 60),
    "weight": (60, 120, 230),
    "obstacle": (240, 160, 30),
    "scene": (60, 170, 90),
    "limits": (120, 120, 120),
    "device": (170, 70, 200),  # the total force rendered on the handle, turned into the world
}
