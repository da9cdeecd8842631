"""The recording: every stream of a robot, logged to Rerun in columns.

The bus callbacks (services/recorder.py) only copy the record's bytes into a bounded
per-stream buffer; the recorder's thread swaps the buffers every
``recorder.flush_every_s`` and sends each stream to Rerun with ``send_columns`` (one
call per entity per flush, never one per sample), so a 1 kHz stream costs a few Rerun
calls per flush, not a thousand.

Every sample is logged at its own time, never at its arrival time:

- ``sim_time`` (duration): the record's ``sim_time_ns`` (plant simulation time), for
  every kind that carries it (all but HAND_INPUT); HAND_INPUT is
  logged at the start of the tick it applies to, ``valid_from_tick * Config.tick_s``;
- ``source_time`` (duration): the header's ``t_source_ns``, the producer's monotonic
  clock, for every record.

A few entities are drawn once per flush from the newest sample instead of per sample:
the tool trace and the force arrows at the tool (a 3D view only shows the latest
value anyway, and re-logging them at 1 kHz would cost a Rerun row per sample).

The 3D scene comes from the MuJoCo model itself (teleop.viz.scene3d): every visual geom is
logged once as static, and the arm's bodies move by transforms computed with
``mj_kinematics`` from PLANT_STATE, at ``recorder.scene_rate_hz`` of sim time (each at
the sim time of the plant state it was computed from). Every ``recorder.ghost_period_s``
a ghost of the arm is left behind (the paper's stroboscopic Fig. 7).

Derived series, per flush and per stream: the loop rate (records per second of the
producer's clock) and the latency of each hop between two stamps of the header's
``trace_ns`` (named by :class:`~teleop.bus.messages.Stage`). Sequence gaps and restarts,
dropped records and services leaving or joining the bus go to the event log.

The blueprint (teleop.viz.blueprint) is sent with the recording.

The entity paths below are an API: the blueprint and the tests look them up by name.
"""

from __future__ import annotations

import io
import json
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import PIL.Image
import rerun as rr

