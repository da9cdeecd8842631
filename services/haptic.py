"""The haptic service: one device step per plant tick, in realtime or lockstep.

Inputs: FORCE_FEEDBACK (the force to render, from the controller), HAND_INPUT (where the
operator's hand pulls the handle, keyed by the plant tick it applies from) and, in
lockstep, PLANT_STATE, used only as the simulation clock (its ``seq`` is the plant
tick). Output: HAPTIC_STATE per step, with the encoder position, the Kalman velocity and
the force actually rendered, in the device frame, and the deadline of the device period
it was sampled in (the realtime plant steps on that clock).

- realtime: a :class:`LoopTimer` at the plant period steps the device on wall-clock
  deadlines with the newest feedback (faded out by :class:`FeedbackHold` when stale) and
  the hand input valid at the newest plant tick seen. The tick and sim time are those
  of the newest feedback (the state it answers, at most a period or two old): a 1 kHz
  PLANT_STATE subscription only for that cost this service and the plant a message
  each per period. A feedback tick below the last one means the plant started over (a
  new run). Each feedback force is handed to
  the motors the moment it arrives (``haptic.render_on_arrival``; else at the next step)
  and its trace, completed with FEEDBACK_RX and FEEDBACK_RENDERED, is kept for the
  latency report (written to ``<run dir>/haptic.trace.npy`` at exit).
- lockstep: deterministic and event driven. Tick k steps once PLANT_STATE k, the
  FORCE_FEEDBACK of tick k-1 (k >= 1) and the HAND_INPUT that applies at k (if any) are
  all in; the callback that completes the set does the step (no thread hand-off, as in the
  plant). A hand input still missing after ``HAND_INPUT_WAIT_S`` means there is no
  operator: log once and go on without waiting for hand inputs until one arrives.

Lockstep: a PLANT_STATE seq 0 with a new ``t_source_ns`` (or as the first state) starts
a new run: the handle goes back to the centre at rest and every stored input is
forgotten. A state with a seq already seen is a plant re-send (nobody answered it; the
plant re-sends every state in flight byte for byte, so a re-sent state 0 keeps its
stamp): it never steps the device again; if it names the tick last stepped, that tick's
HAPTIC_STATE is sent again unchanged (same seq), in case the first copy was lost to a
late subscriber.
"""

from __future__ import annotations

import logging
import math
import sys
import threading
import time
from typing import Any

import numpy as np

from teleop.bus.messages import (
    FORCE_FEEDBACK,
    HAND_INPUT,
    HAPTIC_STATE,
    N_STAGES,
    PLANT_STATE,
    Button,
    Flag,
    Stage,
)
from teleop.bus.service import STOP_POLL_S, Service, service_main
from teleop.bus.session import BatchPublisher, Publisher, subscribe
from teleop.bus.stamps import SHED_AGE_NS, SeqCheck, StampLog
from teleop.core.clock import NS_PER_S, LoopTimer, MonotonicClock
from teleop.core.rundir import HAPTIC_SAMPLES_FILE, HAPTIC_TRACE_FILE, shed_path
from teleop.core.ticks import TickedInputs, expected_valid_from
from teleop.devices.haptic import (
    DeviceSample,
    EmulatedDevice,
    FeedbackHold,
    max_stable_stiffness_n_per_m,
)

logger = logging.getLogger(__name__)

# Lockstep: how long a tick waits for its hand input before the operator counts as absent (s).
HAND_INPUT_WAIT_S = 1.0
# Feedback whose norm exceeds this multiple of the peak force is garbage, not a saturation case.
OVERSIZED_FEEDBACK_FACTOR = 10.0
# Lockstep feedback records kept by tick (a few ahead of the device is all that can happen).
FEEDBACK_KEEP = 64


