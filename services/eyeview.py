"""The operator's eye view: the scene rendered from the HMD's predicted pose.

:class:`teleop.viz.eyeview.EyeRenderer` is the renderer (no bus); :class:`EyeViewService`
is its bus adapter: it drives the renderer at ``eyeview.rate_hz`` of wall-clock time and
publishes EYE_VIEW frames. A frame (320 x 240 RGB: 230 kB) is far above the SHM
threshold, so it always takes the shared-memory path.

Why a process of its own and not a render thread inside the plant (see
docs/eye-view.md): MuJoCo's renderer does release the GIL while it draws, but a
software-GL frame still costs milliseconds of CPU in llvmpipe threads that would share
the plant's scheduling priority, and any Python work around it (state copy, encoding,
the Zenoh put) holds the GIL that the plant's 1 kHz loop needs. A separate process runs
at ``eyeview.nice`` (below the control loops), cannot stall or crash the plant, and
leaves the plant's realtime path untouched. It mirrors the plant from PLANT_STATE (taken
at ``eyeview.state_rate_hz`` through Zenoh ingress downsampling, so the 1 kHz stream
costs no Python wake-ups) and OBJECT_POSES.

The view follows the newest HEAD_POSE (predicted position, yaw and pitch: the pose the
operator's head will have when the frame is seen), and each frame waits for the next
HEAD_POSE (at most 1.5 HMD periods) so that it renders the freshest one; without one
(path following has no HMD) it uses the fixed viewpoint of the config. Frames are paced
on wall-clock time in both timing modes: the eye view is for watching, not part of a
reproducible run.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from typing import Any

import numpy as np

import shm
from teleop.bus.messages import (
    EYE_VIEW,
    PLANT_STATE,
    RGB_CHANNELS,
    DecodeError,
    Kind,
    Reason,
)
from teleop.bus.service import Service, lower_priority_to, service_main
from teleop.bus.session import Latest, open_session, subscribe
from teleop.core.clock import NS_PER_S, LoopTimer, MonotonicClock
from teleop.core.config import ConfigError
from teleop.core.ring import Ring
from teleop.viz.eyeview import EyeRenderer

logger = logging.getLogger(__name__)

NS_PER_MS = 1_000_000
# With an HMD, a frame waits for the next HEAD_POSE (so it shows the freshest head pose,
# not one that aged while the frame waited for its deadline) for at most this many HMD
# periods; then it renders with the pose it has.
HEAD_WAIT_PERIODS = 1.5
# The SHM pool must hold this many frames at once (the one being written, those the
# recorder has not released yet), else publishing would block on the pool.
FRAMES_IN_FLIGHT = 4
# Render-time samples kept for the summary's percentiles (the newest ones).
RENDER_TIME_SAMPLES = 4096


def lower_priority(nice: int, idle: bool) -> None:
    """Put this thread (and the threads it starts later: GL, Zenoh) below the control loops.

    ``idle``: Linux SCHED_IDLE, which any normal task preempts at once when it wakes, so a
    render never delays a 1 kHz wake-up (but gets only CPU time nobody else wants);
    otherwise ``nice`` (0-19). The service uses ``nice``: a starved SCHED_IDLE process
    would also starve its Zenoh threads, and a peer that stops reading back-pressures
    the plant's BLOCK publishers (the placement benchmark compares both).
    """
    if idle:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    else:
        lower_priority_to(nice)


class EyeViewService(Service):
    """Renders the eye view at ``eyeview.rate_hz`` and publishes EYE_VIEW frames."""

    name = "eyeview"

    def open(self) -> None:
        eye = self.config.eyeview
        frame_bytes = EYE_VIEW.frame_bytes(eye.width_px, eye.height_px)
        if self.config.bus.shm and frame_bytes * FRAMES_IN_FLIGHT > self.config.bus.shm_pool_bytes:
            raise ConfigError(
                f"eyeview: a {eye.width_px} x {eye.height_px} frame ({frame_bytes} B) needs "
                f"bus.shm_pool_bytes >= {frame_bytes * FRAMES_IN_FLIGHT}"
            )
        lower_priority(eye.nice, idle=False)
        # Built before the session: if the model or the GL context fails, nothing is open.
        self.renderer = EyeRenderer(self.config)
        # PLANT_STATE is a 1 kHz stream: its observers' copy comes several states per
        # message, and of those only what the frames need gets in.
        self.session = open_session(
            self.config.bus,
            listen=self.options.listen,
            ingress_rate_hz=(
                {self.topics.plant_state_batch: eye.state_rate_hz} if eye.state_rate_hz else None
            ),
        )
        self.states = Latest()
        self.objects = Latest()
        self.heads = Latest()
        self.keep(
            subscribe(
                self.session,
                self.topics.plant_state_batch,
                PLANT_STATE,
                self._on_state,
                self.drops,
                batched=True,
            )
        )
        self.subscribe_stream("objects", self.objects)
        self.subscribe_stream("head_pose", self.heads)
        # Within the locked-memory limit: a smaller pool, or the socket path (counted in
        # the summary's shm_pool) when not even FRAMES_IN_FLIGHT frames fit.
        provider, self.pool = None, None
        if self.config.bus.shm:
            provider, self.pool = shm.open_provider(
                self.config.bus.shm_pool_bytes, frame_bytes * FRAMES_IN_FLIGHT
            )
            if self.pool.reason:
                logger.warning("shared memory: %s", self.pool.reason)
        # A viewer stream (teleop.bus.graph): dropped rather than blocking a slow receiver.
        self.frame_pub = self.publish_stream("eye_view", shm=provider)
        self._frame = EYE_VIEW.new()
        self._frame["width_px"] = eye.width_px
        self._frame["height_px"] = eye.height_px
        self._frame["channels"] = RGB_CHANNELS
        self._frame["fov_y_rad"] = eye.fov_y_rad
        self.frames_published = 0
        self.frames_without_state = 0  # ticks before the first PLANT_STATE
        self.frames_from_hmd = 0
        self._render_ns = Ring(RENDER_TIME_SAMPLES)
        self.timer: LoopTimer | None = None
        self._cpu_start_s = time.process_time()
        self._wall_start_ns = time.monotonic_ns()
        self.announce()

    def _on_state(self, rec: np.ndarray, rx_ns: int) -> None:
        """Keep states of exactly this arm; anything else is counted and dropped."""
        n = int(rec["n_joints"])
        if n != self.renderer.n_joints:
            detail = f"n_joints={n}, arm has {self.renderer.n_joints}"
            self.drops.record(DecodeError(Kind.PLANT_STATE, Reason.COUNT, detail))
            return
        self.states(rec, rx_ns)

    def run(self, stop: threading.Event) -> None:
        period_ns = round(NS_PER_S / self.config.eyeview.rate_hz)
        self.timer = LoopTimer(period_ns, MonotonicClock())
        head_wait_s = HEAD_WAIT_PERIODS / self.config.hmd.rate_hz
        while not stop.is_set():
            self.timer.wait()
            newest = self.heads.get()
            if newest is not None:  # an HMD is running: render for its next sample
                self.heads.wait_newer(int(newest[0]["seq"]), head_wait_s)
            self.render_once()

    def render_once(self) -> bool:
        """Render and publish one frame from the newest state and head pose; False if
        no state has arrived yet."""
        latest = self.states.get()
        if latest is None:
            self.frames_without_state += 1
            return False
        state, _ = latest
        # Inputs are taken before the render's start stamp, so a head pose arriving while
        # this frame renders belongs to the next frame: head_rx_ns <= render_start_ns.
        objects = self.objects.get()
        head = self.heads.get()
        n = self.renderer.n_joints
        start_ns = time.monotonic_ns()
        rec = self._frame
        if objects is not None:
            k = int(objects[0]["n_objects"])
            self.renderer.set_state(
                state["q_rad"][:n],
                float(state["gripper_opening_m"]),
                objects[0]["world_p_m"][:k],
                objects[0]["world_q_wxyz"][:k],
            )
        else:
            self.renderer.set_state(state["q_rad"][:n], float(state["gripper_opening_m"]))
        eye = self.config.eyeview
        if head is not None:
            pose, head_rx_ns = head
            p_m, yaw, pitch = (
                pose["predicted_p_m"],
                float(pose["predicted_yaw_rad"]),
                float(pose["predicted_pitch_rad"]),
            )
            rec["head_seq"] = pose["seq"]
            rec["head_t_source_ns"] = pose["t_source_ns"]
            rec["head_rx_ns"] = head_rx_ns
            self.frames_from_hmd += 1
        else:
            p_m, yaw, pitch = np.asarray(eye.fixed_p_m), eye.fixed_yaw_rad, eye.fixed_pitch_rad
            rec["head_seq"] = 0
            rec["head_t_source_ns"] = 0
            rec["head_rx_ns"] = 0
        pixels = self.renderer.render(p_m, yaw, pitch)
        end_ns = time.monotonic_ns()
        self._render_ns.append(end_ns - start_ns)
        rec["seq"] = self.frames_published
        rec["t_source_ns"] = start_ns
        rec["sim_time_ns"] = state["sim_time_ns"]
        rec["state_seq"] = state["seq"]
        rec["render_start_ns"] = start_ns
        rec["render_end_ns"] = end_ns
        rec["world_p_eye_m"] = p_m
        rec["yaw_rad"] = yaw
        rec["pitch_rad"] = pitch
        rec["publish_ns"] = time.monotonic_ns()
        if not self.frame_pub.put_bytes(EYE_VIEW.encode_frame(rec, pixels)):
            return True  # the pool is full: counted in frames_dropped_pool_full
        self.frames_published += 1
        return True

    def close(self) -> None:
        renderer = getattr(self, "renderer", None)
        try:
            super().close()
        finally:
            if renderer is not None:
                renderer.close()
                self.renderer = None

    def summary(self) -> dict[str, Any]:
        """Frames, render time (ms), the loop's statistics and this process's CPU share."""
        p50_ns, p99_ns = self._render_ns.percentiles([50, 99]) or (0.0, 0.0)
        p50, p99 = p50_ns / NS_PER_MS, p99_ns / NS_PER_MS
        wall_s = (time.monotonic_ns() - self._wall_start_ns) / NS_PER_S
        cpu_s = time.process_time() - self._cpu_start_s
        eye = self.config.eyeview
        return {
            **super().summary(),
            "frames_published": self.frames_published,
            "frames_from_hmd": self.frames_from_hmd,
            "frames_dropped_pool_full": self.frame_pub.dropped_pool_full
            if hasattr(self, "frame_pub")
            else 0,
            "frames_without_state": self.frames_without_state,
            "states_received": self.states.count,
            "frame_bytes": EYE_VIEW.frame_bytes(eye.width_px, eye.height_px),
            "shm_pool": self.pool.as_dict() if getattr(self, "pool", None) else None,
            "render_ms_p50": float(p50),
            "render_ms_p99": float(p99),
            "loop": self.timer.summary() if self.timer is not None else {},
            "cpu_time_s": cpu_s,
            "wall_time_s": wall_s,
            "cpu_share": cpu_s / wall_s if wall_s > 0 else 0.0,
        }


if __name__ == "__main__":
    sys.exit(service_main(EyeViewService))
