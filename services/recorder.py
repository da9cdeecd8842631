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
from pathlib import Path
from typing import Any, ClassVar

import zenoh

from teleop.bus.messages import EYE_VIEW, RUN_EVENT
from teleop.bus.service import Service, ServiceOptions, lower_priority_to, service_main
from teleop.bus.session import subscribe, subscribe_events, subscribe_frames
from teleop.core.config import Config, ConfigError
from teleop.core.rundir import RECORDER_SEGMENTS_FILE, RECORDING_FILE
from teleop.viz.recording import (
    BATCHED_STREAMS,
    BUFFER_CAPACITY_RECORDS,
    LEVEL_INFO,
    LEVEL_WARN,
    STREAM_SCHEMAS,
    RecordingWriter,
    claim_segment,
)

logger = logging.getLogger(__name__)


class RecorderService(Service):
    """Subscribes to every stream of the robot and hands it to a RecordingWriter."""

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
        run_dir = self.options.run_dir
        ledger = run_dir / RECORDER_SEGMENTS_FILE if run_dir is not None else None
        segment = claim_segment(self._resolve_rrd_path(), ledger)
        self.writer = self.writer_class(
            config, segment.path, self.drops, buffer_capacity=buffer_capacity, segment=segment
        )
        self._subscribers: list[Any] = []
        self._recording_closed = False

    @property
    def rrd_path(self) -> Path:
        return self.writer.rrd_path

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
            session, topics, drops, writer = self.session, self.topics, self.drops, self.writer
            writer.open()
            for name, schema in STREAM_SCHEMAS.items():
                batched = name in BATCHED_STREAMS
                key = getattr(topics, BATCHED_STREAMS[name] if batched else name)
                buffer = writer.buffers[name]
                if schema is RUN_EVENT:  # only the events the stream's service owns
                    sub = subscribe_events(session, topics, name, buffer, drops)
                else:
                    sub = subscribe(session, key, schema, buffer, drops, batched=batched)
                self._subscribers.append(self.keep(sub))
            sub = subscribe_frames(session, topics.eye_view, EYE_VIEW, writer.eye_view, drops)
            self._subscribers.append(self.keep(sub))
            liveliness = session.liveliness().declare_subscriber(
                topics.alive_all, self._on_liveliness, history=True
            )
            self._subscribers.append(self.keep(liveliness))
            self.announce()
        except BaseException:
            self.close()
            raise

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        """A service joined or left the bus: a line in the event log (a restart is both)."""
        service = self.topics.service_of(str(sample.key_expr))
        if sample.kind == zenoh.SampleKind.DELETE:
            level, text = LEVEL_WARN, f"service {service} left the bus"
        else:
            level, text = LEVEL_INFO, f"service {service} joined the bus"
        self.writer.add_line(level, text)

    def run(self, stop: threading.Event) -> None:
        """Flush every ``recorder.flush_every_s`` until ``stop`` is set, then flush the
        rest."""
        period_s = self.config.recorder.flush_every_s
        while not stop.wait(period_s):
            self.writer.flush()
        self.writer.flush()

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
            try:
                self.writer.close()
            except Exception:  # the summary and the session close must still happen
                logger.exception("closing the Rerun recording failed")
        super().close()

    def summary(self) -> dict[str, Any]:
        """The base summary plus the writer's: samples per stream, drops, flushes, CPU."""
        return {**super().summary(), **self.writer.stats()}


if __name__ == "__main__":
    sys.exit(service_main(RecorderService))
