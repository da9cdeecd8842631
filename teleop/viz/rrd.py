"""Reading a recording (``.rrd``) back: for the report, the tests and tools.

Uses Rerun's own chunk reader (``rerun.chunk.RrdReader``): no viewer, no server. The file,
and the later segments a restarted recorder wrote beside it (teleop.core.rundir
``segment_path``), are decoded once into Arrow record batches grouped by entity
(:class:`Recording`): one timeline, with the gaps between segments known
(:meth:`Recording.gaps`). The helpers then pick columns from memory. Duration and
timestamp time columns come back as int nanoseconds. A recording of several robots
holds each robot's entities under its id (:attr:`Recording.robots`); :meth:`Recording.under`
reads one robot's as a one-robot recording's.
"""

from __future__ import annotations

import copy
import warnings
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from rerun.chunk import RrdReader

from teleop.core.rundir import segment_paths
from teleop.viz.entities import ENTITY_WORLD, TIMELINE_SIM

SCALARS_COLUMN = "Scalars:scalars"  # the value column of a Scalars archetype


@dataclass(frozen=True)
class Series:
    """One scalar series: times (N,) in ns on one timeline, values (N,), sorted by time."""

    t_ns: np.ndarray
    values: np.ndarray

    @property
    def t_s(self) -> np.ndarray:
        return self.t_ns * 1e-9


def _as_int_ns(column: pa.Array) -> pa.Array:
    if pa.types.is_duration(column.type) or pa.types.is_timestamp(column.type):
        return column.cast(pa.int64())
    return column


class NotARecording(ValueError):
    """The file is missing or is not a Rerun recording (.rrd); the message says which."""


@dataclass(frozen=True)
class Segment:
    """One file of a recording and the sim time it covers (ns; None: no sim time)."""

    path: Path
    sim_start_ns: int | None
    sim_end_ns: int | None


@dataclass(frozen=True)
class Gap:
    """Sim time between two segments that no segment covers (a recorder restart)."""

    after: Path  # the segment that ends at start_ns
    start_ns: int
    end_ns: int


