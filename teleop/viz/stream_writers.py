"""The recording's writers, one per family of streams (:class:`teleop.viz.recording.
RecordingWriter` holds them and hands each its streams' records at every flush):

- :class:`ArmWriter`: the arm as the plant and the controller see it (joints, gripper,
  contact and proximity, the controller's status: the desired path's plots in a run that
  follows one, the velocity tracking's in teleoperation);
- :class:`WorldWriter`: the tool and the objects in the world, the tool's trace;
- :class:`SceneWriter`: the model's bodies moved and the ghosts left behind (only where
  the model matches the config: chosen once);
- :class:`TeleopWriter`: the operator's side (handle, hand, force feedback, head);
- :class:`EventLog`: the run's events and the recorder's own lines;
- :class:`TimingWriter`: loop rates, per-hop latency and sequence checks of any stream.

Each logs at the records' own times through :class:`Columns`. Their state is their own;
what one needs of another (the newest tool position for the force arrows, the newest sim
time for a recorder line) it is given at construction.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import rerun as rr

from teleop.bus.messages import DropCounter, Event, Kind, Stage
from teleop.bus.stamps import SeqGaps
from teleop.control.desired_path import DesiredPath
from teleop.control.rate import view_to_world
from teleop.core.config import Config
from teleop.sim.stepping import Abort
from teleop.viz.entities import (
    AXES,
    ENTITY_CONTACT_COUNT,
    ENTITY_CONTACT_FORCE,
    ENTITY_DESIRED_P,
    ENTITY_DESIRED_PATH,
    ENTITY_EVENTS,
    ENTITY_GRIPPER_CMD,
    ENTITY_GRIPPER_OPENING,
    ENTITY_HAND_BUTTONS,
    ENTITY_HAND_TARGET,
    ENTITY_HAPTIC_BUTTONS,
    ENTITY_HAPTIC_F,
    ENTITY_HAPTIC_P,
    ENTITY_HAPTIC_V,
    ENTITY_HMD,
    ENTITY_HMD_FILTERED_P,
    ENTITY_HMD_MEASURED_P,
    ENTITY_HMD_MEASURED_YAW,
    ENTITY_HMD_PREDICTED_YAW,
    ENTITY_JOINT_Q,
    ENTITY_JOINT_QD,
    ENTITY_MANIPULABILITY,
    ENTITY_OBSTACLE_DISTANCE,
    ENTITY_PASSIVITY_DISSIPATED,
    ENTITY_PASSIVITY_OBSERVED,
    ENTITY_PATH_ERROR,
    ENTITY_PATH_S,
    ENTITY_QD_REF,
    ENTITY_RECORDER_EVENTS,
    ENTITY_TELEOP_GRIPPER_CMD,
    ENTITY_TELEOP_HOLDING,
    ENTITY_TELEOP_SPEED_SCALE,
    ENTITY_TELEOP_V_ERROR,
    ENTITY_TELEOP_V_REF,
    ENTITY_TELEOP_V_TOOL,
    ENTITY_TOOL,
    ENTITY_TOOL_P,
    ENTITY_TOOL_TRACE,
    FEEDBACK_COMPONENTS,
    FORCE_ARROW_COLORS,
    TIMELINE_SIM,
    TIMELINE_SOURCE,
    axis_entity,
    force_arrow_entity,
    hop_name,
    joint_entity,
    latency_entity,
    norm_entity,
    object_entity,
    rate_entity,
)
from teleop.viz.recording_file import RootedStream
from teleop.viz.scene3d import SceneModel, ghost_entity, ghost_rgba

# The tool trace keeps one point per this much sim time (ns) ...
TOOL_TRACE_PERIOD_NS = 20_000_000
# ... and at most this many points (10 s of motion at the period above).
TOOL_TRACE_MAX_POINTS = 500
# Length of the axes drawn at the tool and object frames (m).
FRAME_AXIS_LENGTH_M = 0.05
# Force arrows at the tool: drawn length per newton (m/N), so the device's peak force
# (about 8 N) draws a 0.16 m arrow in a workspace of about a metre.
FORCE_ARROW_M_PER_N = 0.02
# Colours of the two series of a "desired vs actual" plot, and of the desired path.
DESIRED_COLOR = (230, 60, 60)
ACTUAL_COLOR = (40, 110, 220)
DESIRED_PATH_POINTS = 720  # points of the static desired path (one period of P(s))
DESIRED_PATH_RADIUS_M = 0.003
NS_PER_MS = 1_000_000
# The HMD frustum: vertical field of view (rad, a typical headset's ~90 degrees), width
# over height, and the distance of the drawn image plane from the eye (m).
HMD_FOV_Y_RAD = math.radians(90.0)
HMD_ASPECT_RATIO = 1.0
HMD_IMAGE_PLANE_M = 0.1
# TextLog level of each run event; the watchdog braking is worth a warning.
LEVEL_INFO = "INFO"  # Rerun TextLog level names
LEVEL_WARN = "WARN"
EVENT_LEVELS: Mapping[Event, str] = {
    Event.STARTED: LEVEL_INFO,
    Event.FINISHED: LEVEL_INFO,
    Event.WATCHDOG_BRAKE: LEVEL_WARN,
    Event.WATCHDOG_RESUME: LEVEL_INFO,
    Event.PROTECTIVE_STOP: LEVEL_WARN,
    Event.PROTECTIVE_RELEASE: LEVEL_INFO,
    Event.UNKNOWN_PEER: LEVEL_WARN,
    Event.GRASP: LEVEL_INFO,
    Event.RELEASE: LEVEL_INFO,
    Event.PHASE: LEVEL_INFO,
    Event.TASK_DONE: LEVEL_INFO,
    Event.RESUMED: LEVEL_WARN,
    Event.ABORTED: LEVEL_WARN,
    Event.STALL: LEVEL_WARN,
    Event.CONTACT: LEVEL_WARN,
    Event.SINGULARITY: LEVEL_WARN,
    Event.OUT_OF_REACH: LEVEL_WARN,
}
# TASK_DONE's value: 1 success, 0 the operator gave up.
TASK_OUTCOMES: Mapping[bool, str] = {True: "success", False: "gave up"}
# ABORTED's value (teleop.sim.stepping.Abort), in words.
ABORT_REASONS: Mapping[int, str] = {
    Abort.RESUME_FAILED: "the restarted plant could not resume its checkpoint",
    Abort.LOCKSTEP_TIMEOUT: "lockstep got no answer within plant.lockstep_timeout_s",
}


def wxyz_to_xyzw(q_wxyz: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) from the wire order (w, x, y, z) to Rerun's (x, y, z, w)."""
    return q_wxyz[..., [1, 2, 3, 0]]


