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
    FrameSchema,
    Schema,
)
from teleop.core.config import Config, ModelError
from teleop.viz.entities import (
    ENTITY_EYE_VIEW,
    ENTITY_OBJECTS,
    ENTITY_STATS,
    ENTITY_WORLD,
    TIMELINE_SIM,
    TIMELINE_SOURCE,
)
from teleop.viz.recording_file import RecordingFile, RootedStream
from teleop.viz.scene3d import SceneModel
from teleop.viz.stream_writers import (
    LEVEL_WARN,
    NS_PER_MS,
    ArmWriter,
    Columns,
    EventLog,
    SceneWriter,
    SimClock,
    TeleopWriter,
    TimingWriter,
    WorldWriter,
    Write,
)

logger = logging.getLogger(__name__)

# --- Tuning -------------------------------------------------------------------------------
# Per-stream buffer bound (records): 20 s of a 1 kHz stream, about 6 MB of PLANT_STATE.
# A flush that falls further behind drops the oldest records and counts them.
BUFFER_CAPACITY_RECORDS = 20_000
# Eye-view frames buffered between flushes (at 5-10 Hz and 0.1 s flushes about 1 is
# waiting); beyond this the oldest is dropped and counted, so memory stays bounded.
EYE_VIEW_BUFFER_FRAMES = 32
# Latency samples kept per hop for the eye-view percentiles (the newest ones).
EYE_VIEW_LATENCY_SAMPLES = 100_000
JPEG_MEDIA_TYPE = "image/jpeg"
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


def _scene_model(config: Config) -> SceneModel | None:
    """The 3D scene of ``recorder.scene3d``, or None (off, or a model that does not match
    the config: the recording goes on without it)."""
    if not config.recorder.scene3d:
        return None
    try:
        return SceneModel(config, ENTITY_OBJECTS)
    except (ModelError, ValueError) as exc:
        logger.warning("no 3D scene: the model does not match the config (%s)", exc)
        return None


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
    entity ``root``, by the writer of each stream's family
    (:mod:`teleop.viz.stream_writers`).

    Bus callbacks feed :attr:`buffers` (one per stream, a :class:`StreamBuffer` is a
    record callback) and :attr:`eye_view`; :meth:`flush` logs what they hold; ``drops``
    is the receiver's count of bad records (for the event log). The file is opened
    before :meth:`open` and closed after :meth:`close`, by its owner.
    """

    arm_writer: type[ArmWriter] = ArmWriter  # the arm's family (a test swaps in a faulty one)

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
        self._joint_names: Sequence[str] = config.robot.arm_joints[:MAX_JOINTS]
        clock = SimClock()
        self.clock = clock
        self.events = EventLog(clock, drops)
        world = WorldWriter(config, config.robot.object_bodies[:MAX_OBJECTS])
        self._families = [self.arm_writer(config, clock), world]
        scene = _scene_model(config)
        if scene is not None:  # after the arm: a plant state's plots, then its bodies
            self._families.append(SceneWriter(config, scene))
        self._families.append(TeleopWriter(config, world))
        self.timing = TimingWriter(config, self.events, PERIODIC_STREAMS, SEQ_CHECKED_STREAMS)
        # Per stream, its writers in order (a plant state: the arm's plots, the scene).
        self._writes: dict[str, list[Write]] = {}
        for family in (*self._families, self.events):
            for name, write in family.writes().items():
                self._writes.setdefault(name, []).append(write)
        self._out: Columns | None = None
        self._logged = dict.fromkeys(STREAM_SCHEMAS, 0)
        self._flushes = 0
        self._flush_wall_s_max = 0.0
        self._flush_wall_s_total = 0.0
        self._rerun_errors = 0
        self._rerun_error_logged: set[str] = set()
        self._segment_announced = True  # a later segment's start is in the event log
        self._cpu_start_s = time.process_time()
        self._wall_start_ns = time.monotonic_ns()

    # -- lifecycle ---------------------------------------------------------------------
    def open(self) -> None:
        """Log this robot's static entities (the scene, frames, plot styles) into the
        open file."""
        rec = self.file.stream(self.root)
        self._out = out = Columns(rec, self._joint_names)
        # A later segment says so in the event log, at the sim time of its first states.
        self._segment_announced = self.segment.index == 0
        out.static(ENTITY_WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP)
        for family in self._families:
            family.open(out)

    def add_line(self, level: str, text: str) -> None:
        """Queue one recorder event line, at the recorder's clock and the newest sim time."""
        self.events.add_line(level, text)

    def close(self) -> None:
        """Log what is left and the stats (the file stays open for its owner to close).
        Safe to call twice."""
        out = self._out
        if out is None:
            return
        self.flush()
        for name in self.timing.streams_with_windows():  # a short run still gets a window
            self._guarded(name, self.timing.close_rate_window, name, out)
        out.static(
            ENTITY_STATS,
            rr.TextDocument(json.dumps(self.stats(), indent=2), media_type="text/markdown"),
        )
        self._out = None

    # -- flushing ----------------------------------------------------------------------
    def flush(self) -> None:
        """Send every buffered record to Rerun, one ``send_columns`` per entity.

        A Rerun error on one stream is counted and logged once per stream; the other
        streams and later flushes go on.
        """
        out = self._out
        if out is None:
            return
        start_ns = time.monotonic_ns()
        for name, buffer in self.buffers.items():
            records = buffer.take()
            if records.size == 0:
                continue
            if not self._guarded(name, self._write, name, records, out):
                continue
            self._logged[name] += int(records.size)
            self._guarded(f"{name} timing", self.timing.write, name, records, out)
        if not self._segment_announced and self.clock.newest_ns > 0:
            self._segment_announced = True
            self.add_line(
                LEVEL_WARN,
                f"recorder restarted: segment {self.segment.index} ({self.rrd_path.name}) "
                "begins; nothing was recorded since the previous segment's end",
            )
        with self._cond:
            overflow = {n: b.overflow for n, b in self.buffers.items()}
        self._guarded("events", self.events.write_lines, overflow, out)
        self._guarded("eye_view", self.eye_view.write, out.stream)
        elapsed_s = (time.monotonic_ns() - start_ns) * 1e-9
        self._flush_wall_s_max = max(self._flush_wall_s_max, elapsed_s)
        self._flush_wall_s_total += elapsed_s
        with self._cond:
            self._flushes += 1
            self._cond.notify_all()

    def _write(self, name: str, records: np.ndarray, out: Columns) -> None:
        for write in self._writes[name]:
            write(records, out)

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
