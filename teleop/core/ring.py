"""A fixed-size ring of the newest samples, resident from the start.

Every figure a long-running service keeps about its own loop (lateness, latency, a
cycle's stages, the stamps a latency test reads back) lives in one of these: its memory
is taken and written once at construction, so a stack kept up for an hour uses the same
memory at minute 60 as at minute 1, and a running summary's percentiles are computed in
one scratch buffer the ring keeps (no temporary the size of the ring each time: taken
and freed once a second, such temporaries fragment the heap of a long run).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np


class Ring:
    """The newest ``capacity`` rows of ``columns`` values each (``columns=None``: one
    value per row, a 1-D ring). ``count`` rows were appended in all; ``dropped`` of them
    (the oldest) are no longer kept. Not thread-safe: its owner appends and reads under
    its own lock or from one thread."""

    def __init__(self, capacity: int, columns: int | None = None, dtype: type = np.int64) -> None:
        if capacity <= 0:
            raise ValueError(f"capacity must be > 0, got {capacity}")
        if columns is not None and columns <= 0:
            raise ValueError(f"columns must be > 0, got {columns}")
        shape = (capacity,) if columns is None else (capacity, columns)
        # np.full writes every page now: the ring's memory is resident from the start.
        self._data = np.full(shape, 0, dtype=dtype)
        self._scratch: np.ndarray | None = None  # made by the first percentiles(), then kept
        self.count = 0

    def __len__(self) -> int:
        """Rows kept: the newest ``min(count, capacity)``."""
        return min(self.count, len(self._data))

    @property
    def dropped(self) -> int:
        """Rows appended but no longer kept (overwritten by newer ones)."""
        return self.count - len(self)

    def append(self, row: float | int | np.ndarray | Sequence[float]) -> None:
        """Keep ``row`` (a value, or ``columns`` values), overwriting the oldest if full."""
        self._data[self.count % len(self._data)] = row
        self.count += 1

    @property
    def rows(self) -> np.ndarray:
        """The rows kept, oldest first: a view while the ring has not wrapped, else a copy
        (copy it to keep it either way)."""
        kept = len(self)
        if self.count <= len(self._data):
            return self._data[:kept]
        start = self.count % len(self._data)
        return np.concatenate((self._data[start:], self._data[:start]))

    def percentiles(self, qs: Sequence[float], column: int | None = None) -> list[float]:
        """The ``qs`` percentiles (0-100, linear interpolation as ``np.percentile``) of the
        rows kept (of one ``column`` of a 2-D ring); [] when none is kept."""
        kept = len(self)
        if not kept:
            return []
        if self._scratch is None:
            self._scratch = np.full(len(self._data), 0, dtype=self._data.dtype)
        values = self._scratch[:kept]
        np.copyto(values, self._data[:kept] if column is None else self._data[:kept, column])
        positions = [(kept - 1) * q / 100.0 for q in qs]
        kth = sorted({int(np.floor(p)) for p in positions} | {int(np.ceil(p)) for p in positions})
        values.partition(kth)  # in place: each kth element is where sorting would put it
        result = []
        for p in positions:
            lo, hi = int(np.floor(p)), int(np.ceil(p))
            frac = p - lo
            result.append(float(values[lo]) + (float(values[hi]) - float(values[lo])) * frac)
        return result

    def max(self, column: int | None = None) -> float:
        """The largest value kept (of one ``column``); 0 when none is kept."""
        kept = len(self)
        if not kept:
            return 0.0
        return float((self._data[:kept] if column is None else self._data[:kept, column]).max())

    def save(self, path: Path) -> None:
        """Write the rows kept, oldest first, as a .npy file (atomically: a reader never
        sees half a file)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            np.save(f, self.rows)
        tmp.replace(path)
