"""The ring of newest samples every long-running figure lives in (teleop.core.ring)."""

from __future__ import annotations

import numpy as np
import pytest

from teleop.core.ring import Ring


def test_percentiles_match_numpy_before_and_after_the_ring_wraps():
    rng = np.random.default_rng(0)
    ring = Ring(100)
    values = rng.integers(0, 10_000, 250)
    for n in (1, 2, 37, 100, 250):
        ring = Ring(100)
        for v in values[:n]:
            ring.append(v)
        kept = values[:n][-100:]
        expected = np.percentile(kept, [0, 50, 99, 100])
        assert ring.percentiles([0, 50, 99, 100]) == pytest.approx(expected)
        assert ring.max() == kept.max()
        assert len(ring) == len(kept) and ring.dropped == n - len(kept)


def test_rows_are_oldest_first_and_a_column_has_its_own_percentiles():
    ring = Ring(3, columns=2)
    for i in range(5):
        ring.append((i, -i))
    np.testing.assert_array_equal(ring.rows, [[2, -2], [3, -3], [4, -4]])
    assert ring.percentiles([50], column=1) == [-3.0]
    assert ring.max(column=0) == 4.0


def test_an_empty_ring_has_no_percentiles_and_nothing_is_kept_twice(tmp_path):
    ring = Ring(4, dtype=np.float64)
    assert ring.percentiles([50]) == [] and ring.max() == 0.0 and len(ring.rows) == 0
    for v in (1.5, 2.5):
        ring.append(v)
    ring.save(tmp_path / "sub" / "r.npy")
    np.testing.assert_array_equal(np.load(tmp_path / "sub" / "r.npy"), [1.5, 2.5])


def test_percentiles_leave_the_kept_samples_in_order():
    ring = Ring(8)
    for v in (5, 1, 4, 2, 3):
        ring.append(v)
    ring.percentiles([50])
    np.testing.assert_array_equal(ring.rows, [5, 1, 4, 2, 3])


def test_a_bad_size_is_refused():
    with pytest.raises(ValueError):
        Ring(0)
    with pytest.raises(ValueError):
        Ring(4, columns=0)
