"""The plant's loop: the step core and the pacer of the run's timing mode, put together.

:class:`PlantLoop` is what the plant service runs (``services/plant.py`` is its bus
adapter): a :class:`teleop.sim.stepping.PlantStepCore` (admission, apply or brake, step,
publish, checkpoint, summary) and the :class:`teleop.sim.pacing.Pacer` chosen once for
the configured mode (plant tick, haptic device clock, lockstep). The run's start (fresh
or resumed from a checkpoint) and end are the same in every mode: they live here.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from teleop.bus.messages import Event
from teleop.core.clock import Clock
from teleop.core.config import Config
from teleop.sim.checkpoint import CheckpointStore
from teleop.sim.pacing import LockstepPacer, Pacer, make_pacer
from teleop.sim.stepping import PlantOutputs, PlantStepCore


class PlantLoop:
    """One plant run, driven by commands and a clock; see :mod:`teleop.sim.pacing` for
    which thread steps in each mode."""

    def __init__(
        self,
        config: Config,
        outputs: PlantOutputs,
        clock: Clock,
        store: CheckpointStore | None = None,
        holds_ns: Sequence[int] = (),
    ) -> None:
        self.pacer: Pacer = make_pacer(config, outputs, clock, store, holds_ns)
        self.core: PlantStepCore = self.pacer.core

    def release(self, at_ns: int) -> None:
        """The launcher released the lockstep holds at or before sim ``at_ns`` (a plant
        made with ``holds_ns``, which only lockstep has)."""
        assert isinstance(self.pacer, LockstepPacer), "holds are lockstep's"
        self.pacer.release(at_ns)

    def on_command(self, rec: np.ndarray, rx_ns: int) -> None:
        """A JOINT_COMMAND for this arm arrived at ``rx_ns`` (on a Zenoh thread)."""
        self.pacer.on_command(rec, rx_ns)

    def on_task_done(self, step: int) -> None:
        """The operator's TASK_DONE: the run ends at tick ``step``."""
        self.core.on_task_done(step)

    def run(self, stop: threading.Event, steps: int | None) -> None:
        """One run of ``steps`` steps (None: until stopped) from the initial configuration,
        or from the store's checkpoint if there is one (a restart); ``core.finished`` says
        whether it ran to its end (not stopped, not aborted)."""
        core = self.core
        resumed = core.start_or_resume(steps)
        if core.aborted:
            return
        if core.finished:  # restarted after the end: the run stays over
            core.publish_event(Event.FINISHED)
            return
        start_ns = core.clock.now_ns()
        self.pacer.run(stop, resumed=resumed)
        core.end_run(stop, start_ns, resumed)

    def summary(self) -> dict[str, Any]:
        """The run's figures (the plant service's summary, less the service's own)."""
        return self.core.summary(self.pacer.figures())

    def save_shed_log(self, path: Path) -> None:
        """Write the commands shed or dropped this run to ``path``."""
        self.core.save_shed_log(path)
