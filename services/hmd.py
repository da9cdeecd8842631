"""The HMD service: :class:`teleop.devices.hmd.HmdLoop` on the bus.

The plant's TOOL_POSE stream (``plant.scene_rate_hz``, 100 Hz) is this service's clock and
nothing else: each arrival's tick goes to the loop, which samples, filters and predicts
every HMD sample tick up to it, and each sample goes out as a HEAD_POSE record valid from
``tick + lead_ticks``. Clocking on the scene stream instead of the 1 kHz PLANT_STATE gives
the same records at a tenth of the wake-ups. Being driven by plant ticks, the same code
serves realtime and lockstep, and the output depends only on the config and the seed.

Consumers pick the record that applies at their tick with
:meth:`teleop.devices.hmd.HmdSchedule.valid_from_for`, e.g. stored in a
:class:`teleop.core.ticks.TickedInputs`.
"""

from __future__ import annotations

import sys
import threading
import time
from typing import Any

import numpy as np

from teleop.bus.messages import HEAD_POSE
from teleop.bus.service import Service, service_main
from teleop.bus.session import Publisher
from teleop.core.clock import NS_PER_S
from teleop.devices.hmd import HmdLoop, fill_head_pose


class HmdService(Service):
    name = "hmd"

    def open(self) -> None:
        super().open()
        assert self.session is not None
        self.loop = HmdLoop(self.config)
        self.timestep_ns = round(self.config.plant.timestep_s * NS_PER_S)
        self.pose_pub = self.keep(Publisher.for_stream(self.session, self.topics, "head_pose"))
        self._record = HEAD_POSE.new()
        self._lock = threading.Lock()
        self.published = 0
        self.subscribe_stream("tool_pose", self._on_clock)
        self.announce()

    def _on_clock(self, rec: np.ndarray, rx_ns: int) -> None:
        """Plant tick ``m``: publish every HMD sample up to ``m``."""
        tick = int(rec["sim_time_ns"]) // self.timestep_ns
        with self._lock:
            for sample in self.loop.on_clock(tick):
                fill_head_pose(
                    self._record, sample, self.published, time.monotonic_ns(), self.timestep_ns
                )
                self.published += 1
                self.pose_pub.put(self._record)

    def run(self, stop: threading.Event) -> None:
        """The work happens in the clock's callback; this thread only waits to be stopped."""
        stop.wait()

    def summary(self) -> dict[str, Any]:
        """Samples and RMS errors vs the scripted truth (m, rad), for the current run."""
        with self._lock:
            return {
                **super().summary(),
                **self.loop.emulator.summary(),
                "published": self.published,
                "runs": self.loop.runs,
                "resent_states": self.loop.resent_states,
            }


if __name__ == "__main__":
    sys.exit(service_main(HmdService))
