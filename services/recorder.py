"""The recorder service: :class:`teleop.viz.recording.RecordingWriter` on the bus.

It subscribes to every stream the graph gives it (teleop.bus.graph: the recorder among a
stream's consumers; a fast stream through its observers' batched copy), the eye-view
frames and the liveliness tokens (services joining or leaving the bus go to the event
log), and flushes the writer every ``recorder.flush_every_s`` (more often while a live
viewer watches).
"""

from __future__ import annotations

import logging
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

import zenoh

from teleop.bus.messages import EYE_VIEW, RUN_EVENT
from teleop.bus.service import Service, ServiceOptions, lower_priority_to, service_main
from teleop.bus.session import subscribe, subscribe_frames
from teleop.bus.topics import Topics
from teleop.core.config import Config, ConfigError
from teleop.core.rundir import RECORDER_SEGMENTS_FILE, RECORDING_FILE
from teleop.viz.entities import entity_roots
from teleop.viz.recording import (
    BATCHED_STREAMS,
    BUFFER_CAPACITY_RECORDS,
    STREAM_SCHEMAS,
    RecordingWriter,
)
from teleop.viz.recording_file import RecordingFile, claim_segment
from teleop.viz.stream_writers import LEVEL_INFO, LEVEL_WARN

logger = logging.getLogger(__name__)


class RecorderService(Service):
    """Subscribes to every stream of each robot and hands it to that robot's
    RecordingWriter, all of them writing one recording (a RecordingFile)."""

    name: ClassVar[str] = "recorder"
    writer_class: ClassVar[type[RecordingWriter]] = RecordingWriter

    def __init__(
        self,
        config: Config,
        options: ServiceOptions | None = None,
        *,
        buffer_capacity: int = BUFFER_CAPACITY_RECORDS,
    ) -> None:
        super().__init__(config, options)
        # One recording of every robot: a robot's entities under its id when there are
        # several (teleop.viz.entities entity_roots), all in one 3D view.
        self._ledger: Path | None = None  # the run's segments (None: no run directory)
        if self.options.run_dir is not None:
            self._ledger = self.options.run_dir / RECORDER_SEGMENTS_FILE
        roots = entity_roots([t.robot_id for t in self.robot_topics])
        segment = claim_segment(self._resolve_rrd_path(), self._ledger)
        self.file = RecordingFile(config, segment, roots)
        self.writers: list[RecordingWriter] = [
            self.writer_class(
                config, self.file, self.drops, root=root, buffer_capacity=buffer_capacity
            )
            for root in roots
        ]
        self.writer = self.writers[0]
        self._subscribers: list[Any] = []
        self._recording_closed = False

    @property
    def rrd_path(self) -> Path:
        return self.file.rrd_path

    def _resolve_rrd_path(self) -> Path:
        if self.config.recorder.rrd_path:
            return Path(self.config.recorder.rrd_path)
        if self.options.run_dir is not None:
            return self.options.run_dir / RECORDING_FILE
        raise ConfigError("recorder.rrd_path is empty and no --run-dir was given")

    # -- lifecycle ---------------------------------------------------------------------
    def open(self) -> None:
        """Open the session and the recording, subscribe to every stream, then announce.

        The liveliness token comes last, so a producer that waits for it knows that
        nothing it publishes from then on is missed. On failure, everything opened so
        far is closed again (``__exit__`` does not run when ``__enter__`` raises).
        """
        try:
            lower_priority_to(self.config.recorder.nice)
            super().open()
            assert self.session is not None
            self.file.open()
            for topics, writer in zip(self.robot_topics, self.writers, strict=True):
                self._subscribe_robot(topics, writer)
            self.announce()
        except BaseException:
            self.close()
            raise

    def _subscribe_robot(self, topics: Topics, writer: RecordingWriter) -> None:
        """Every stream of one robot into its writer."""
        session, drops = self.session, self.drops
        assert session is not None
        writer.open()
        for name, schema in STREAM_SCHEMAS.items():
            batched = name in BATCHED_STREAMS
            key = getattr(topics, BATCHED_STREAMS[name] if batched else name)
            buffer = writer.buffers[name]
            if schema is RUN_EVENT:  # only the events the stream's service owns, recovered
                self._subscribers.append(self.subscribe_events(name, buffer, topics))
            else:
                sub = subscribe(session, key, schema, buffer, drops, batched=batched)
                self._subscribers.append(self.keep(sub))
        sub = subscribe_frames(session, topics.eye_view, EYE_VIEW, writer.eye_view, drops)
        self._subscribers.append(self.keep(sub))
        liveliness = session.liveliness().declare_subscriber(
            topics.alive_all, self._on_liveliness(topics, writer), history=True
        )
        self._subscribers.append(self.keep(liveliness))

    @staticmethod
    def _on_liveliness(topics: Topics, writer: RecordingWriter) -> Callable[[zenoh.Sample], None]:
        """A service joined or left the bus: a line in the event log (a restart is both)."""

        def on_token(sample: zenoh.Sample) -> None:
            service = topics.service_of(str(sample.key_expr))
            if sample.kind == zenoh.SampleKind.DELETE:
                level, text = LEVEL_WARN, f"service {service} left the bus"
            else:
                level, text = LEVEL_INFO, f"service {service} joined the bus"
            writer.add_line(level, text)

        return on_token

    def run(self, stop: threading.Event) -> None:
        """Flush every ``recorder.flush_every_s`` until ``stop`` is set, then flush the
        rest; a segment that reached ``recorder.segment_mb`` is closed and the next one
        begun between two flushes (the writers log only in them)."""
        period_s = self.config.recorder.flush_every_s
        while not stop.wait(period_s):
            for writer in self.writers:
                writer.flush()
            if self.file.full():
                current = self.file.segment
                self.file.rotate(claim_segment(current.recording_path, self._ledger, current))
        for writer in self.writers:
            writer.flush()

    def close(self) -> None:
        """Stop the subscribers, log what is left and the stats, close the file, then
        the session. Safe to call twice."""
        if not self._recording_closed:
            self._recording_closed = True
            for sub in self._subscribers:
                try:
                    sub.undeclare()
                except zenoh.ZError as exc:  # session already gone
                    logger.debug("undeclare %r: %s", sub, exc)
            for close in (*(writer.close for writer in self.writers), self.file.close):
                try:
                    close()
                except Exception:  # the others, the summary and the session close go on
                    logger.exception("closing the Rerun recording %s failed", self.file.rrd_path)
        super().close()

    def summary(self) -> dict[str, Any]:
        """The base summary plus the writer's: samples per stream, drops, flushes, CPU."""
        if len(self.writers) == 1:
            return {**super().summary(), **self.writer.stats()}
        robots = {
            t.robot_id: w.stats() for t, w in zip(self.robot_topics, self.writers, strict=True)
        }
        return {**super().summary(), "robots": robots}


if __name__ == "__main__":
    sys.exit(service_main(RecorderService))