from teleop.bus import graph
from teleop.bus.messages import (
    EYE_VIEW,
    MAX_JOINTS,
    MAX_OBJECTS,
    DropCounter,
    Event,
    FrameSchema,
    Kind,
    Schema,
    Stage,
)
from teleop.bus.stamps import SeqGaps
from teleop.control.path import DesiredPath
from teleop.control.rate import view_to_world
from teleop.core.config import Config, ModelError
from teleop.sim.stepping import Abort
from teleop.viz.entities import (
    AXES,
    ENTITY_CONTACT_COUNT,
    ENTITY_CONTACT_FORCE,
    ENTITY_DESIRED_P,
    ENTITY_DESIRED_PATH,
    ENTITY_EVENTS,
    ENTITY_EYE_VIEW,
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
    ENTITY_OBJECTS,
    ENTITY_OBSTACLE_DISTANCE,
    ENTITY_PASSIVITY_DISSIPATED,
    ENTITY_PASSIVITY_OBSERVED,
    ENTITY_PATH_ERROR,
    ENTITY_PATH_S,
    ENTITY_QD_REF,
    ENTITY_RECORDER_EVENTS,
    ENTITY_STATS,
    ENTITY_TELEOP_GRIPPER_CMD,
    ENTITY_TELEOP_HOLDING,
    ENTITY_TELEOP_SPEED_SCALE,
    ENTITY_TELEOP_V_ERROR,
    ENTITY_TELEOP_V_REF,
    ENTITY_TELEOP_V_TOOL,
    ENTITY_TOOL,
    ENTITY_TOOL_P,
    ENTITY_TOOL_TRACE,
    ENTITY_WORLD,
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
from teleop.viz.recording_file import RecordingFile, RootedStream
from teleop.viz.scene3d import SceneModel, ghost_entity, ghost_rgba

logger = logging.getLogger(__name__)

# --- Tuning -------------------------------------------------------------------------------
# Per-stream buffer bound (records): 20 s of a 1 kHz stream, about 6 MB of PLANT_STATE.
# A flush that falls further behind drops the oldest records and counts them.
BUFFER_CAPACITY_RECORDS = 20_000
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
NS_PER_MS = 1e6
# The HMD frustum: vertical field of view (rad, a typical headset's ~90 degrees), width
# over height, and the distance of the drawn image plane from the eye (m).
HMD_FOV_Y_RAD = math.radians(90.0)
HMD_ASPECT_RATIO = 1.0
HMD_IMAGE_PLANE_M = 0.1
# Eye-view frames buffered between flushes (at 5-10 Hz and 0.1 s flushes about 1 is
# waiting); beyond this the oldest is dropped and counted, so memory stays bounded.
EYE_VIEW_BUFFER_FRAMES = 32
# Latency samples kept per hop for the eye-view percentiles (the newest ones).
EYE_VIEW_LATENCY_SAMPLES = 100_000
NS_PER_MS = 1_000_000
JPEG_MEDIA_TYPE = "image/jpeg"
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

# The record streams the recorder takes (teleop.bus.graph: it is among their consumers;
# image frames come on a subscription of their own), in the graph's order.
_RECORDED = [
    s for s in graph.STREAMS if "recorder" in s.consumers and not isinstance(s.schema, FrameSchema)
]
# Every stream logged, by name (a Topics attribute, and the key of the per-stream counters in
# the summary), with its schema: a batched copy is logged under the stream it copies.
STREAM_SCHEMAS: Mapping[str, Schema] = {s.batch_of or s.name: s.schema for s in _RECORDED}
# Streams the recorder takes from their observers' copy: stream name -> name of the copy.
BATCHED_STREAMS: Mapping[str, str] = {s.batch_of: s.name for s in _RECORDED if s.batch_of}
# Periodic streams: their loop rate is logged and their seq checked for gaps and restarts.
PERIODIC_STREAMS = frozenset(n for n in STREAM_SCHEMAS if graph.stream(n).periodic)
# Of those, the streams whose seq goes up by one per record (not a cycle counter).
SEQ_CHECKED_STREAMS = frozenset(n for n in PERIODIC_STREAMS if graph.stream(n).seq_per_record)


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


class StreamBuffer:
    """Bounded FIFO of one stream's records, filled by a Zenoh callback.

    The callback copies the record's bytes (``tobytes``: the received record is a
    read-only view) and appends under the shared lock, nothing more. ``take`` swaps the
    FIFO out and turns it into one structured array of shape (N,) with a single
    ``frombuffer``, ready for column slicing. When full, the oldest record is dropped
    and counted, so memory stays bounded if flushing falls behind.
    """

    def __init__(self, schema: Schema, capacity: int, cond: threading.Condition) -> None:
        if capacity <= 0:
            raise ValueError("StreamBuffer capacity must be positive")
        self.schema = schema
        self.capacity = capacity
        self._cond = cond
        self._items: deque[bytes] = deque(maxlen=capacity)
        self.received = 0  # records handed to the callback since creation
        self.overflow = 0  # records dropped because the buffer was full

    def __call__(self, rec: np.ndarray, rx_ns: int) -> None:
        data = rec.tobytes()
        with self._cond:
            if len(self._items) == self.capacity:
                self.overflow += 1
            self._items.append(data)
            self.received += 1
            self._cond.notify_all()

    def take(self) -> np.ndarray:
        """Every buffered record, oldest first, as a read-only (N,) structured array."""
        with self._cond:
            items = self._items
            self._items = deque(maxlen=self.capacity)
        return np.frombuffer(b"".join(items), dtype=self.schema.dtype)


class EyeViewFrames:
    """The recorder's eye-view handler: buffers EYE_VIEW frames, logs them as images.

    The Zenoh callback copies the frame (record and pixels) into a small bounded FIFO,
    counts whether it came over shared memory, and keeps the latency of each hop of the
    chain (HMD sample -> render start -> render end -> publish -> received here), all
    monotonic-clock stamps of this host. :meth:`write` logs each frame at its own
    ``sim_time`` (the state it shows) and ``source_time`` (render start), JPEG-encoded
    with ``jpeg_quality`` (0: raw RGB): a JPEG frame takes a fraction of a raw one's
    room in the .rrd, and the eye view needs no more than a person's look at it.
    """

    HOPS = ("hmd_to_received", "hmd_to_publish", "render", "publish_to_received")

    def __init__(self, jpeg_quality: int, cond: threading.Condition) -> None:
        self.jpeg_quality = jpeg_quality
        self._cond = cond
        self._frames: deque[tuple[bytes, np.ndarray]] = deque(maxlen=EYE_VIEW_BUFFER_FRAMES)
        self._latency_ns = {hop: deque(maxlen=EYE_VIEW_LATENCY_SAMPLES) for hop in self.HOPS}
        self.received = 0
        self.received_shm = 0
        self.overflow = 0
        self.logged = 0
        self.logged_bytes = 0  # image bytes handed to Rerun (JPEG or raw RGB)

    def __call__(self, rec: np.ndarray, pixels: np.ndarray, rx_ns: int, via_shm: bool) -> None:
        frame = (rec.tobytes(), pixels.copy())
        with self._cond:
            if len(self._frames) == self._frames.maxlen:
                self.overflow += 1
            self._frames.append(frame)
            self.received += 1
            self.received_shm += int(via_shm)
            latency = self._latency_ns
            head_ns = int(rec["head_t_source_ns"])
            if head_ns:
                latency["hmd_to_received"].append(rx_ns - head_ns)
                latency["hmd_to_publish"].append(int(rec["publish_ns"]) - head_ns)
            latency["render"].append(int(rec["render_end_ns"]) - int(rec["render_start_ns"]))
            latency["publish_to_received"].append(rx_ns - int(rec["publish_ns"]))
            self._cond.notify_all()

    def write(self, stream: RootedStream) -> None:
        """Log every buffered frame at its own times: one ``send_columns`` per flush.

        (``send_columns`` rather than ``log``: no wall-clock ``log_time`` column, like
        every other stream of the recording.)
        """
        with self._cond:
            frames = list(self._frames)
            self._frames.clear()
        if not frames:
            return
        records = np.frombuffer(b"".join(data for data, _ in frames), dtype=EYE_VIEW.dtype)
        indexes = [
            rr.TimeColumn(
                TIMELINE_SOURCE, duration=records["t_source_ns"].astype("timedelta64[ns]")
            ),
            rr.TimeColumn(TIMELINE_SIM, duration=records["sim_time_ns"].astype("timedelta64[ns]")),
        ]
        if self.jpeg_quality:
            blobs = [self._jpeg(pixels) for _, pixels in frames]
            columns = rr.EncodedImage.columns(blob=blobs, media_type=[JPEG_MEDIA_TYPE] * len(blobs))
            self.logged_bytes += sum(len(b) for b in blobs)
        else:
            formats = [
                rr.components.ImageFormat(
                    p.shape[1], p.shape[0], color_model="RGB", channel_datatype="U8"
                )
                for _, p in frames
            ]
            columns = rr.Image.columns(buffer=[p.tobytes() for _, p in frames], format=formats)
            self.logged_bytes += sum(p.nbytes for _, p in frames)
        stream.send_columns(ENTITY_EYE_VIEW, indexes=indexes, columns=columns, strict=True)
        self.logged += len(frames)

    def _jpeg(self, pixels: np.ndarray) -> bytes:
        out = io.BytesIO()
        PIL.Image.fromarray(pixels).save(out, format="JPEG", quality=self.jpeg_quality)
        return out.getvalue()

    def stats(self) -> dict[str, Any]:
        """Frames received (and over SHM), dropped, logged; per-hop latency in ms."""
        with self._cond:
            latency = {hop: np.array(v, dtype=np.int64) for hop, v in self._latency_ns.items()}
            out: dict[str, Any] = {
                "received": self.received,
                "received_shm": self.received_shm,
                "overflow_drops": self.overflow,
                "logged": self.logged,
                "logged_bytes_per_frame": self.logged_bytes / self.logged if self.logged else 0.0,
            }
        for hop, values in latency.items():
            p50, p99 = np.percentile(values, [50, 99]) / NS_PER_MS if values.size else (0, 0)
            out[f"{hop}_ms"] = {"count": int(values.size), "p50": float(p50), "p99": float(p99)}
        return out


class RecordingWriter:
    """Every stream of one robot, buffered as it arrives and logged to the run's
    recording (a :class:`~teleop.viz.recording_file.RecordingFile`), under the robot's
    entity ``root``.

    Bus callbacks feed :attr:`buffers` (one per stream, a :class:`StreamBuffer` is a
    record callback) and :attr:`eye_view`; :meth:`flush` logs what they hold; ``drops``
    is the receiver's count of bad records (for the event log). The file is opened
    before :meth:`open` and closed after :meth:`close`, by its owner.
    """

    def __init__(
        self,
        config: Config,
        file: RecordingFile,
        drops: DropCounter,
        *,
        root: str = "",
        buffer_capacity: int = BUFFER_CAPACITY_RECORDS,
    ) -> None:
        self.config = config
        self.file = file
        self.segment = file.segment
        self.rrd_path = file.rrd_path
        self.root = root
        self.drops = drops
        self._cond = threading.Condition()
        self.buffers = {
            name: StreamBuffer(schema, buffer_capacity, self._cond)
            for name, schema in STREAM_SCHEMAS.items()
        }
        self.eye_view = EyeViewFrames(config.eyeview.jpeg_quality, self._cond)
        self._writers: Mapping[str, Callable[[np.ndarray], None]] = {
            "plant_state": self._write_plant_state,
            "tool_pose": self._write_tool_pose,
            "objects": self._write_objects,
            "control_status": self._write_control_status,
            "plant_events": self._write_events,
            "operator_events": self._write_events,
            "controller_events": self._write_events,
            "haptic_state": self._write_haptic_state,
            "hand_input": self._write_hand_input,
            "force_feedback": self._write_force_feedback,
            "head_pose": self._write_head_pose,
            "teleop_status": self._write_teleop_status,
        }
        self._joint_names: Sequence[str] = config.robot.arm_joints[:MAX_JOINTS]
        self._object_names: Sequence[str] = config.robot.object_bodies[:MAX_OBJECTS]
        self._rec: RootedStream | None = None
        self._logged = dict.fromkeys(STREAM_SCHEMAS, 0)
        self._flushes = 0
        self._flush_wall_s_max = 0.0
        self._flush_wall_s_total = 0.0
        self._rerun_errors = 0
        self._rerun_error_logged: set[str] = set()
        self._trace: deque[np.ndarray] = deque(maxlen=TOOL_TRACE_MAX_POINTS)
        self._trace_bucket: int | None = None  # sim-time bucket of the newest trace point
        self._timestep_ns = round(config.tick_s * 1e9)  # plant tick (HAND_INPUT)
        self._tool_p_m: np.ndarray | None = None  # newest tool position (world), for arrows
        self._cpu_start_s = time.process_time()
        self._wall_start_ns = time.monotonic_ns()
        self._init_observers(config)

    def _init_observers(self, config: Config) -> None:
        """State of the 3D scene, the ghosts and the derived timing series."""
        rc = config.recorder
        self._scene: SceneModel | None = None
        if rc.scene3d:
            try:
                self._scene = SceneModel(config, ENTITY_OBJECTS)
            except (ModelError, ValueError) as exc:  # the recording goes on without the scene
                logger.warning("no 3D scene: the model does not match the config (%s)", exc)
        self._scene_period_ns = round(1e9 / rc.scene_rate_hz)
        self._scene_bucket: int | None = None  # sim-time bucket of the newest scene frame
        self._ghost_period_ns = round(rc.ghost_period_s * 1e9)
        self._ghost_bucket: int | None = None
        self._ghosts = 0
        self._run_duration_ns = round(config.run.duration_s * 1e9)
        self._yaw_rad = 0.0  # newest predicted HMD yaw: device frame -> world (feedback)
        self._sim_time_ns = 0  # newest sim time seen, for events that carry none
        self._segment_announced = True  # a later segment's start is in the event log
        self._rate_window_ns = round(rc.rate_window_s * 1e9)
        # Per stream: [window start ns, records counted]; and the newest record counted.
        self._rate_windows: dict[str, list[int]] = {}
        self._rate_last: dict[str, np.ndarray] = {}
        self._seq_gaps: dict[str, SeqGaps] = {}  # per stream: its seq gaps and restarts
        self._hops: dict[str, list[tuple[Stage, Stage]]] = {}  # per stream, column order
        self._chain_stages: dict[str, set[Stage]] = {}  # per stream: stages seen so far
        self._seen_drops: dict[tuple[int, str], int] = {}
        self._seen_overflow = dict.fromkeys(STREAM_SCHEMAS, 0)
        self._lines: list[tuple[int, int, str, str]] = []  # (source ns, sim ns, level, text)
        self._lines_lock = threading.Lock()

    # -- lifecycle ---------------------------------------------------------------------
    def open(self) -> None:
        """Log this robot's static entities (the scene, frames, plot styles) into the
        open file."""
        self._rec = rec = self.file.stream(self.root)
        # A later segment says so in the event log, at the sim time of its first states.
        self._segment_announced = self.segment.index == 0
        self._log_static_scene(rec)
        # Frames are drawn as axes; these are static and never change during a run.
        for entity in (ENTITY_TOOL, *(object_entity(n) for n in self._object_names)):
            rec.log(entity, rr.TransformAxes3D(FRAME_AXIS_LENGTH_M), static=True)
        # The head camera: its frame is the head's (x forward, y left, z up), hence FLU.
        rec.log(
            ENTITY_HMD,
            rr.Pinhole(
                fov_y=HMD_FOV_Y_RAD,
                aspect_ratio=HMD_ASPECT_RATIO,
                camera_xyz=rr.ViewCoordinates.FLU,
                image_plane_distance=HMD_IMAGE_PLANE_M,
            ),
            static=True,
        )
        for component, color in FORCE_ARROW_COLORS.items():
            rec.log(
                force_arrow_entity(component),
                rr.Arrows3D.from_fields(colors=[color]),
                static=True,
            )

    def _log_static_scene(self, rec: RootedStream) -> None:
        """World axes, the model's geoms, the desired path and the plot series' styles."""
        rec.log(ENTITY_WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if self._scene is not None:
            for entity, archetype in self._scene.static_entities():
                rec.log(entity, archetype, static=True)
        if self.config.run.follows_path:
            path = DesiredPath(self.config.path)
            s = np.linspace(0.0, path.search_window_s, DESIRED_PATH_POINTS)
            points = np.stack([path.point(v) for v in s])
            rec.log(
                ENTITY_DESIRED_PATH,
                rr.LineStrips3D([points], colors=[DESIRED_COLOR], radii=DESIRED_PATH_RADIUS_M),
                static=True,
            )
        if self.config.run.follows_path:
            desired, actual = ENTITY_DESIRED_P, ENTITY_TOOL_P
        else:
            desired, actual = ENTITY_TELEOP_V_REF, ENTITY_TELEOP_V_TOOL
        for axis in AXES:
            for base, color, label in (
                (desired, DESIRED_COLOR, "desired"),
                (actual, ACTUAL_COLOR, "actual"),
            ):
                rec.log(
                    axis_entity(base, axis),
                    rr.SeriesLines(colors=[color], names=[f"{label} {axis}"]),
                    static=True,
                )
        for component, color in FORCE_ARROW_COLORS.items():
            rec.log(
                norm_entity(component),
                rr.SeriesLines(colors=[color], names=[component]),
                static=True,
            )

    def add_line(self, level: str, text: str) -> None:
        """Queue one recorder event line, at the recorder's clock and the newest sim time."""
        with self._lines_lock:
            self._lines.append((time.monotonic_ns(), self._sim_time_ns, level, text))

    def close(self) -> None:
        """Log what is left and the stats (the file stays open for its owner to close).
        Safe to call twice."""
        if self._rec is None:
            return
        self.flush()
        for name in list(self._rate_windows):  # a run shorter than a window still gets one
            self._guarded(name, self._close_rate_window, name)
        self._rec.log(
            ENTITY_STATS,
            rr.TextDocument(json.dumps(self.stats(), indent=2), media_type="text/markdown"),
            static=True,
        )
        self._rec = None

    # -- flushing ----------------------------------------------------------------------
    def flush(self) -> None:
        """Send every buffered record to Rerun, one ``send_columns`` per entity.

        A Rerun error on one stream is counted and logged once per stream; the other
        streams and later flushes go on.
        """
        if self._rec is None:
            return
        start_ns = time.monotonic_ns()
        for name, buffer in self.buffers.items():
            records = buffer.take()
            if records.size == 0:
                continue
            if not self._guarded(name, self._writers[name], records):
                continue
            self._logged[name] += int(records.size)
            self._guarded(f"{name} timing", self._write_timing, name, records)
        if not self._segment_announced and self._sim_time_ns > 0:
            self._segment_announced = True
            self.add_line(
                LEVEL_WARN,
                f"recorder restarted: segment {self.segment.index} ({self.rrd_path.name}) "
                "begins; nothing was recorded since the previous segment's end",
            )
        self._guarded("events", self._write_recorder_events)
        self._guarded("eye_view", self.eye_view.write, self._rec)
        elapsed_s = (time.monotonic_ns() - start_ns) * 1e-9
        self._flush_wall_s_max = max(self._flush_wall_s_max, elapsed_s)
        self._flush_wall_s_total += elapsed_s
        with self._cond:
            self._flushes += 1
            self._cond.notify_all()

    def _guarded(self, what: str, write: Callable[..., None], *args: Any) -> bool:
        """Run one writer; a Rerun error is counted, logged once per ``what``, and
        swallowed so the other streams and later flushes go on. True on success."""
        try:
            write(*args)
        except Exception as exc:  # Rerun raises assorted types (ValueError, arrow errors)
            self._rerun_errors += 1
            if what not in self._rerun_error_logged:
                self._rerun_error_logged.add(what)
                logger.warning("Rerun rejected %s (%s); further errors only counted", what, exc)
            return False
        return True

    def _send(self, entity: str, indexes: list[rr.TimeColumn], columns: Any) -> None:
        assert self._rec is not None
        self._rec.send_columns(entity, indexes=indexes, columns=columns, strict=True)

    def _send_scalars(self, entity: str, indexes: list[rr.TimeColumn], values: np.ndarray) -> None:
        self._send(entity, indexes, rr.Scalars.columns(scalars=np.ascontiguousarray(values)))

    @staticmethod
    def _indexes(records: np.ndarray, mask: np.ndarray | None = None) -> list[rr.TimeColumn]:
        """The time columns of ``records`` (optionally a row subset): their own times."""
        if mask is not None:
            records = records[mask]
        source = records["t_source_ns"].astype("timedelta64[ns]")
        indexes = [rr.TimeColumn(TIMELINE_SOURCE, duration=source)]
        if "sim_time_ns" in records.dtype.names:
            sim = records["sim_time_ns"].astype("timedelta64[ns]")
            indexes.append(rr.TimeColumn(TIMELINE_SIM, duration=sim))
        return indexes

    def _send_per_joint(self, records: np.ndarray, field: str, base: str) -> None:
        """One scalar series per named joint; rows whose ``n_joints`` excludes it skipped."""
        n_joints = records["n_joints"]
        all_indexes = self._indexes(records)
        values = records[field]
        for j, joint in enumerate(self._joint_names):
            rows = n_joints > j
            if rows.all():
                self._send_scalars(joint_entity(base, joint), all_indexes, values[:, j])
            elif rows.any():
                indexes = self._indexes(records, rows)
                self._send_scalars(joint_entity(base, joint), indexes, values[rows, j])

    def _send_xyz(self, indexes: list[rr.TimeColumn], base: str, xyz: np.ndarray) -> None:
        for axis, column in zip(AXES, xyz.T, strict=True):
            self._send_scalars(axis_entity(base, axis), indexes, column)

    def _write_plant_state(self, records: np.ndarray) -> None:
        self._send_per_joint(records, "q_rad", ENTITY_JOINT_Q)
        self._send_per_joint(records, "qd_rad_s", ENTITY_JOINT_QD)
        self._send_per_joint(records, "qd_ref_applied_rad_s", ENTITY_QD_REF)
        indexes = self._indexes(records)
        self._send_scalars(ENTITY_GRIPPER_OPENING, indexes, records["gripper_opening_m"])
        self._send_scalars(ENTITY_GRIPPER_CMD, indexes, records["gripper_cmd_applied"])
        self._sim_time_ns = int(records["sim_time_ns"][-1])
        self._write_interaction(records)
        if self._scene is not None:
            self._write_scene(records)

    def _write_interaction(self, records: np.ndarray) -> None:
        """Contact and obstacle proximity of the states that computed them (their own
        step): a state between two scene periods only repeats the last values."""
        fresh = records["interaction_step"] == records["step"]
        if not fresh.any():
            return
        rows = records if fresh.all() else records[fresh]
        indexes = self._indexes(rows)
        self._send_xyz(indexes, ENTITY_CONTACT_FORCE, rows["world_f_contact_n"])
        self._send_scalars(ENTITY_CONTACT_COUNT, indexes, rows["n_contacts"].astype(float))
        self._send_scalars(ENTITY_OBSTACLE_DISTANCE, indexes, rows["distance_m"])

    @staticmethod
    def _first_of_buckets(
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

    def _write_scene(self, records: np.ndarray) -> None:
        """Move the arm's bodies (scene rate) and leave a ghost every ghost period."""
        assert self._scene is not None
        sim = records["sim_time_ns"]
        rows, self._scene_bucket = self._first_of_buckets(
            sim, self._scene_period_ns, self._scene_bucket
        )
        if rows.any():
            chosen = records[rows]
            n = int(chosen["n_joints"][0])
            p_m, q_xyzw = self._scene.frames(chosen["q_rad"][:, :n], chosen["gripper_opening_m"])
            indexes = self._indexes(chosen)
            for b, body in enumerate(self._scene.moving_bodies):
                self._send(
                    self._scene.body_entity(body),
                    indexes,
                    rr.Transform3D.columns(translation=p_m[:, b], quaternion=q_xyzw[:, b]),
                )
        ghosts, self._ghost_bucket = self._first_of_buckets(
            sim, self._ghost_period_ns, self._ghost_bucket
        )
        for rec in records[ghosts]:
            self._write_ghost(rec)

    def _write_ghost(self, rec: np.ndarray) -> None:
        """One stroboscopic pose: the arm in world-frame primitives at the record's time."""
        assert self._scene is not None and self._rec is not None
        n = int(rec["n_joints"])
        fraction = int(rec["sim_time_ns"]) / max(self._run_duration_ns, 1)
        entity = ghost_entity(self._ghosts)
        self._ghosts += 1
        parts = self._scene.ghost(
            rec["q_rad"][:n], float(rec["gripper_opening_m"]), ghost_rgba(fraction)
        )
        self._log_at(rec, [(f"{entity}/{child}", archetype) for child, archetype in parts])

    def _log_at(self, rec: np.ndarray, items: Sequence[tuple[str, Any]]) -> None:
        """Send a few archetypes as one row each at one record's own times (rare rows).

        Each archetype's component batches become one-row columns, so the row carries
        sim_time and source_time only, never the SDK's log_time.
        """
        indexes = self._indexes(rec[np.newaxis])
        for entity, archetype in items:
            columns = [
                batch.partition([len(batch.as_arrow_array())])
                for batch in archetype.as_component_batches()
            ]
            self._send(entity, indexes, columns)

    def _write_tool_pose(self, records: np.ndarray) -> None:
        indexes = self._indexes(records)
        world_p_tool_m = records["world_p_tool_m"]
        self._tool_p_m = world_p_tool_m[-1].copy()
        self._send(
            ENTITY_TOOL,
            indexes,
            rr.Transform3D.columns(
                translation=world_p_tool_m,
                quaternion=wxyz_to_xyzw(records["world_q_tool_wxyz"]),
            ),
        )
        self._update_trace(records["sim_time_ns"], world_p_tool_m)
        if len(self._trace) >= 2:
            last = self._indexes(records[-1:])
            strip = np.stack(self._trace)
            self._send(ENTITY_TOOL_TRACE, last, rr.LineStrips3D.columns(strips=[strip]))

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
        rows, self._trace_bucket = self._first_of_buckets(
            sim_time_ns, TOOL_TRACE_PERIOD_NS, self._trace_bucket
        )
        self._trace.extend(world_p_m[rows])

    def _write_objects(self, records: np.ndarray) -> None:
        n_objects = records["n_objects"]
        for i, body in enumerate(self._object_names):
            rows = n_objects > i
            if not rows.any():
                continue
            subset = records[rows]
            self._send(
                object_entity(body),
                self._indexes(subset),
                rr.Transform3D.columns(
                    translation=subset["world_p_m"][:, i],
                    quaternion=wxyz_to_xyzw(subset["world_q_wxyz"][:, i]),
                ),
            )

    def _write_control_status(self, records: np.ndarray) -> None:
        indexes = self._indexes(records)
        self._send_scalars(ENTITY_PATH_ERROR, indexes, records["path_error_m"])
        self._send_scalars(ENTITY_MANIPULABILITY, indexes, records["manipulability"])
        self._send_scalars(ENTITY_PATH_S, indexes, records["path_s"])
        self._send_xyz(indexes, ENTITY_DESIRED_P, records["desired_p_m"])
        self._send_xyz(indexes, ENTITY_TOOL_P, records["tool_p_m"])

    def _write_events(self, records: np.ndarray) -> None:
        texts = [event_text(int(r["event"]), int(r["step"]), float(r["value"])) for r in records]
        levels = [EVENT_LEVELS.get(int(e), LEVEL_INFO) for e in records["event"]]
        self._send(
            ENTITY_EVENTS, self._indexes(records), rr.TextLog.columns(text=texts, level=levels)
        )

    def _write_haptic_state(self, records: np.ndarray) -> None:
        indexes = self._indexes(records)
        self._send_xyz(indexes, ENTITY_HAPTIC_P, records["device_p_m"])
        self._send_xyz(indexes, ENTITY_HAPTIC_V, records["device_v_m_s"])
        self._send_xyz(indexes, ENTITY_HAPTIC_F, records["device_f_n"])
        self._send_scalars(ENTITY_PASSIVITY_OBSERVED, indexes, records["passivity_observed_j"])
        self._send_scalars(ENTITY_PASSIVITY_DISSIPATED, indexes, records["passivity_dissipated_j"])
        self._send_scalars(ENTITY_HAPTIC_BUTTONS, indexes, records["buttons"].astype(float))

    def _write_hand_input(self, records: np.ndarray) -> None:
        """HAND_INPUT has no sim time: it sits at the start of the tick it applies to."""
        indexes = self._indexes(records)
        sim_ns = records["valid_from_tick"].astype(np.int64) * self._timestep_ns
        indexes.append(rr.TimeColumn(TIMELINE_SIM, duration=sim_ns.astype("timedelta64[ns]")))
        self._send_xyz(indexes, ENTITY_HAND_TARGET, records["target_p_m"])
        self._send_scalars(ENTITY_HAND_BUTTONS, indexes, records["buttons"].astype(float))

    def _write_force_feedback(self, records: np.ndarray) -> None:
        """Every component per sample, then the world-frame ones as arrows at the tool.

        The arrows are one row per flush, from the newest feedback record, drawn from the
        newest tool position: TOOL_POSE comes before FORCE_FEEDBACK in STREAM_SCHEMAS, so
        this flush's tool records are already seen. No arrows before the first tool pose.
        """
        indexes = self._indexes(records)
        for component, (field, base) in FEEDBACK_COMPONENTS.items():
            force_n = records[field]
            self._send_xyz(indexes, base, force_n)
            self._send_scalars(norm_entity(component), indexes, np.linalg.norm(force_n, axis=1))
        if self._tool_p_m is None:
            return
        newest = records[-1:]
        last = self._indexes(newest)
        origin = self._tool_p_m[np.newaxis]
        for component in FORCE_ARROW_COLORS:
            field, _ = FEEDBACK_COMPONENTS[component]
            force_n = newest[field]
            if component == "device":  # device frame -> world: rotated by the view yaw
                force_n = force_n @ view_to_world(self._yaw_rad).T
            vectors = force_n * FORCE_ARROW_M_PER_N
            self._send(
                force_arrow_entity(component),
                last,
                rr.Arrows3D.columns(vectors=vectors, origins=origin),
            )

    def _write_head_pose(self, records: np.ndarray) -> None:
        indexes = self._indexes(records)
        self._yaw_rad = float(records["predicted_yaw_rad"][-1])
        self._send_scalars(ENTITY_HMD_MEASURED_YAW, indexes, records["measured_yaw_rad"])
        self._send_scalars(ENTITY_HMD_PREDICTED_YAW, indexes, records["predicted_yaw_rad"])
        self._send_xyz(indexes, ENTITY_HMD_FILTERED_P, records["filtered_p_m"])
        self._send_xyz(indexes, ENTITY_HMD_MEASURED_P, records["measured_p_m"])
        self._send(
            ENTITY_HMD,
            indexes,
            rr.Transform3D.columns(
                translation=records["predicted_p_m"],
                quaternion=yaw_pitch_to_xyzw(
                    records["predicted_yaw_rad"], records["predicted_pitch_rad"]
                ),
            ),
        )

    def _write_teleop_status(self, records: np.ndarray) -> None:
        indexes = self._indexes(records)
        self._send_xyz(indexes, ENTITY_TELEOP_V_REF, records["world_v_ref_m_s"])
        self._send_xyz(indexes, ENTITY_TELEOP_V_TOOL, records["world_v_tool_m_s"])
        self._send_xyz(
            indexes, ENTITY_TELEOP_V_ERROR, records["world_v_ref_m_s"] - records["world_v_tool_m_s"]
        )
        self._send_scalars(ENTITY_TELEOP_SPEED_SCALE, indexes, records["speed_scale"])
        self._send_scalars(ENTITY_TELEOP_GRIPPER_CMD, indexes, records["gripper_cmd"])
        self._send_scalars(ENTITY_TELEOP_HOLDING, indexes, records["holding"].astype(float))

    # -- derived series: loop rates, per-hop latency, sequence checks -------------------
    def _write_timing(self, name: str, records: np.ndarray) -> None:
        """Loop rate and per-hop latency of one stream's flushed records; seq checks.

        Works on any record kind with the common header (fields t_source_ns, seq,
        trace_ns); a stream buffered in another form is skipped.
        """
        fields = getattr(records.dtype, "names", None) or ()
        if not {"t_source_ns", "seq", "trace_ns"} <= set(fields):
            return
        self._write_latency(name, records)
        if name not in PERIODIC_STREAMS:
            return
        self._write_rate(name, records)
        if name in SEQ_CHECKED_STREAMS:
            self._check_seq(name, records["seq"].astype(np.int64))

    def _write_rate(self, name: str, records: np.ndarray) -> None:
        """Records per second of the producer's clock, once per ``recorder.rate_window_s``.

        The window starts at a record's t_source_ns and counts the records after it; a
        row is logged at the time of the record that closes the window.
        """
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
            self._close_rate_window(name)

    def _close_rate_window(self, name: str) -> None:
        """Log the rate of the stream's open window (if it counted any record), restart it."""
        window, last = self._rate_windows[name], self._rate_last.get(name)
        if last is None or window[1] == 0:
            return
        end_ns = int(last["t_source_ns"][0])
        if end_ns > window[0]:
            rate_hz = window[1] / ((end_ns - window[0]) * 1e-9)
            self._send_scalars(rate_entity(name), self._indexes(last), np.array([rate_hz]))
        window[0], window[1] = end_ns, 0

    def _hop_chain(self, name: str, trace: np.ndarray) -> list[tuple[Stage, Stage]]:
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
                self._send_static(
                    latency_entity(name),
                    rr.SeriesLines(names=[hop_name(a, b) for a, b in hops]),
                )
        return hops

    def _write_latency(self, name: str, records: np.ndarray) -> None:
        """Every hop of the stream's records in one multi-series entity, in ms.

        ``latency/<stream>`` holds one scalar per hop (column order: :meth:`_hop_chain`,
        names in its SeriesLines), so a 1 kHz stream costs one Rerun call per flush.
        A hop whose stamps are unset, or whose later stamp is older (copied from another
        cycle), is NaN in that row. Streams that copy the stamps of the records they
        answer show the same hop as each of them sees it.
        """
        trace = records["trace_ns"]
        hops = self._hop_chain(name, trace)
        if not hops:
            return
        first = trace[:, [a for a, _ in hops]]
        second = trace[:, [b for _, b in hops]]
        hop_ms = (second - first) / NS_PER_MS
        hop_ms[(first <= 0) | (second <= 0) | (second < first)] = np.nan
        rows = ~np.isnan(hop_ms).all(axis=1)
        if rows.any():
            self._send(
                latency_entity(name),
                self._indexes(records, rows),
                rr.Scalars.columns(scalars=np.ascontiguousarray(hop_ms[rows])),
            )

    def _send_static(self, entity: str, archetype: Any) -> None:
        assert self._rec is not None
        self._rec.log(entity, archetype, static=True)

    def _check_seq(self, name: str, seq: np.ndarray) -> None:
        """Gaps (lost records) and restarts (the producer started over), by the bus
        layer's rule (:class:`teleop.bus.stamps.SeqGaps`)."""
        missing, restarts = self._seq_gaps.setdefault(name, SeqGaps()).add_batch(seq)
        if missing:
            self.add_line(LEVEL_WARN, f"{name}: {missing} record(s) missing (seq gaps)")
        if restarts:
            self.add_line(
                LEVEL_INFO,
                f"{name}: seq started over {restarts} time(s) (producer restart or new run)",
            )

    def _write_recorder_events(self) -> None:
        """Queued lines plus new drops (bad records, buffer overflow) as event-log rows."""
        for (kind, reason), count in self.drops.counts().items():
            new = count - self._seen_drops.get((kind, reason), 0)
            if new > 0:
                self._seen_drops[(kind, reason)] = count
                try:
                    kind_name = Kind(kind).name
                except ValueError:
                    kind_name = f"kind {kind}"
                self.add_line(LEVEL_WARN, f"dropped {new} bad {kind_name} record(s) ({reason})")
        with self._cond:
            overflow = {n: b.overflow for n, b in self.buffers.items()}
        for name, count in overflow.items():
            new = count - self._seen_overflow[name]
            if new > 0:
                self._seen_overflow[name] = count
                self.add_line(LEVEL_WARN, f"recorder buffer full: dropped {new} {name} record(s)")
        with self._lines_lock:
            lines, self._lines = self._lines, []
        if not lines:
            return
        source = np.array([line[0] for line in lines], dtype=np.int64)
        sim = np.array([line[1] for line in lines], dtype=np.int64)
        self._send(
            ENTITY_RECORDER_EVENTS,
            [
                rr.TimeColumn(TIMELINE_SOURCE, duration=source.astype("timedelta64[ns]")),
                rr.TimeColumn(TIMELINE_SIM, duration=sim.astype("timedelta64[ns]")),
            ],
            rr.TextLog.columns(text=[line[3] for line in lines], level=[line[2] for line in lines]),
        )

    # -- reporting ---------------------------------------------------------------------
    def wait_received(self, counts: Mapping[str, int], timeout_s: float) -> bool:
        """Wait until each named stream has received at least its count of records.

        Event driven (the callbacks notify a condition); for tests and tools that must
        know the recorder has everything before they stop it.
        """
        with self._cond:
            return self._cond.wait_for(
                lambda: all(self.buffers[n].received >= c for n, c in counts.items()),
                timeout_s,
            )

    @property
    def flushes(self) -> int:
        """Flushes completed so far."""
        with self._cond:
            return self._flushes

    def wait_flushes(self, count: int, timeout_s: float) -> bool:
        """Wait until at least ``count`` flushes have completed (event driven)."""
        with self._cond:
            return self._cond.wait_for(lambda: self._flushes >= count, timeout_s)

    def stats(self) -> dict[str, Any]:
        """Samples per stream, drops, flushes and the CPU share (``cpu_time_s`` is
        ``time.process_time()`` of the whole process since construction)."""
        with self._cond:
            received = {n: b.received for n, b in self.buffers.items()}
            overflow = {n: b.overflow for n, b in self.buffers.items()}
        wall_s = (time.monotonic_ns() - self._wall_start_ns) * 1e-9
        cpu_s = time.process_time() - self._cpu_start_s
        return {
            "rrd_path": str(self.segment.recording_path),
            "rrd_segment": self.segment.index,
            "samples_logged": dict(self._logged),
            "samples_received": received,
            "overflow_drops": overflow,
            "decode_drops": self.drops.total,
            "rerun_errors": self._rerun_errors,
            "viewer": self.file.viewer,
            "flushes": self._flushes,
            "flush_wall_s_max": self._flush_wall_s_max,
            "flush_wall_s_total": self._flush_wall_s_total,
            "cpu_time_s": cpu_s,
            "wall_time_s": wall_s,
            "cpu_share": cpu_s / wall_s if wall_s > 0 else 0.0,
            "eye_view": self.eye_view.stats(),
        }