def yaw_pitch_to_xyzw(yaw_rad: np.ndarray, pitch_rad: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4) in Rerun's (x, y, z, w) order of ``Rz(yaw) @ Ry(pitch)``.

    The HMD convention (teleop.devices.hmd): yaw about world z, then pitch about the head's own
    y axis (positive = nose down), so the head's +x is where it looks.
    """
    cy, sy = np.cos(0.5 * yaw_rad), np.sin(0.5 * yaw_rad)
    cp, sp = np.cos(0.5 * pitch_rad), np.sin(0.5 * pitch_rad)
    return np.stack([-sy * sp, cy * sp, sy * cp, cy * cp], axis=-1)


def event_text(event: int, step: int, value: float) -> str:
    """One TextLog line of a RUN_EVENT, e.g. ``WATCHDOG_BRAKE at step 123 (value 0.021)``.

    Events whose value is an index or an outcome say so in words: ``PHASE 3 at step
    1200``, ``TASK_DONE (success) at step 5000``.
    """
    try:
        name = Event(event).name
    except ValueError:  # a newer producer's event: keep the number rather than drop it
        name = f"EVENT_{event}"
    if event == Event.PHASE:
        return f"{name} {round(value)} at step {step}"
    if event == Event.TASK_DONE:
        return f"{name} ({TASK_OUTCOMES[bool(value)]}) at step {step}"
    if event == Event.RESUMED:
        return f"{name} at step {step}: the plant restarted, {round(value)} steps of physics lost"
    if event == Event.ABORTED:
        return f"{name} at step {step}: {ABORT_REASONS.get(round(value), f'reason {value:g}')}"
    text = f"{name} at step {step}"
    return f"{text} (value {value:g})" if value else text


def first_of_buckets(
    sim_time_ns: np.ndarray, period_ns: int, newest: int | None
) -> tuple[np.ndarray, int | None]:
    """Rows that open a new bucket of ``period_ns`` sim time after bucket ``newest``.

    A jump back in sim time (a new run) starts over. Returns the row mask and the
    newest bucket.
    """
    buckets = sim_time_ns // period_ns
    if newest is not None and buckets[0] < newest:
        newest = None
    previous = np.empty_like(buckets)
    previous[0] = -1 if newest is None else newest
    previous[1:] = buckets[:-1]
    return buckets != previous, int(buckets[-1])


class Columns:
    """One robot's rooted stream, sent in columns (``send_columns``: no wall-clock
    ``log_time``) at each record's own times: ``source_time`` always, ``sim_time`` where
    the record has it."""

    def __init__(self, stream: RootedStream, joint_names: Sequence[str]) -> None:
        self.stream = stream
        self.joint_names = joint_names

    @staticmethod
    def indexes(records: np.ndarray, mask: np.ndarray | None = None) -> list[rr.TimeColumn]:
        """The time columns of ``records`` (optionally a row subset): their own times."""
        if mask is not None:
            records = records[mask]
        source = records["t_source_ns"].astype("timedelta64[ns]")
        indexes = [rr.TimeColumn(TIMELINE_SOURCE, duration=source)]
        if "sim_time_ns" in records.dtype.names:
            sim = records["sim_time_ns"].astype("timedelta64[ns]")
            indexes.append(rr.TimeColumn(TIMELINE_SIM, duration=sim))
        return indexes

    def send(self, entity: str, indexes: list[rr.TimeColumn], columns: Any) -> None:
        self.stream.send_columns(entity, indexes=indexes, columns=columns, strict=True)

    def scalars(self, entity: str, indexes: list[rr.TimeColumn], values: np.ndarray) -> None:
        self.send(entity, indexes, rr.Scalars.columns(scalars=np.ascontiguousarray(values)))

    def xyz(self, indexes: list[rr.TimeColumn], base: str, xyz: np.ndarray) -> None:
        for axis, column in zip(AXES, xyz.T, strict=True):
            self.scalars(axis_entity(base, axis), indexes, column)

    def per_joint(self, records: np.ndarray, field: str, base: str) -> None:
        """One scalar series per named joint; rows whose ``n_joints`` excludes it skipped."""
        n_joints = records["n_joints"]
        all_indexes = self.indexes(records)
        values = records[field]
        for j, joint in enumerate(self.joint_names):
            rows = n_joints > j
            if rows.all():
                self.scalars(joint_entity(base, joint), all_indexes, values[:, j])
            elif rows.any():
                indexes = self.indexes(records, rows)
                self.scalars(joint_entity(base, joint), indexes, values[rows, j])

    def at(self, rec: np.ndarray, items: Sequence[tuple[str, Any]]) -> None:
        """Send a few archetypes as one row each at one record's own times (rare rows).

        Each archetype's component batches become one-row columns, so the row carries
        sim_time and source_time only, never the SDK's log_time.
        """
        indexes = self.indexes(rec[np.newaxis])
        for entity, archetype in items:
            columns = [
                batch.partition([len(batch.as_arrow_array())])
                for batch in archetype.as_component_batches()
            ]
            self.send(entity, indexes, columns)

    def static(self, entity: str, archetype: Any) -> None:
        self.stream.log(entity, archetype, static=True)


Write = Callable[[np.ndarray, Columns], None]


class SimClock:
    """The newest sim time the recording has seen (the plant's states), for the lines
    of the recorder's own that carry none."""

    def __init__(self) -> None:
        self.newest_ns = 0


class EventLog:
    """The run's events (every RUN_EVENT stream) and the recorder's own lines: services
    joining or leaving, sequence gaps, drops, buffer overflows, a segment's start."""

    def __init__(self, clock: SimClock, drops: DropCounter) -> None:
        self.clock = clock
        self.drops = drops
        self._lines: list[tuple[int, int, str, str]] = []  # (source ns, sim ns, level, text)
        self._lock = threading.Lock()
        self._seen_drops: dict[tuple[int, str], int] = {}
        self._seen_overflow: dict[str, int] = {}

    def writes(self) -> dict[str, Write]:
        return dict.fromkeys(("plant_events", "operator_events", "controller_events"), self.events)

    def add_line(self, level: str, text: str) -> None:
        """Queue one recorder line, at the recorder's clock and the newest sim time."""
        with self._lock:
            self._lines.append((time.monotonic_ns(), self.clock.newest_ns, level, text))

    def events(self, records: np.ndarray, out: Columns) -> None:
        texts = [event_text(int(r["event"]), int(r["step"]), float(r["value"])) for r in records]
        levels = [EVENT_LEVELS.get(int(e), LEVEL_INFO) for e in records["event"]]
        out.send(ENTITY_EVENTS, out.indexes(records), rr.TextLog.columns(text=texts, level=levels))

    def write_lines(self, overflow: Mapping[str, int], out: Columns) -> None:
        """Queued lines plus new drops (bad records; ``overflow``: records each stream's
        buffer dropped so far) as event-log rows."""
        for (kind, reason), count in self.drops.counts().items():
            new = count - self._seen_drops.get((kind, reason), 0)
            if new > 0:
                self._seen_drops[(kind, reason)] = count
                try:
                    kind_name = Kind(kind).name
                except ValueError:
                    kind_name = f"kind {kind}"
                self.add_line(LEVEL_WARN, f"dropped {new} bad {kind_name} record(s) ({reason})")
        for name, count in overflow.items():
            new = count - self._seen_overflow.get(name, 0)
            if new > 0:
                self._seen_overflow[name] = count
                self.add_line(LEVEL_WARN, f"recorder buffer full: dropped {new} {name} record(s)")
        with self._lock:
            lines, self._lines = self._lines, []
        if not lines:
            return
        source = np.array([line[0] for line in lines], dtype=np.int64)
        sim = np.array([line[1] for line in lines], dtype=np.int64)
        out.send(
            ENTITY_RECORDER_EVENTS,
            [
                rr.TimeColumn(TIMELINE_SOURCE, duration=source.astype("timedelta64[ns]")),
                rr.TimeColumn(TIMELINE_SIM, duration=sim.astype("timedelta64[ns]")),
            ],
            rr.TextLog.columns(text=[line[3] for line in lines], level=[line[2] for line in lines]),
        )


class ArmWriter:
    """The arm as the plant and the controller see it. A run that follows a path
    (``run.follows_path``) plots the desired against the actual tool position; a
    teleoperated one the velocity asked against the tool's."""

    def __init__(self, config: Config, clock: SimClock) -> None:
        self.clock = clock
        self.path = DesiredPath(config.path) if config.run.follows_path else None

    def writes(self) -> dict[str, Write]:
        return {
            "plant_state": self.plant_state,
            "control_status": self.control_status,
            "teleop_status": self.teleop_status,
        }

    def open(self, out: Columns) -> None:
        if self.path is not None:
            s = np.linspace(0.0, self.path.search_window_s, DESIRED_PATH_POINTS)
            points = np.stack([self.path.point(v) for v in s])
            out.static(
                ENTITY_DESIRED_PATH,
                rr.LineStrips3D([points], colors=[DESIRED_COLOR], radii=DESIRED_PATH_RADIUS_M),
            )
            desired, actual = ENTITY_DESIRED_P, ENTITY_TOOL_P
        else:
            desired, actual = ENTITY_TELEOP_V_REF, ENTITY_TELEOP_V_TOOL
        for axis in AXES:
            for base, color, label in (
                (desired, DESIRED_COLOR, "desired"),
                (actual, ACTUAL_COLOR, "actual"),
            ):
                out.static(
                    axis_entity(base, axis),
                    rr.SeriesLines(colors=[color], names=[f"{label} {axis}"]),
                )

    def plant_state(self, records: np.ndarray, out: Columns) -> None:
        out.per_joint(records, "q_rad", ENTITY_JOINT_Q)
        out.per_joint(records, "qd_rad_s", ENTITY_JOINT_QD)
        out.per_joint(records, "qd_ref_applied_rad_s", ENTITY_QD_REF)
        indexes = out.indexes(records)
        out.scalars(ENTITY_GRIPPER_OPENING, indexes, records["gripper_opening_m"])
        out.scalars(ENTITY_GRIPPER_CMD, indexes, records["gripper_cmd_applied"])
        self.clock.newest_ns = int(records["sim_time_ns"][-1])
        self._interaction(records, out)

    @staticmethod
    def _interaction(records: np.ndarray, out: Columns) -> None:
        """Contact and obstacle proximity of the states that computed them (their own
        step): a state between two scene periods only repeats the last values."""
        fresh = records["interaction_step"] == records["step"]
        if not fresh.any():
            return
        rows = records if fresh.all() else records[fresh]
        indexes = out.indexes(rows)
        out.xyz(indexes, ENTITY_CONTACT_FORCE, rows["world_f_contact_n"])
        out.scalars(ENTITY_CONTACT_COUNT, indexes, rows["n_contacts"].astype(float))
        out.scalars(ENTITY_OBSTACLE_DISTANCE, indexes, rows["distance_m"])

    def control_status(self, records: np.ndarray, out: Columns) -> None:
        indexes = out.indexes(records)
        out.scalars(ENTITY_PATH_ERROR, indexes, records["path_error_m"])
        out.scalars(ENTITY_MANIPULABILITY, indexes, records["manipulability"])
        out.scalars(ENTITY_PATH_S, indexes, records["path_s"])
        out.xyz(indexes, ENTITY_DESIRED_P, records["desired_p_m"])
        out.xyz(indexes, ENTITY_TOOL_P, records["tool_p_m"])

    def teleop_status(self, records: np.ndarray, out: Columns) -> None:
        indexes = out.indexes(records)
        v_ref, v_tool = records["world_v_ref_m_s"], records["world_v_tool_m_s"]
        out.xyz(indexes, ENTITY_TELEOP_V_REF, v_ref)
        out.xyz(indexes, ENTITY_TELEOP_V_TOOL, v_tool)
        out.xyz(indexes, ENTITY_TELEOP_V_ERROR, v_ref - v_tool)
        out.scalars(ENTITY_TELEOP_SPEED_SCALE, indexes, records["speed_scale"])
        out.scalars(ENTITY_TELEOP_GRIPPER_CMD, indexes, records["gripper_cmd"])
        out.scalars(ENTITY_TELEOP_HOLDING, indexes, records["holding"].astype(float))


class WorldWriter:
    """The tool and the objects in the world, and the tool's trace (one point per
    TOOL_TRACE_PERIOD_NS of sim time, drawn once per flush)."""

    def __init__(self, config: Config, object_names: Sequence[str]) -> None:
        self.object_names = object_names
        self.tool_p_m: np.ndarray | None = None  # the newest tool position (world)
        self._trace: deque[np.ndarray] = deque(maxlen=TOOL_TRACE_MAX_POINTS)
        self._trace_bucket: int | None = None  # sim-time bucket of the newest trace point

    def writes(self) -> dict[str, Write]:
        return {"tool_pose": self.tool_pose, "objects": self.objects}

    def open(self, out: Columns) -> None:
        # Frames are drawn as axes; these are static and never change during a run.
        for entity in (ENTITY_TOOL, *(object_entity(n) for n in self.object_names)):
            out.static(entity, rr.TransformAxes3D(FRAME_AXIS_LENGTH_M))

    def tool_pose(self, records: np.ndarray, out: Columns) -> None:
        indexes = out.indexes(records)
        world_p_tool_m = records["world_p_tool_m"]
        self.tool_p_m = world_p_tool_m[-1].copy()
        out.send(
            ENTITY_TOOL,
            indexes,
            rr.Transform3D.columns(
                translation=world_p_tool_m,
                quaternion=wxyz_to_xyzw(records["world_q_tool_wxyz"]),
            ),
        )
        self._update_trace(records["sim_time_ns"], world_p_tool_m)
        if len(self._trace) >= 2:
            last = out.indexes(records[-1:])
            strip = np.stack(self._trace)
            out.send(ENTITY_TOOL_TRACE, last, rr.LineStrips3D.columns(strips=[strip]))

    def _update_trace(self, sim_time_ns: np.ndarray, world_p_m: np.ndarray) -> None:
        """Keep the first position of every TOOL_TRACE_PERIOD_NS bucket of sim time.

        Vectorised over the flush; a jump back in sim time (a new run) restarts the
        trace so it never draws a line from one run into the next.
        """
        if (
            self._trace_bucket is not None
            and sim_time_ns[0] // TOOL_TRACE_PERIOD_NS < self._trace_bucket
        ):
            self._trace.clear()
        rows, self._trace_bucket = first_of_buckets(
            sim_time_ns, TOOL_TRACE_PERIOD_NS, self._trace_bucket
        )
        self._trace.extend(world_p_m[rows])

    def objects(self, records: np.ndarray, out: Columns) -> None:
        n_objects = records["n_objects"]
        for i, body in enumerate(self.object_names):
            rows = n_objects > i
            if not rows.any():
                continue
            subset = records[rows]
            out.send(
                object_entity(body),
                out.indexes(subset),
                rr.Transform3D.columns(
                    translation=subset["world_p_m"][:, i],
                    quaternion=wxyz_to_xyzw(subset["world_q_wxyz"][:, i]),
                ),
            )


class SceneWriter:
    """The model's geoms (static), its moving bodies at ``recorder.scene_rate_hz`` of sim
    time and a ghost of the arm every ``recorder.ghost_period_s`` (the paper's
    stroboscopic Fig. 7), from the plant's states."""

    def __init__(self, config: Config, scene: SceneModel) -> None:
        rc = config.recorder
        self.scene = scene
        self._scene_period_ns = round(1e9 / rc.scene_rate_hz)
        self._scene_bucket: int | None = None  # sim-time bucket of the newest scene frame
        self._ghost_period_ns = round(rc.ghost_period_s * 1e9)
        self._ghost_bucket: int | None = None
        self._ghosts = 0
        self._run_duration_ns = round(config.run.duration_s * 1e9)

    def writes(self) -> dict[str, Write]:
        return {"plant_state": self.plant_state}

    def open(self, out: Columns) -> None:
        for entity, archetype in self.scene.static_entities():
            out.static(entity, archetype)

    def plant_state(self, records: np.ndarray, out: Columns) -> None:
        """Move the arm's bodies (scene rate) and leave a ghost every ghost period."""
        sim = records["sim_time_ns"]
        rows, self._scene_bucket = first_of_buckets(sim, self._scene_period_ns, self._scene_bucket)
        if rows.any():
            chosen = records[rows]
            n = int(chosen["n_joints"][0])
            p_m, q_xyzw = self.scene.frames(chosen["q_rad"][:, :n], chosen["gripper_opening_m"])
            indexes = out.indexes(chosen)
            for b, body in enumerate(self.scene.moving_bodies):
                out.send(
                    self.scene.body_entity(body),
                    indexes,
                    rr.Transform3D.columns(translation=p_m[:, b], quaternion=q_xyzw[:, b]),
                )
        ghosts, self._ghost_bucket = first_of_buckets(
            sim, self._ghost_period_ns, self._ghost_bucket
        )
        for rec in records[ghosts]:
            self._ghost(rec, out)

    def _ghost(self, rec: np.ndarray, out: Columns) -> None:
        """One stroboscopic pose: the arm in world-frame primitives at the record's time."""
        n = int(rec["n_joints"])
        fraction = int(rec["sim_time_ns"]) / max(self._run_duration_ns, 1)
        entity = ghost_entity(self._ghosts)
        self._ghosts += 1
        parts = self.scene.ghost(
            rec["q_rad"][:n], float(rec["gripper_opening_m"]), ghost_rgba(fraction)
        )
        out.at(rec, [(f"{entity}/{child}", archetype) for child, archetype in parts])


class TeleopWriter:
    """The operator's side: the handle, the hand's targets, the force fed back (each
    component, and as arrows at the tool, drawn once per flush from the newest record)
    and the head."""

    def __init__(self, config: Config, world: WorldWriter) -> None:
        self.world = world
        self.tick_ns = round(config.tick_s * 1e9)  # HAND_INPUT's sim time
        self._yaw_rad = 0.0  # newest predicted HMD yaw: device frame -> world (feedback)

    def writes(self) -> dict[str, Write]:
        return {
            "haptic_state": self.haptic_state,
            "hand_input": self.hand_input,
            "force_feedback": self.force_feedback,
            "head_pose": self.head_pose,
        }

    def open(self, out: Columns) -> None:
        for component, color in FORCE_ARROW_COLORS.items():
            out.static(norm_entity(component), rr.SeriesLines(colors=[color], names=[component]))
        # The head camera: its frame is the head's (x forward, y left, z up), hence FLU.
        out.static(
            ENTITY_HMD,
            rr.Pinhole(
                fov_y=HMD_FOV_Y_RAD,
                aspect_ratio=HMD_ASPECT_RATIO,
                camera_xyz=rr.ViewCoordinates.FLU,
                image_plane_distance=HMD_IMAGE_PLANE_M,
            ),
        )
        for component, color in FORCE_ARROW_COLORS.items():
            out.static(force_arrow_entity(component), rr.Arrows3D.from_fields(colors=[color]))

    def haptic_state(self, records: np.ndarray, out: Columns) -> None:
        indexes = out.indexes(records)
        out.xyz(indexes, ENTITY_HAPTIC_P, records["device_p_m"])
        out.xyz(indexes, ENTITY_HAPTIC_V, records["device_v_m_s"])
        out.xyz(indexes, ENTITY_HAPTIC_F, records["device_f_n"])
        out.scalars(ENTITY_PASSIVITY_OBSERVED, indexes, records["passivity_observed_j"])
        out.scalars(ENTITY_PASSIVITY_DISSIPATED, indexes, records["passivity_dissipated_j"])
        out.scalars(ENTITY_HAPTIC_BUTTONS, indexes, records["buttons"].astype(float))

    def hand_input(self, records: np.ndarray, out: Columns) -> None:
        """HAND_INPUT has no sim time: it sits at the start of the tick it applies to."""
        indexes = out.indexes(records)
        sim_ns = records["valid_from_tick"].astype(np.int64) * self.tick_ns
        indexes.append(rr.TimeColumn(TIMELINE_SIM, duration=sim_ns.astype("timedelta64[ns]")))
        out.xyz(indexes, ENTITY_HAND_TARGET, records["target_p_m"])
        out.scalars(ENTITY_HAND_BUTTONS, indexes, records["buttons"].astype(float))

    def force_feedback(self, records: np.ndarray, out: Columns) -> None:
        """Every component per sample, then the world-frame ones as arrows at the tool.

        The arrows are one row per flush, from the newest feedback record, drawn from the
        newest tool position: TOOL_POSE comes before FORCE_FEEDBACK in the flush's order,
        so this flush's tool records are already seen. No arrows before the first tool pose.
        """
        indexes = out.indexes(records)
        for component, (field, base) in FEEDBACK_COMPONENTS.items():
            force_n = records[field]
            out.xyz(indexes, base, force_n)
            out.scalars(norm_entity(component), indexes, np.linalg.norm(force_n, axis=1))
        tool_p_m = self.world.tool_p_m
        if tool_p_m is None:
            return
        newest = records[-1:]
        last = out.indexes(newest)
        origin = tool_p_m[np.newaxis]
        for component in FORCE_ARROW_COLORS:
            field, _ = FEEDBACK_COMPONENTS[component]
            force_n = newest[field]
            if component == "device":  # device frame -> world: rotated by the view yaw
                force_n = force_n @ view_to_world(self._yaw_rad).T
            out.send(
                force_arrow_entity(component),
                last,
                rr.Arrows3D.columns(vectors=force_n * FORCE_ARROW_M_PER_N, origins=origin),
            )

    def head_pose(self, records: np.ndarray, out: Columns) -> None:
        indexes = out.indexes(records)
        self._yaw_rad = float(records["predicted_yaw_rad"][-1])
        out.scalars(ENTITY_HMD_MEASURED_YAW, indexes, records["measured_yaw_rad"])
        out.scalars(ENTITY_HMD_PREDICTED_YAW, indexes, records["predicted_yaw_rad"])
        out.xyz(indexes, ENTITY_HMD_FILTERED_P, records["filtered_p_m"])
        out.xyz(indexes, ENTITY_HMD_MEASURED_P, records["measured_p_m"])
        out.send(
            ENTITY_HMD,
            indexes,
            rr.Transform3D.columns(
                translation=records["predicted_p_m"],
                quaternion=yaw_pitch_to_xyzw(
                    records["predicted_yaw_rad"], records["predicted_pitch_rad"]
                ),
            ),
        )


class TimingWriter:
    """Derived series of any stream with the common header (t_source_ns, seq, trace_ns):
    the latency of each hop between two of its stamps; for a periodic stream its loop
    rate (records per second of the producer's clock, once per ``recorder.rate_window_s``)
    and, where its seq goes up by one per record, its gaps and restarts (the bus layer's
    rule, :class:`teleop.bus.stamps.SeqGaps`) as lines of the event log."""

    def __init__(
        self,
        config: Config,
        events: EventLog,
        periodic: frozenset[str],
        seq_checked: frozenset[str],
    ) -> None:
        self.events = events
        self.periodic, self.seq_checked = periodic, seq_checked
        self._rate_window_ns = round(config.recorder.rate_window_s * 1e9)
        # Per stream: [window start ns, records counted]; and the newest record counted.
        self._rate_windows: dict[str, list[int]] = {}
        self._rate_last: dict[str, np.ndarray] = {}
        self._seq_gaps: dict[str, SeqGaps] = {}  # per stream: its seq gaps and restarts
        self._hops: dict[str, list[tuple[Stage, Stage]]] = {}  # per stream, column order
        self._chain_stages: dict[str, set[Stage]] = {}  # per stream: stages seen so far

    def write(self, name: str, records: np.ndarray, out: Columns) -> None:
        """Latency, rate and seq of one stream's flushed records (a stream buffered in
        another form is skipped)."""
        fields = getattr(records.dtype, "names", None) or ()
        if not {"t_source_ns", "seq", "trace_ns"} <= set(fields):
            return
        self._latency(name, records, out)
        if name not in self.periodic:
            return
        self._rate(name, records, out)
        if name in self.seq_checked:
            self._check_seq(name, records["seq"].astype(np.int64))

    def streams_with_windows(self) -> list[str]:
        return list(self._rate_windows)

    def _rate(self, name: str, records: np.ndarray, out: Columns) -> None:
        """The window starts at a record's t_source_ns and counts the records after it; a
        row is logged at the time of the record that closes the window."""
        source = records["t_source_ns"]
        window = self._rate_windows.get(name)
        if window is None:  # the first record opens the first window
            window = self._rate_windows[name] = [int(source[0]), 0]
            source = source[1:]
            records = records[1:]
        window[1] += int(source.size)
        if source.size == 0:
            return
        self._rate_last[name] = records[-1:].copy()
        if int(source[-1]) - window[0] >= self._rate_window_ns:
            self.close_rate_window(name, out)

    def close_rate_window(self, name: str, out: Columns) -> None:
        """Log the rate of the stream's open window (if it counted any record), restart it."""
        window, last = self._rate_windows[name], self._rate_last.get(name)
        if last is None or window[1] == 0:
            return
        end_ns = int(last["t_source_ns"][0])
        if end_ns > window[0]:
            rate_hz = window[1] / ((end_ns - window[0]) * 1e-9)
            out.scalars(rate_entity(name), out.indexes(last), np.array([rate_hz]))
        window[0], window[1] = end_ns, 0

    def _hop_chain(self, name: str, trace: np.ndarray, out: Columns) -> list[tuple[Stage, Stage]]:
        """The hops of a stream: pairs of stages its records stamp, consecutive in time.

        A record copies the stamps of the records it answers, possibly from earlier
        cycles, so the order is taken from the data (the stamps of the batch's record
        that has the most of them), not from the Stage values. The list only grows (a
        stage that shows up later adds hops at its end), so each hop keeps its column of
        the stream's latency entity.
        """
        present = {
            stage for stage in Stage if stage < trace.shape[1] and (trace[:, stage] > 0).any()
        }
        hops = self._hops.setdefault(name, [])
        if not present <= self._chain_stages.get(name, set()):
            self._chain_stages[name] = present | self._chain_stages.get(name, set())
            # Order by the stamps of one record that has the most of them (stamps of
            # different records are not comparable: a batch starts before commands flow).
            stages = sorted(present)
            counts = (trace[:, stages] > 0).sum(axis=1)
            fullest = trace[int(np.flatnonzero(counts == counts.max())[-1])]
            order = {
                s: float(fullest[s])
                if fullest[s] > 0
                else float(np.median(trace[trace[:, s] > 0, s]))
                for s in present
            }
            chain = sorted(present, key=lambda s: (order[s], s))
            new = [hop for hop in zip(chain, chain[1:], strict=False) if hop not in hops]
            if new:
                hops.extend(new)
                out.static(
                    latency_entity(name),
                    rr.SeriesLines(names=[hop_name(a, b) for a, b in hops]),
                )
        return hops

    def _latency(self, name: str, records: np.ndarray, out: Columns) -> None:
        """Every hop of the stream's records in one multi-series entity, in ms.

        ``latency/<stream>`` holds one scalar per hop (column order: :meth:`_hop_chain`,
        names in its SeriesLines), so a 1 kHz stream costs one Rerun call per flush.
        A hop whose stamps are unset, or whose later stamp is older (copied from another
        cycle), is NaN in that row. Streams that copy the stamps of the records they
        answer show the same hop as each of them sees it.
        """
        trace = records["trace_ns"]
        hops = self._hop_chain(name, trace, out)
        if not hops:
            return
        first = trace[:, [a for a, _ in hops]]
        second = trace[:, [b for _, b in hops]]
        hop_ms = (second - first) / NS_PER_MS
        hop_ms[(first <= 0) | (second <= 0) | (second < first)] = np.nan
        rows = ~np.isnan(hop_ms).all(axis=1)
        if rows.any():
            out.send(
                latency_entity(name),
                out.indexes(records, rows),
                rr.Scalars.columns(scalars=np.ascontiguousarray(hop_ms[rows])),
            )

    def _check_seq(self, name: str, seq: np.ndarray) -> None:
        missing, restarts = self._seq_gaps.setdefault(name, SeqGaps()).add_batch(seq)
        if missing:
            self.events.add_line(LEVEL_WARN, f"{name}: {missing} record(s) missing (seq gaps)")
        if restarts:
            self.events.add_line(
                LEVEL_INFO,
                f"{name}: seq started over {restarts} time(s) (producer restart or new run)",
            )