class Recording:
    """Every chunk of a recording, all its segments, grouped by entity (no leading '/')."""

    def __init__(self, path: str | Path, *, one_segment: bool = False) -> None:
        """The recording whose first segment is ``path``, all its segments; with
        ``one_segment``, ``path`` alone (a viewer opening one segment sees that)."""
        self.path = Path(path)
        if not self.path.is_file():
            raise NotARecording(f"no recording {self.path}")
        self.batches: dict[str, list[pa.RecordBatch]] = defaultdict(list)
        self.segments: list[Segment] = []
        self.has_blueprint = False
        for segment in [self.path] if one_segment else segment_paths(self.path):
            self._read_segment(segment)

    def _read_segment(self, path: Path) -> None:
        try:
            with warnings.catch_warnings():  # written so on purpose (recording_file.py)
                warnings.filterwarnings("ignore", message="RRD file has no footer")
                reader = RrdReader(path)
        except RuntimeError as exc:  # Rerun's reader: not an .rrd, or a damaged one
            raise NotARecording(f"{path} is not a readable Rerun recording: {exc}") from None
        self.has_blueprint = self.has_blueprint or bool(reader.blueprints)
        start, end = None, None
        # collect() compacts the recorder's many small chunks (one per entity and flush)
        # into a few large ones, much faster to read.
        for chunk in reader.stream().collect().stream():
            batch = chunk.to_record_batch()
            self.batches[chunk.entity_path.lstrip("/")].append(batch)
            if TIMELINE_SIM in batch.schema.names:
                times = _as_int_ns(batch.column(TIMELINE_SIM))
                low, high = pc.min(times).as_py(), pc.max(times).as_py()
                if low is not None:
                    start = low if start is None else min(start, low)
                    end = high if end is None else max(end, high)
        self.segments.append(Segment(path, start, end))

    def gaps(self) -> list[Gap]:
        """The sim time missing between consecutive segments (where a recorder was down;
        segments that overlap leave none)."""
        gaps = []
        for before, after in zip(self.segments, self.segments[1:], strict=False):
            end, start = before.sim_end_ns, after.sim_start_ns
            if end is not None and start is not None and start > end:
                gaps.append(Gap(before.path, end, start))
        return gaps

    @property
    def entities(self) -> list[str]:
        return sorted(self.batches)

    @property
    def robots(self) -> list[str]:
        """The entity root of each robot recorded (teleop.viz.entities ``entity_roots``):
        ``[""]`` for a one-robot recording, the robot ids for several ([]: no 3D scene
        was logged, so no robot known)."""
        if ENTITY_WORLD in self.batches:
            return [""]
        suffix = "/" + ENTITY_WORLD
        return sorted(
            e[: -len(suffix)] for e in self.batches if e.endswith(suffix) and e.count("/") == 1
        )

    def under(self, root: str) -> Recording:
        """The entities under one robot's entity ``root``, named as in a one-robot
        recording (the empty root: this recording). Shares this one's data."""
        if not root:
            return self
        prefix = root + "/"
        view = copy.copy(self)
        view.batches = defaultdict(list)
        for entity, batches in self.batches.items():
            if entity.startswith(prefix):
                view.batches[entity[len(prefix) :]] = batches
        return view

    def lists(self, entities: Iterable[str] | None = None) -> dict[str, dict[str, list[Any]]]:
        """{entity: {column: values}} as Python lists, rows in chunk order.

        Convenient for tests and small entities; long series are faster with
        :meth:`scalars`, which stays in numpy.
        """
        wanted = self.batches.keys() if entities is None else entities
        out: dict[str, dict[str, list[Any]]] = defaultdict(lambda: defaultdict(list))
        for entity in wanted:
            for batch in self.batches.get(entity, []):
                for name in batch.schema.names:
                    out[entity][name].extend(_as_int_ns(batch.column(name)).to_pylist())
        return out

    def scalars(self, timeline: str) -> dict[str, Series]:
        """Every Scalars entity that has ``timeline``, as numpy series sorted by that time.

        Rows without a time on that timeline (static rows) are left out; a row holding
        several scalars keeps its first.
        """
        out: dict[str, Series] = {}
        for entity, batches in self.batches.items():
            parts = []
            for batch in batches:
                names = batch.schema.names
                if SCALARS_COLUMN not in names or timeline not in names:
                    continue
                times = _as_int_ns(batch.column(timeline))
                values = batch.column(SCALARS_COLUMN)
                valid = pc.and_(pc.is_valid(times), pc.greater(pc.list_value_length(values), 0))
                times, values = times.filter(valid), values.filter(valid)
                first = pc.list_element(values, 0)
                parts.append((times.to_numpy(), first.to_numpy(zero_copy_only=False)))
            if parts:
                t = np.concatenate([p[0] for p in parts])
                v = np.concatenate([p[1] for p in parts]).astype(float)
                order = np.argsort(t, kind="stable")
                out[entity] = Series(t[order], v[order])
        return out

    def multi_series(self, entity: str, timeline: str) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """A Scalars entity with several series per row: times (N,) ns, values (N, k) with
        NaN where a row has fewer series, and the series' names (its SeriesLines names,
        else ``"0"``, ``"1"``, ...). Sorted by time; rows without that timeline skipped."""
        cols = self.lists([entity])[entity]
        names = [n for row in cols.get("SeriesLines:names", []) if row for n in row]
        times = cols.get(timeline, [])
        rows = [
            (t, v)
            for t, v in zip(times, cols.get(SCALARS_COLUMN, []), strict=False)
            if t is not None and v
        ]
        k = max((len(v) for _, v in rows), default=0)
        values = np.full((len(rows), k), np.nan)
        for i, (_, v) in enumerate(rows):
            values[i, : len(v)] = v
        t_ns = np.array([t for t, _ in rows], dtype=np.int64)
        order = np.argsort(t_ns, kind="stable")
        names = names[-k:] if len(names) >= k else [*names, *map(str, range(len(names), k))]
        return t_ns[order], values[order], names

    def column(self, prefix: str, column: str) -> dict[str, list[Any]]:
        """{entity: values of ``column``} for every entity at or under ``prefix``."""
        out: dict[str, list[Any]] = {}
        for entity, batches in self.batches.items():
            if entity != prefix and not entity.startswith(prefix + "/"):
                continue
            values = [
                v
                for batch in batches
                if column in batch.schema.names
                for v in batch.column(column).to_pylist()
            ]
            if values:
                out[entity] = values
        return out


def read_rrd(path: str | Path) -> dict[str, dict[str, list[Any]]]:
    """{entity: {column: values}} of the whole recording as Python lists (see
    :meth:`Recording.lists`)."""
    return Recording(path).lists()
