"""The Rerun recording a recorder writes: its file (and live viewer), its segments, and
the entity root each robot's writer logs under.

One :class:`RecordingFile` per recorder process, whatever the number of robots: the
file, the sinks (a spawned viewer, a gRPC URL), the blueprint and, in a run of several
robots, where each robot stands in the 3D scene. Each robot's
:class:`~teleop.viz.recording.RecordingWriter` logs through :meth:`RecordingFile.stream`,
under its robot's entity root (teleop.viz.entities ``entity_roots``): a one-robot
recording has the entity paths of entities.py as they are, a recording of several has
them under each robot's id (``arm1/world/tool``), every robot in one 3D view.
"""

from __future__ import annotations

import json
import logging
import os
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import rerun as rr

from teleop.core.config import Config
from teleop.core.rundir import segment_path, segment_paths
from teleop.viz.blueprint import build_blueprint, robot_offset_m
from teleop.viz.entities import APPLICATION_ID, rooted
from teleop.viz.viewer import grpc_url, listening

logger = logging.getLogger(__name__)

# The port a spawned native viewer listens on (Rerun's default), and how long one attempt
# to connect to it may take (s; the spawn has already waited for the viewer to start).
VIEWER_PORT = 9876
VIEWER_PROBE_S = 1.0
# How long close() waits for Rerun to write the last chunks to the file (s).
RRD_FLUSH_TIMEOUT_S = 10.0
VIEWER_SPAWNED = "spawned"
VIEWER_NOT_REQUESTED = "not requested"


@dataclass(frozen=True)
class Segment:
    """The part of a run's recording one recorder process writes: the first, or the
    next one after a restart; every segment of a run has the run's Rerun recording id, so
    a viewer given them all shows one recording."""

    index: int
    path: Path  # this segment's file
    recording_id: str
    recording_path: Path  # the recording's (its first segment's): what a reader opens

    @classmethod
    def only(cls, rrd_path: Path) -> Segment:
        """The one segment of a recording written by one process, never restarted."""
        return cls(0, rrd_path, uuid.uuid4().hex, rrd_path)


def claim_segment(rrd_path: Path, ledger: Path | None, after: Segment | None = None) -> Segment:
    """The next segment of the recording ``rrd_path`` for this recorder, from the run's
    ``ledger`` (None: a recorder without a run directory) and the segment it closes
    (``after``: it goes on in the next one, :meth:`RecordingFile.rotate`).

    No ledger and no segment before: the run's first recorder; it takes ``rrd_path``
    itself and removes stale later segments beside it (of an earlier run). A ledger: a
    restarted or rotating recorder; it takes the next segment, never an existing file.
    The ledger is updated atomically.
    """
    segments: list[str] = []
    recording_id = after.recording_id if after is not None else uuid.uuid4().hex
    if ledger is not None and ledger.exists():
        known = json.loads(ledger.read_text())
        segments, recording_id = list(known["segments"]), str(known["recording_id"])
    elif after is None:
        index = 1
        while (stale := segment_path(rrd_path, index)).exists():
            stale.unlink()
            index += 1
    index = max(len(segments), after.index + 1 if after is not None else 0)
    segment = Segment(index, segment_path(rrd_path, index), recording_id, rrd_path)
    if ledger is not None:
        ledger.parent.mkdir(parents=True, exist_ok=True)
        tmp = ledger.with_name(ledger.name + ".tmp")
        text = {"recording_id": recording_id, "segments": [*segments, str(segment.path)]}
        tmp.write_text(json.dumps(text, indent=2) + "\n")
        os.replace(tmp, ledger)
    return segment


