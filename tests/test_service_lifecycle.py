"""Pieces of the service lifecycle that need no bus."""

from __future__ import annotations

import logging
import os

from teleop.service import pin_to_cpus


def test_pin_to_cpus_uses_existing_cpus_and_ignores_others(caplog):
    original = os.sched_getaffinity(0)
    try:
        first = min(original)
        pin_to_cpus((first, 10_000))
        assert os.sched_getaffinity(0) == {first}
        os.sched_setaffinity(0, original)
        with caplog.at_level(logging.WARNING):
            pin_to_cpus((10_000,))
        assert os.sched_getaffinity(0) == original
        assert "no such CPU" in caplog.text
        pin_to_cpus(())
        assert os.sched_getaffinity(0) == original
    finally:
        os.sched_setaffinity(0, original)