class HapticService(Service):
    name = "haptic"

    def open(self) -> None:
        super().open()
        assert self.session is not None
        cfg = self.config
        self.period_s = cfg.plant.timestep_s
        self.period_ns = round(self.period_s * NS_PER_S)
        self.lockstep = cfg.run.mode == "lockstep"
        self.hand_rate_hz = cfg.operator.decision_rate_hz
        self.lead_ticks = round(1.0 / (self.hand_rate_hz * self.period_s))
        self.max_feedback_n = OVERSIZED_FEEDBACK_FACTOR * cfg.haptic.peak_force_n
        self.device = EmulatedDevice(cfg.haptic, self.period_s)
        self.hold = FeedbackHold(cfg.haptic.stale_feedback_s, cfg.haptic.fade_s)
        self.hand_inputs = TickedInputs()
        self.timer: LoopTimer | None = None
        # Everything below is shared by the Zenoh callbacks and the run thread.
        self._cond = threading.Condition()
        self._state_seq = -1  # newest PLANT_STATE seq of this run; -1: none yet
        self._run_start_ns = -1  # t_source_ns of this run's state 0 (a re-send repeats it)
        self._state_sim_ns = 0  # its sim_time_ns
        self._first_tick = 0  # first tick of the run this service saw (joined mid-run: > 0)
        self._last_tick = -1  # lockstep: last tick stepped
        self._feedback: dict[int, np.ndarray] = {}  # lockstep: device_f_n by tick
        self._hand_blocked_since_ns: int | None = None  # lockstep: tick waits for its hand
        self._operator_absent = False
        self._last_missing_valid_from: int | None = None
        self._record = HAPTIC_STATE.new()
        # Counters for the summary.
        self.steps = 0
        self.runs = 0
        self.lockstep_waits = 0
        self.missing_hand_inputs = 0
        self.oversized_feedback = 0
        self.republished_states = 0
        self.max_force_n = 0.0
        self.max_abs_position_m = 0.0
        # Realtime latency bookkeeping (stamps of the bilateral loop, feedback stream order).
        self.render_on_arrival = cfg.haptic.render_on_arrival
        self.trace_log = StampLog(N_STAGES)
        self.sample_log = StampLog(2)  # (HAPTIC_STATE seq, HAPTIC_SAMPLE ns)
        self._pending_trace: np.ndarray | None = None  # render at the next step
        self.feedback_seq = SeqCheck()  # FORCE_FEEDBACK gaps and reordering (realtime)
        self.feedback_superseded = 0  # replaced before the next step rendered it
        self.feedback_shed = 0  # too old on arrival (this service was behind): not rendered
        self.shed_log = StampLog(1)  # HAPTIC_SAMPLE stamps of the loops shed here
        self._warned_oversized = False
        self._warned_no_operator = False

        self.state_pub = self.keep(
            Publisher.declare(self.session, self.topics.haptic_state, HAPTIC_STATE)
        )
        self.state_batch = self.keep(  # the recorder's copy, several samples per message
            BatchPublisher.declare(
                self.session,
                self.topics.haptic_state_batch,
                HAPTIC_STATE,
                cfg.bus.observer_batch_records,
            )
        )
        topics, drops = self.topics, self.drops
        self.keep(
            subscribe(self.session, topics.force_feedback, FORCE_FEEDBACK, self._on_feedback, drops)
        )
        self.keep(subscribe(self.session, topics.hand_input, HAND_INPUT, self._on_hand, drops))
        if self.lockstep:  # realtime: the feedback's tick is the clock (see the docstring)
            self.keep(
                subscribe(self.session, topics.plant_state, PLANT_STATE, self._on_state, drops)
            )
        logger.info(
            "%s mode; stiffness a feedback law may render: K_max = 2 b / T = %.0f N/m",
            self.config.run.mode,
            max_stable_stiffness_n_per_m(cfg.haptic, self.period_s),
        )
        self.announce()

    # -- callbacks ---------------------------------------------------------------------
    def _on_state(self, rec: np.ndarray, rx_ns: int) -> None:
        seq = int(rec["seq"])
        with self._cond:
            if seq == 0 and int(rec["t_source_ns"]) != self._run_start_ns:
                self._run_start_ns = int(rec["t_source_ns"])
                self._new_run()
            elif seq <= self._state_seq:
                if self.lockstep and seq == self._last_tick:
                    self.republished_states += 1
                    self.state_pub.put(self._record)
                return
            elif self._state_seq < 0:  # joined a run already under way
                self._first_tick = seq
                self._last_tick = seq - 1
            self._state_seq = seq
            self._state_sim_ns = int(rec["sim_time_ns"])
            if self.lockstep:
                self._try_steps()
                if self._last_tick < seq:
                    self.lockstep_waits += 1

    def _on_feedback(self, rec: np.ndarray, rx_ns: int) -> None:
        force = np.array(rec["device_f_n"], dtype=np.float64)
        force_norm_n = math.hypot(*force.tolist())
        if force_norm_n > self.max_feedback_n:
            with self._cond:
                self.oversized_feedback += 1
                first = not self._warned_oversized
                self._warned_oversized = True
            if first:
                logger.warning(
                    "dropping feedback of %.3g N (> %g x peak); further ones are only counted",
                    force_norm_n,
                    OVERSIZED_FEEDBACK_FACTOR,
                )
            return
        with self._cond:
            if not self.lockstep:
                self._feedback_realtime(rec, force, rx_ns)
                return
            tick = int(rec["tick"])
            if tick < self._last_tick:
                return  # late: its step has been taken
            self._feedback[tick] = force
            if len(self._feedback) > FEEDBACK_KEEP:
                del self._feedback[min(self._feedback)]
            self._try_steps()

    def _on_hand(self, rec: np.ndarray, rx_ns: int) -> None:
        self.hand_inputs.put(int(rec["valid_from_tick"]), rec)
        with self._cond:
            self._operator_absent = False
            if self.lockstep:
                self._try_steps()

    def _feedback_realtime(self, rec: np.ndarray, force: np.ndarray, rx_ns: int) -> None:
        """Hold the force; render it now or at the next step; keep its trace (lock held)."""
        if not self.feedback_seq.accept(int(rec["seq"])):
            return  # older than what the handle already feels
        if time.monotonic_ns() - int(rec["trace_ns"][Stage.FEEDBACK_TX]) > SHED_AGE_NS:
            self.feedback_shed += 1  # a backlog: a newer force is right behind it
            if int(rec["trace_ns"][Stage.HAPTIC_SAMPLE]) > 0:
                self.shed_log.append((int(rec["trace_ns"][Stage.HAPTIC_SAMPLE]),))
            return
        tick = int(rec["tick"])
        if tick < self._state_seq:  # the plant started over: a new run
            self._new_run()
        elif self._state_seq < 0:  # this service's first feedback: the run is under way
            self.runs += 1
        self._state_seq = tick
        self._state_sim_ns = int(rec["sim_time_ns"])
        self.hold.receive(force, rx_ns)
        trace = np.array(rec["trace_ns"])
        trace[Stage.FEEDBACK_RX] = rx_ns
        if self.render_on_arrival:
            self.device.render(force)
            trace[Stage.FEEDBACK_RENDERED] = time.monotonic_ns()
            self.trace_log.append(trace)
        else:
            if self._pending_trace is not None:
                self.feedback_superseded += 1
            self._pending_trace = trace

    # -- run boundaries ----------------------------------------------------------------
    def _new_run(self) -> None:
        """Handle to the centre at rest, inputs forgotten (caller holds the lock)."""
        self.device.reset()
        self.hold.clear()
        self.hand_inputs.clear()
        self._feedback.clear()
        self._first_tick = 0
        self._last_tick = -1
        self._hand_blocked_since_ns = None
        self._operator_absent = False
        self._last_missing_valid_from = None
        self.runs += 1

    # -- lockstep ----------------------------------------------------------------------
    def _hand_for(self, tick: int) -> tuple[np.ndarray | None, bool]:
        """(hand input that applies at ``tick`` or None, still waiting for it)."""
        valid_from = expected_valid_from(tick, self.hand_rate_hz, self.period_s, self.lead_ticks)
        if valid_from is None:
            return None, False  # before the operator's first input can apply
        rec = self.hand_inputs.wait_for(valid_from, 0.0)
        if rec is not None:
            return rec, False
        if not self._operator_absent:
            return None, True
        if valid_from != self._last_missing_valid_from:
            self._last_missing_valid_from = valid_from
            self.missing_hand_inputs += 1
        return self.hand_inputs.latest_at(tick), False  # keep the last hand pose, if any

    def _try_steps(self) -> None:
        """Step every tick whose inputs are all in, in order (caller holds the lock)."""
        while True:
            tick = self._last_tick + 1
            if tick > self._state_seq:
                return
            force = self._feedback.get(tick - 1)
            if force is None and tick > self._first_tick:
                return
            hand, waiting = self._hand_for(tick)
            if waiting:
                if self._hand_blocked_since_ns is None:
                    self._hand_blocked_since_ns = time.monotonic_ns()
                    self._cond.notify_all()  # the run thread times the wait
                return
            self._hand_blocked_since_ns = None
            t_ns = tick * self.period_ns
            if force is not None:
                self.hold.receive(force, t_ns - self.period_ns)
                del self._feedback[tick - 1]
            sim_ns = self._state_sim_ns - (self._state_seq - tick) * self.period_ns
            sample = self._step(tick, sim_ns, hand, t_ns)
            self._publish_sample()
            self._account_sample(sample)
            self._last_tick = tick

    def _run_lockstep(self, stop: threading.Event) -> None:
        """Steps happen in the callbacks; this thread only times out a missing hand input."""
        wait_ns = round(HAND_INPUT_WAIT_S * NS_PER_S)
        with self._cond:
            while not stop.is_set():
                timeout_s = STOP_POLL_S
                since_ns = self._hand_blocked_since_ns
                if since_ns is not None:
                    left_ns = since_ns + wait_ns - time.monotonic_ns()
                    if left_ns <= 0:
                        self._give_up_on_hand()
                        continue
                    timeout_s = min(timeout_s, left_ns / NS_PER_S)
                self._cond.wait(timeout_s)

    def _give_up_on_hand(self) -> None:
        """No hand input for HAND_INPUT_WAIT_S: go on without an operator (lock held)."""
        if not self._warned_no_operator:
            self._warned_no_operator = True
            logger.warning(
                "no HAND_INPUT for tick %d after %g s: no operator, stepping without one",
                self._last_tick + 1,
                HAND_INPUT_WAIT_S,
            )
        self._operator_absent = True
        self._hand_blocked_since_ns = None
        self._try_steps()

    # -- realtime ----------------------------------------------------------------------
    def _run_realtime(self, stop: threading.Event) -> None:
        self.timer = LoopTimer(self.period_ns, MonotonicClock())
        self._first_wake_ns = 0
        while not stop.is_set():
            deadline_ns = self.timer.deadline_ns(self.timer.wait())
            if self.timer.count == 1:
                self._first_wake_ns = self.timer.last_wake_ns
            with self._cond:
                tick = max(self._state_seq, 0)
                hand = self.hand_inputs.latest_at(tick) if self._state_seq >= 0 else None
                sample = self._step(
                    tick, self._state_sim_ns, hand, time.monotonic_ns(), deadline_ns
                )
            # Outside the lock: a feedback that arrives meanwhile is rendered at once.
            self._publish_sample()
            self._account_sample(sample)

    # -- shared ------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        if self.lockstep:
            self._run_lockstep(stop)
        else:
            self._run_realtime(stop)
        logger.info("stopped: %s", self.summary())

    def _step(
        self,
        tick: int,
        sim_time_ns: int,
        hand: np.ndarray | None,
        t_ns: int,
        deadline_ns: int = 0,
    ) -> DeviceSample:
        """Render, integrate one period, sample into the HAPTIC_STATE record (caller holds
        the lock; :meth:`_publish_sample` sends it, then :meth:`_account_sample` counts the
        returned sample: the statistics wait until the sample is on its way).

        ``t_ns`` is the feedback clock (monotonic in realtime, sim time in lockstep);
        ``deadline_ns`` the device period's start in realtime (the plant steps on it),
        0 in lockstep.
        """
        force, stale = self.hold.force_at(t_ns)
        self.device.render(force)
        if self._pending_trace is not None:
            self._pending_trace[Stage.FEEDBACK_RENDERED] = time.monotonic_ns()
            self.trace_log.append(self._pending_trace)
            self._pending_trace = None
        if hand is None:
            self.device.step(self.period_s, None, Button.NONE)
        else:
            self.device.step(self.period_s, hand["target_p_m"], Button(int(hand["buttons"])))
        sample = self.device.read()
        sample_ns = time.monotonic_ns()
        self.steps += 1
        rec = self._record
        rec["seq"] = self.steps
        rec["flags"] = Flag.STALE if stale else Flag.NONE
        rec["t_source_ns"] = sample_ns
        rec["trace_ns"][:] = 0
        rec["trace_ns"][Stage.HAPTIC_SAMPLE] = sample_ns
        rec["sim_time_ns"] = sim_time_ns
        rec["tick"] = tick
        rec["device_deadline_ns"] = deadline_ns
        rec["device_p_m"] = sample.p_m
        rec["device_v_m_s"] = sample.v_m_s
        rec["device_f_n"] = sample.f_n
        rec["buttons"] = int(sample.buttons)
        return sample

    def _account_sample(self, sample: DeviceSample) -> None:
        """Statistics of the sample just published (and its stamp, in realtime)."""
        self.max_force_n = max(self.max_force_n, math.hypot(*sample.f_n.tolist()))
        self.max_abs_position_m = max(self.max_abs_position_m, *map(abs, sample.p_m.tolist()))
        if not self.lockstep:
            rec = self._record
            self.sample_log.append((int(rec["seq"]), int(rec["trace_ns"][Stage.HAPTIC_SAMPLE])))

    def _publish_sample(self) -> None:
        """Send the HAPTIC_STATE the last :meth:`_step` filled in (one thread at a time:
        lockstep steps under the lock, realtime only in the run thread)."""
        self.state_batch.add(self.state_pub.put(self._record))

    def close(self) -> None:
        device = getattr(self, "device", None)  # None if open() failed before building it
        if device is not None:
            device.close()
        run_dir = self.options.run_dir
        if run_dir is not None and getattr(self, "trace_log", None) is not None:
            with self._cond:
                self.trace_log.save(run_dir / HAPTIC_TRACE_FILE)
                self.sample_log.save(run_dir / HAPTIC_SAMPLES_FILE)
                self.shed_log.save(shed_path(run_dir, self.name))
        super().close()

    def _rate_hz(self) -> float | None:
        """Device steps per second of wall time over the realtime run (None in lockstep)."""
        if self.timer is None or self.timer.count < 2:
            return None
        elapsed_ns = self.timer.last_wake_ns - self._first_wake_ns
        return (self.timer.count - 1) * NS_PER_S / elapsed_ns if elapsed_ns > 0 else None

    def summary(self) -> dict[str, Any]:
        timer = self.timer.summary() if self.timer is not None else {}
        return {
            **super().summary(),
            "mode": self.config.run.mode,
            "steps": self.steps,
            "runs": self.runs,
            "stale_feedback_events": self.hold.stale_events,
            "max_rendered_force_n": self.max_force_n,
            "max_abs_position_m": self.max_abs_position_m,
            "lockstep_waits": self.lockstep_waits,
            "missing_hand_inputs": self.missing_hand_inputs,
            "oversized_feedback": self.oversized_feedback,
            "republished_states": self.republished_states,
            "feedback_lost": self.feedback_seq.lost,
            "feedback_reordered": self.feedback_seq.reordered,
            "feedback_superseded": self.feedback_superseded,
            "feedback_shed": self.feedback_shed,
            "feedback_rendered": len(self.trace_log) + self.trace_log.overflow,
            "trace_rows_not_kept": self.trace_log.overflow,
            "rate_hz": self._rate_hz(),
            "max_stable_stiffness_n_per_m": max_stable_stiffness_n_per_m(
                self.config.haptic, self.period_s
            ),
            "loop": timer,
        }


def main() -> int:
    return service_main(HapticService)


if __name__ == "__main__":
    sys.exit(main())
