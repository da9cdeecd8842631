"""The HMD service: :class:`teleop.devices.hmd.HmdLoop` on the bus.

The plant's TOOL_POSE stream (``plant.scene_rate_hz``, 100 Hz) is this service's clock and
nothing else: each arrival's tick goes to the loop, which samples, filters and predicts
every HMD sample tick up to it, and each sample goes out as a HEAD_POSE record valid from
``tick + lead_ticks``. Clocking on the scene stream instead of the 1 kHz PLANT_STATE gives
the same records at a tenth of the wake-ups. Being driven by plant ticks, the same code
serves realtime and lockstep, and the output depends only on the config and the seed.

Consumers pick the record that applies at their tick with
``valid_from_for`` of :func:`teleop.core.ticks.head_schedule`, e.g. stored in a
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
from teleop.bus.session import RecordCallback
from teleop.core.clock import NS_PER_S
from teleop.devices.hmd import HmdLoop, fill_head_pose


class HmdService(Service):
    name = "hmd"

    def open(self) -> None:
        super().open()
        assert self.session is not None
        self.loop = HmdLoop(self.config)
        self.timestep_ns = round(self.config.tick_s * NS_PER_S)
        # One head, every robot's keys (a run of several robots): each robot's controller
        # and operator take the head pose from their own robot's stream.
        self.pose_pubs = [self.publish_stream("head_pose", topics) for topics in self.robot_topics]
        self._record = HEAD_POSE.new()
        self._lock = threading.Lock()
        self.published = 0
        for robot, topics in enumerate(self.robot_topics):
            self.subscribe_stream("tool_pose", self._on_clock(robot), topics)
        self.announce()

    def _on_clock(self, robot: int) -> RecordCallback:
        """Plant tick ``m`` of ``robot``: publish every HMD sample up to ``m``. Every
        robot's poses clock the HMD (one whose task is over stops sending); only robot
        0's tick 0 starts a run (another robot's, late, would restart it), and under
        several robots a tick another robot brought first is no re-send (the loop's
        ``resent_states`` counts none of them)."""
        several = len(self.robot_topics) > 1

        def on_clock(rec: np.ndarray, rx_ns: int) -> None:
            tick = int(rec["sim_time_ns"]) // self.timestep_ns
            with self._lock:
                if robot and tick == 0:
                    return  # robot 0 starts a run
                if several and tick > 0 and tick <= self.loop.last_tick:
                    return  # another robot brought this tick first: no re-send
                for sample in self.loop.on_clock(tick):
                    fill_head_pose(
                        self._record, sample, self.published, time.monotonic_ns(), self.timestep_ns
                    )
                    self.published += 1
                    for pub in self.pose_pubs:
                        pub.put(self._record)

        return on_clock

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