def no_display_reason(environ: Mapping[str, str]) -> str | None:
    """Why a native window cannot open in this environment (None: it may): no X11
    display and no Wayland one."""
    if any(environ.get(name) for name in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET")):
        return None
    return "no display (DISPLAY and WAYLAND_DISPLAY unset)"


class BlueprintSender:
    """Sends one blueprint into a recording stream, again at each segment, through one
    blueprint stream kept for the process.

    Rerun's ``send_blueprint`` builds a new blueprint stream at every call that is never
    freed (its two batcher threads and about 0.5-1.6 MB stay; rerun-sdk 0.41): a day of
    segments would leave thousands of threads. Rerun offers no public way to re-send a
    blueprint, so this uses the calls ``send_blueprint`` itself makes; where a Rerun
    release lacks them it falls back to ``send_blueprint`` (correct files, that leak).
    """

    def __init__(self, blueprint: Any) -> None:
        self.blueprint = blueprint.to_blueprint()
        self._stream: rr.RecordingStream | None = None
        self.fell_back = False  # Rerun's own send_blueprint in use (see above)

    def send(self, rec: rr.RecordingStream) -> None:
        try:
            from rerun import bindings

            if self._stream is None:
                self._stream = rr.RecordingStream._from_native(
                    bindings.new_blueprint(
                        application_id=APPLICATION_ID,
                        make_default=False,
                        make_thread_default=False,
                        default_enabled=True,
                    )
                )
            storage = self._stream.memory_recording()  # a fresh sink for this send
            self._stream.set_time("blueprint", sequence=0)
            self.blueprint._log_to_stream(self._stream)
            bindings.send_blueprint(storage.storage, True, True, recording=rec.to_native())
        except (ImportError, AttributeError, TypeError):
            if not self.fell_back:
                logger.warning("this Rerun release lacks the calls to re-send a blueprint: "
                               "each segment's costs a blueprint stream Rerun never frees",
                               exc_info=True)  # fmt: skip
            self.fell_back = True
            rec.send_blueprint(self.blueprint)


class RootedStream:
    """A recording seen from one robot's entity root: ``log`` and ``send_columns`` as
    Rerun's, every entity path under the root (the empty root: as given), into the
    file's current segment."""

    def __init__(self, file: RecordingFile, root: str) -> None:
        self._file = file
        self.root = root

    def log(self, entity: str, *archetypes: Any, static: bool = False) -> None:
        self._file.log(rooted(self.root, entity), archetypes, static=static)

    def send_columns(self, entity: str, **kwargs: Any) -> None:
        self._file.current.send_columns(rooted(self.root, entity), **kwargs)


class RecordingFile:
    """One Rerun recording of every robot of a run: saved to ``segment.path``, streamed
    to a spawned native viewer as well when ``recorder.spawn`` is set, and to
    ``recorder.grpc_url`` when given. Its own ``RecordingStream`` (no global Rerun
    state). ``roots``: one entity root per robot (teleop.viz.entities ``entity_roots``).
    """

    def __init__(self, config: Config, segment: Segment, roots: Sequence[str] = ("",)) -> None:
        self.config = config
        self.segment = segment
        self.roots = tuple(roots)
        self._rec: rr.RecordingStream | None = None
        self._blueprint = BlueprintSender(build_blueprint(config))
        # The live viewer (recorder.spawn): VIEWER_SPAWNED, or why none was.
        self.viewer = VIEWER_NOT_REQUESTED
        # Every static entity logged, by path and archetypes: each segment gets them
        # again, so the newest segment opens alone with the scene and the series' names.
        self._statics: dict[tuple[str, tuple[str, ...]], tuple[Any, ...]] = {}
        self.segments_closed = 0
        self.segments_deleted = 0  # oldest segments deleted (recorder.keep_mb)

    @property
    def rrd_path(self) -> Path:
        """This process's file (its segment's)."""
        return self.segment.path

    def open(self) -> None:
        """The file (and viewer), the blueprint, and where each robot stands."""
        if self.config.recorder.spawn:
            self.viewer = self._spawn_viewer()
        self._open_segment()
        if len(self.roots) > 1:  # side by side, in a scene whose "up" is every world's
            self.log("/", (rr.ViewCoordinates.RIGHT_HAND_Z_UP,), static=True)
            for index, root in enumerate(self.roots):
                self.log(root, (rr.Transform3D(translation=robot_offset_m(index)),), static=True)

    def _open_segment(self) -> None:
        """The stream's sinks into this segment's file (and the live sinks), then the
        blueprint. The file gets its footer when the segment closes: Rerun keeps the
        chunk index it writes there in memory until then, which ``recorder.segment_mb``
        bounds. One stream for the whole run: a stream per segment would leave Rerun's
        native state of every closed one behind (about 4 MB each)."""
        self.rrd_path.parent.mkdir(parents=True, exist_ok=True)
        if self._rec is None:
            self._rec = rr.RecordingStream(APPLICATION_ID, recording_id=self.segment.recording_id)
        sinks: list[Any] = [rr.FileSink(self.rrd_path, write_footer=True)]
        if self.viewer == VIEWER_SPAWNED:
            sinks.append(rr.GrpcSink(grpc_url(VIEWER_PORT)))
        if self.config.recorder.grpc_url:
            sinks.append(rr.GrpcSink(self.config.recorder.grpc_url))
        self._rec.set_sinks(*sinks)  # the previous sinks closed: its file's footer written
        self._blueprint.send(self._rec)

    @property
    def current(self) -> rr.RecordingStream:
        """The Rerun stream of the segment being written."""
        assert self._rec is not None, "RecordingFile.open() first"
        return self._rec

    def log(self, entity_path: str, archetypes: tuple[Any, ...], *, static: bool) -> None:
        """Log into the current segment; a static entity is kept for the next ones."""
        if static:
            kinds = tuple(type(a).__name__ for a in archetypes)
            self._statics[(entity_path, kinds)] = archetypes
        self.current.log(entity_path, *archetypes, static=static)

    def stream(self, root: str) -> RootedStream:
        """What one robot's writer logs through (the file open)."""
        assert self._rec is not None, "RecordingFile.open() first"
        return RootedStream(self, root)

    def segment_bytes(self) -> int:
        """What the current segment's file holds on disk so far (bytes)."""
        try:
            return self.rrd_path.stat().st_size
        except FileNotFoundError:
            return 0

    def full(self) -> bool:
        """The current segment reached ``recorder.segment_mb``: time to :meth:`rotate`."""
        return self.segment_bytes() >= self.config.recorder.segment_mb * 1e6

    def rotate(self, segment: Segment) -> None:
        """Close the current segment (its footer written) and go on in ``segment`` (the
        run's next, :func:`claim_segment`): the blueprint and every static entity
        logged again, so the newest segment opens alone in a viewer."""
        self.current.flush(timeout_sec=RRD_FLUSH_TIMEOUT_S)
        self.segments_closed += 1
        self.segment = segment
        self._open_segment()
        self._delete_oldest()
        for (entity_path, _), archetypes in self._statics.items():
            self.current.log(entity_path, *archetypes, static=True)

    def _delete_oldest(self) -> None:
        """Past ``recorder.keep_mb`` on disk, the oldest closed segments go (never the
        one being written)."""
        keep_bytes = self.config.recorder.keep_mb * 1e6
        if not keep_bytes:
            return
        paths = [p for p in segment_paths(self.segment.recording_path) if p != self.rrd_path]
        sizes = [p.stat().st_size for p in paths] + [self.segment_bytes()]
        while paths and sum(sizes) > keep_bytes:
            oldest = paths.pop(0)
            sizes.pop(0)
            oldest.unlink(missing_ok=True)
            self.segments_deleted += 1
            logger.info("recorder.keep_mb: deleted the oldest segment %s", oldest)

    def close(self) -> None:
        """Wait for Rerun to write what it holds to the file, then close it (its footer
        written). Safe to call twice."""
        self._close_segment()

    def _close_segment(self) -> None:
        if self._rec is None:
            return
        self._rec.flush(timeout_sec=RRD_FLUSH_TIMEOUT_S)
        self._rec.disconnect()
        self._rec = None

    def _spawn_viewer(self) -> str:
        """Start the native viewer beside the file; VIEWER_SPAWNED, or why not.

        A recording that also streams to a viewer that never came up (no display: it
        exits at once) stalls on that sink, and the file got a tenth of the run. So
        without a display no viewer is started, and one that does not listen after
        Rerun's own start-up wait gets no stream: the file alone has the run."""
        reason = no_display_reason(os.environ)
        if reason is None:
            rr.spawn(port=VIEWER_PORT, connect=False)
            if not listening(VIEWER_PORT, VIEWER_PROBE_S):
                reason = f"the spawned viewer does not listen on port {VIEWER_PORT}"
        if reason is None:
            return VIEWER_SPAWNED
        logger.warning(
            "recorder.spawn: %s: no live viewer; the whole run is in %s (teleop view)",
            reason,
            self.rrd_path,
        )
        return f"not spawned: {reason}"
