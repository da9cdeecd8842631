"""The HMD service: head pose at ``hmd.rate_hz`` of sim time, filtered and predicted.

The plant's JOINT_STATE stream is this service's clock and nothing else: on every plant
tick ``k`` where the HMD samples (:func:`teleop.ticks.is_sample_tick`), the JOINT_STATE
callback runs :class:`teleop.hmd.HmdEmulator` (scripted pose at ``t = k * timestep``,
tracker noise, one Kalman update, one prediction) and publishes a HEAD_POSE record
valid from tick ``k + lead_ticks``. A few small matrix products at 90 Hz cost far less
than a hand-off to a thread, so the work stays in the callback, as in the controller.

Being driven by plant ticks, the same code serves realtime and lockstep, and the output
depends only on the config and the seed, not on wall-clock timing. A re-sent state
(lockstep re-sends an unanswered one with the same seq) is ignored; seq 0 after a later
seq is a new run and resets the filter and statistics (the tracker noise is keyed by
(seed, tick), so the same seed gives the same records again).

Consumers pick the record that applies at their tick with
:meth:`teleop.hmd.HmdSchedule.valid_from_for` (= ``expected_valid_from(tick, rate_hz,
timestep_s, lead_ticks)``), e.g. stored in a :class:`teleop.ticks.TickedInputs`.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import numpy as np

from teleop.bus import Publisher, subscribe
from teleop.clock import NS_PER_S
from teleop.hmd import HeadSample, HmdEmulator
from teleop.messages import HEAD_POSE, JOINT_STATE
from teleop.service import Service

logger = logging.getLogger(__name__)


class HmdService(Service):
    name = "hmd"

    def open(self) -> None:
        super().open()
        assert self.session is not None
        self.emulator = HmdEmulator(self.config)
        self.timestep_ns = round(self.config.plant.timestep_s * NS_PER_S)
        self.pose_pub = self.keep(Publisher.declare(self.session, self.topics.head_pose, HEAD_POSE))
        self._record = HEAD_POSE.new()
        self._lock = threading.Lock()
        self._last_seq = -1
        self.published = 0
        self.resent_states = 0  # JOINT_STATE seqs seen before (lockstep re-sends)
        self.skipped_states = 0  # gaps in the JOINT_STATE seqs (ticks never seen)
        self.runs = 0
        self.keep(
            subscribe(
                self.session, self.topics.joint_state, JOINT_STATE, self._on_state, self.drops
            )
        )
        self.announce()

    def _on_state(self, rec: np.ndarray, rx_ns: int) -> None:
        """One plant tick: sample, filter and publish on the HMD's sample ticks."""
        with self._lock:
            seq = int(rec["seq"])
            if seq == 0 and self._last_seq != 0:
                if self._last_seq > 0:  # a new run: start from a fresh filter
                    self.emulator.reset()
                self.runs += 1
            elif seq <= self._last_seq:
                self.resent_states += 1
                return
            elif self._last_seq >= 0 and seq > self._last_seq + 1:
                self.skipped_states += seq - self._last_seq - 1
            self._last_seq = seq
            sample = self.emulator.on_tick(int(rec["step"]))
            if sample is not None:
                self._publish(sample)

    def _publish(self, sample: HeadSample) -> None:
        rec = self._record
        self.published += 1
        rec["seq"] = self.published - 1
        rec["t_source_ns"] = time.monotonic_ns()
        rec["sim_time_ns"] = sample.tick * self.timestep_ns
        rec["valid_from_tick"] = sample.valid_from_tick
        rec["measured_p_m"] = sample.measured.p_m
        rec["measured_yaw_rad"] = sample.measured.yaw_rad
        rec["filtered_p_m"] = sample.filtered.p_m
        rec["predicted_p_m"] = sample.predicted.p_m
        rec["predicted_yaw_rad"] = sample.predicted.yaw_rad
        rec["predicted_pitch_rad"] = sample.predicted.pitch_rad
        rec["horizon_s"] = sample.horizon_s
        self.pose_pub.put(rec)

    def run(self, stop: threading.Event) -> None:
        """The work happens in the state callback; this thread only waits to be stopped."""
        stop.wait()

    def summary(self) -> dict[str, Any]:
        """Samples and RMS errors vs the scripted truth (m, rad), for the current run."""
        with self._lock:
            return {
                **super().summary(),
                **self.emulator.summary(),
                "published": self.published,
                "runs": self.runs,
                "resent_states": self.resent_states,
                "skipped_states": self.skipped_states,
            }
