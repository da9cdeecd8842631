"""The haptic service's loop as pure code: one bus period per plant tick, with feedback.

Per tick (``Config.tick_s``, the bus period) the loop sends one HAPTIC_STATE and takes one
FORCE_FEEDBACK, which brings a local contact model (:class:`LocalContactModel`: the force
at a reference handle position and its stiffness about it); the device renders that model
every servo period (``haptic.render_period_s``, 1 kHz) at the handle's position then,
rate-limited (:class:`ForceSlew`), with the passivity observer and controller on the
servo periods. A real device's driver renders in its own 1 kHz thread; the emulator
renders a tick's servo periods in one go at the tick's end, each with the model that had
arrived by its time, as that thread would have.

:class:`HapticLoop` takes the records the service receives (FORCE_FEEDBACK, HAND_INPUT
and, in lockstep, PLANT_STATE), drives any :class:`teleop.devices.haptic.device.HapticDevice`
through its interface alone, and hands each HAPTIC_STATE record it fills to
:class:`HapticOutputs`. Time comes from an injected :class:`teleop.core.clock.Clock`,
so a test drives it on a fake clock without Zenoh; ``services/haptic.py`` is the bus
adapter around it.

- realtime: :meth:`HapticLoop.run_realtime` steps the device on the clock's deadlines
  (a :class:`LoopTimer` at the bus period) with the newest feedback (faded out by
  :class:`FeedbackHold` when stale) and the hand input valid at the newest plant tick
  seen. The tick and sim time are those of the newest feedback (the state it answers, at
  most a period or two old): a PLANT_STATE subscription only for that would cost
  this service and the plant a message each per period. A feedback tick below the last
  one means the plant started over (a new run). The feedback stream's order and age are
  checked by a :class:`teleop.bus.stamps.Inbound` (older than the newest: dropped; too
  old on arrival: shed and logged). Each feedback's model is rendered from the first
  servo period after it arrived (``haptic.render_on_arrival``; else from the next tick)
  and its trace, completed with FEEDBACK_RX and FEEDBACK_RENDERED (that servo period's
  start), is kept for the latency report.
- lockstep: deterministic and event driven. Tick k steps once PLANT_STATE k, the
  FORCE_FEEDBACK of tick k-1 (k >= 1) and the HAND_INPUT that applies at k (if any) are
  all in; the input that completes the set does the step (no thread hand-off). A hand
  input still missing after ``HAND_INPUT_WAIT_S`` means there is no operator:
  :meth:`HapticLoop.run_lockstep` logs once and goes on without waiting for hand inputs
  until one arrives. One that never comes because an input for a later tick came first
  (a restarted operator starts where the world is, not where its predecessor stopped)
  is not waited for.

In both modes a hand input more than ``haptic.hand_input_stale_s`` of sim time behind the
tick (no newer one came: the operator starved, frozen or restarting) is a hand that
stopped moving: it centres the handle (the tool holds still) and keeps the buttons it
held (:func:`held_hand`). Sim time, so a stalled plant never makes the hand stale.

Lockstep with an emulated link (``site.emulated_round_trip_ms``: the operator's and the
robot's site a round trip apart, in sim time): what the controller takes at tick k is
the handle as sampled ``forward`` ticks before (the record of that sample under tick
k's seq, tick and stamps), and what the handle feels from tick k on is the feedback of
tick ``k - 1 - backward``. The device still waits for the feedback of tick k-1 before
it steps tick k: that is the lockstep's order, whatever the link delays.

Several robots (``run.robots``): the loop takes every robot's PLANT_STATE, FORCE_FEEDBACK
and HAND_INPUT, each with the robot it came from. The handle drives one robot, the one
the newest hand input was meant for (the robot whose keys it came on), and switches only
while the handle rests in the rate deadband (meanwhile the hand still moves the robot
driven before, with that robot's buttons); the handle feels that robot's feedback alone.
Every other robot gets each sample as a centred handle (no rate: its tool holds still)
with the buttons it last had. In lockstep tick k steps once every running robot's state
k and feedback k-1 are in; a robot whose plant finished (FINISHED, :meth:`on_finished`)
leaves that barrier and gets no more samples. Robot 0's plant starts a run.

Lockstep: a PLANT_STATE seq 0 with a new ``t_source_ns`` (or as the first state) starts
a new run: the device is reset and every stored input is forgotten. A state with a seq
already seen is a plant re-send (the plant re-sends every state in flight byte for byte,
so a re-sent state 0 keeps its stamp): it never steps the device again; the HAPTIC_STATE
of its tick, if stepped, is sent again unchanged (same seq), in case the first copy was
lost (a late subscriber, a link that dropped).
"""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from typing import Any, Protocol

import numpy as np

from teleop.bus.messages import HAPTIC_STATE, N_STAGES, Button, Flag, Stage
from teleop.bus.service import STOP_POLL_S
from teleop.bus.stamps import Inbound, StampLog
from teleop.control.feedback import workspace_force
from teleop.control.wave import (
    WaveEnergyBank,
    handle_rate_m_s,
    handle_resistance_n,
    handle_wave,
)
from teleop.core.clock import NS_PER_S, Clock, LoopTimer
from teleop.core.config import Config
from teleop.core.ticks import TickedInputs, hand_schedule
from teleop.devices.haptic.device import (
    DeviceSample,
    FeedbackHold,
    ForceSlew,
    HandInput,
    HapticDevice,
    LocalContactModel,
    StaleSpells,
    max_stable_stiffness_n_per_m,
    saturate_force,
)
from teleop.devices.haptic.passivity import PassivityControl, max_stable_damping_n_s_m

logger = logging.getLogger(__name__)

# Lockstep: how long a tick waits for its hand input before the operator counts as absent (s).
HAND_INPUT_WAIT_S = 1.0
# Feedback whose norm exceeds this multiple of the peak force is garbage, not a saturation case.
OVERSIZED_FEEDBACK_FACTOR = 10.0
# The clutch's bit, as a plain int (an enum.Flag operation costs microseconds per call).
_CLUTCH = int(Button.CLUTCH)
# Lockstep feedback records kept by tick (a few ahead of the device is all that can happen).
FEEDBACK_KEEP = 64


class HapticOutputs(Protocol):
    """Where :class:`HapticLoop` sends its HAPTIC_STATE records (the service: the bus),
    each to one robot (its index in ``Config.robot_ids``)."""

    def sample(self, rec: np.ndarray, robot: int) -> None:
        """A new sample (every consumer, the recorder's batch included)."""

    def resend(self, rec: np.ndarray, robot: int) -> None:
        """The last sample again, for a plant that re-sent its state (the plant only)."""


# A hand input as the loop keeps it: the HAND_INPUT record and the robot it was meant
# for (the robot whose key it came on: the operator's choice of robot).
HandFor = tuple[np.ndarray, int]


def hand_input(rec: np.ndarray | None) -> HandInput | None:
    """The device's view of a HAND_INPUT record (None: no hand)."""
    if rec is None:
        return None
    return HandInput(rec["target_p_m"], Button(int(rec["buttons"])))


def held_hand(rec: np.ndarray | None, tick: int, stale_ticks: int) -> tuple[HandInput | None, bool]:
    """What the hand does at ``tick`` given the newest HAND_INPUT that applies there
    (None: none yet, no hand), and whether that input is stale.

    An input more than ``stale_ticks`` behind ``tick`` is a hand that stopped moving (its
    operator starved, frozen or restarting): the hand pulls the handle to the centre, so
    the rate control holds the tool still, and keeps holding the buttons it held, so an
    object in the gripper stays there (``haptic.hand_input_stale_s``). Ticks are sim time:
    a stalled plant stalls the ticks, so a hand is never stale for that.
    """
    if rec is None:
        return None, False
    if tick - int(rec["valid_from_tick"]) > stale_ticks:
        return HandInput(np.zeros(3), Button(int(rec["buttons"]))), True
    return hand_input(rec), False


class HapticLoop:
    """The haptic service minus the bus: see the module docstring for both timing modes.

    Thread-safe: the input methods may be called from any thread (Zenoh callbacks); they
    and the run methods serialise on :attr:`cond`. The run methods block until ``stop``.
    """

    def __init__(
        self,
        config: Config,
        device: HapticDevice,
        outputs: HapticOutputs,
        clock: Clock,
        *,
        lockstep: bool,
    ) -> None:
        self.config = config
        self.device = device
        self.outputs = outputs
        self.clock = clock
        self.lockstep = lockstep
        self._init_servo(config)
        self._init_feedback_channel(config)
        self._init_robots(config)
        self._init_run_state()
        self._init_counters()
        self._init_latency(config)

    def _init_servo(self, config: Config) -> None:
        """The bus period and the device's servo: how often it renders, and the limits it
        renders within (a model's stiffness, the force's rate and size, the hand's age)."""
        self.tick_s = config.tick_s  # one tick: one sample out, one feedback in
        self.tick_ns = round(self.tick_s * NS_PER_S)
        # The device's servo: it renders the local contact model this often, a bus
        # period's renders in one go (the emulator integrates its handle at that rate).
        self.render_period_s = config.haptic.render_period_s
        self.render_period_ns = round(self.render_period_s * NS_PER_S)
        self.renders_per_tick = config.renders_per_tick
        # A local model stiffer than the device renders passively (Colgate, at the servo
        # period) is cut down to it: the sender does not decide what the hand feels.
        self.max_model_stiffness_n_per_m = max_stable_stiffness_n_per_m(
            config.haptic, self.render_period_s
        )
        self.models_softened = 0
        self.slew = ForceSlew(config.haptic.max_force_rate_n_per_s, self.render_period_s)
        self.hand_schedule = hand_schedule(config)
        self.hand_stale_ticks = self.hand_schedule.ticks(config.haptic.hand_input_stale_s)
        self.peak_force_n = config.haptic.peak_force_n
        self.max_feedback_n = OVERSIZED_FEEDBACK_FACTOR * self.peak_force_n
        self.render_on_arrival = config.haptic.render_on_arrival

    def _init_feedback_channel(self, config: Config) -> None:
        """How the feedback crosses to the hand: the wave variables (teleop.stabiliser
        "wave"), the emulated link's delay, the fade of stale feedback and the passivity
        controller."""
        # teleop.stabiliser "wave": the feedback brings the robot's wave, not a force, and
        # the handle renders the channel's resistance and its own workspace spring.
        self.teleop_cfg = config.teleop
        wave = config.teleop.stabiliser == "wave"
        self.wave_b = config.teleop.wave_impedance_n_s_m if wave else 0.0
        # The waves toward the robot of the bus period's servo periods, summed: the sample
        # carries their mean (a wave held for the period carries no more energy than its
        # servo periods put in; the last one alone could carry more).
        self._wave_u_sum = np.zeros(3)
        # The robot's waves pass on no more energy than they brought (a varying delay).
        self.wave_bank = WaveEnergyBank(self.tick_s)
        self._banked_received_ns: int | None = None
        # The emulated link's delay each way (ticks; lockstep only, else (0, 0)).
        self.forward_ticks, self.backward_ticks = config.link_delay_ticks()
        self.feedback_keep = FEEDBACK_KEEP + self.backward_ticks
        # Lockstep with a forward delay: the samples still on their way (oldest first).
        self._in_flight: deque[np.ndarray] = deque(maxlen=self.forward_ticks + 1)
        self.hold = FeedbackHold(config.haptic.stale_feedback_s, config.haptic.fade_s)
        self.stale_spells = StaleSpells()
        # The energy the force exchanges with the hand, observed; damped with "tdpa".
        self.passivity = PassivityControl(
            config.teleop.stabiliser == "tdpa",
            min(
                config.teleop.tdpa_max_damping_n_s_m,
                max_stable_damping_n_s_m(config.haptic.handle_mass_kg, self.render_period_s),
            ),
            self.render_period_s,
        )

    def _init_robots(self, config: Config) -> None:
        """The hand inputs, and the robots the handle drives: which one, each one's newest
        state, feedback and buttons, and the samples kept for its plant's re-sends."""
        self.hand_inputs: TickedInputs[HandFor] = TickedInputs()
        # Several robots (run.robots): the handle drives the selected one; the others
        # get a centred handle (their tool holds still) with the buttons they last had.
        # The clock (lockstep) is the slowest robot still running; a robot whose plant
        # finished leaves it.
        self.robots = len(config.robot_ids())
        self.selected = 0
        self.deadband_m = config.teleop.deadband_m
        self._robot_seq = [-1] * self.robots  # newest state seq per robot (lockstep)
        self._finished: set[int] = set()
        self._robot_feedback: list[dict[int, np.ndarray]] = [{} for _ in range(self.robots)]
        self._idle = [HAPTIC_STATE.new() for _ in range(self.robots)]
        self._buttons = [0] * self.robots  # each robot's buttons when it was last driven
        # Lockstep: copies of the samples each robot was sent, by tick, for its plant's
        # states in flight and one more: a re-sent state gets the sample of its tick again.
        kept = config.plant.lockstep_states_in_flight + 1
        self._robot_sent: list[TickedInputs[np.ndarray]] = [
            TickedInputs(kept) for _ in range(self.robots)
        ]
        self.switches: list[dict[str, Any]] = []  # (tick, robot) of each switch
        self.switch_deferred_steps = 0  # steps a switch waited for the handle's deadband
        self.unselected_feedback = 0  # realtime: feedback of a robot not driven, not rendered

    def _init_run_state(self) -> None:
        """Where the run is: the realtime timer, and the ticks, stamps and hand-input wait
        the input methods and the run thread share under :attr:`cond`."""
        self.timer: LoopTimer | None = None
        self._first_wake_ns = 0
        self._last_deadline_ns = 0  # realtime: the newest tick's start (the render grid)
        # From here on shared by the input methods and the run thread (as are the
        # counters and the latency bookkeeping).
        self.cond = threading.Condition()
        self._state_seq = -1  # newest plant tick of this run; -1: none yet
        self._run_start_ns = -1  # t_source_ns of this run's state 0 (a re-send repeats it)
        self._state_sim_ns = 0  # its sim_time_ns (realtime)
        self._sim_offset_ns = 0  # lockstep: robot 0's sim time at tick 0
        self._first_tick = 0  # first tick of the run this loop saw (joined mid-run: > 0)
        self._last_tick = -1  # lockstep: last tick stepped
        self._hand_blocked_since_ns: int | None = None  # lockstep: tick waits for its hand
        self._operator_absent = False
        self._last_missing_valid_from: int | None = None
        self.record = HAPTIC_STATE.new()  # the last sample taken

    def _init_counters(self) -> None:
        """The counters and peaks of the summary, and the warnings given once."""
        self.steps = 0
        self.runs = 0
        self.lockstep_waits = 0
        self.missing_hand_inputs = 0
        self.hand_holds = 0  # times the hand input went stale (the hand centred the handle)
        self.hand_held_steps = 0  # steps taken with a stale hand input
        self._hand_stale = False
        self.oversized_feedback = 0
        self.republished_states = 0
        self.max_force_n = 0.0
        self.max_abs_position_m = 0.0
        self._warned_oversized = False
        self._warned_no_operator = False

    def _init_latency(self, config: Config) -> None:
        """Realtime latency bookkeeping: the bilateral loop's stamps, and each robot's
        feedback stream checked for order and age on its own."""
        self.trace_log = StampLog(N_STAGES)
        self.sample_log = StampLog(2)  # (HAPTIC_STATE seq, HAPTIC_SAMPLE ns)
        self._pending_trace: np.ndarray | None = None  # render at the next step
        # Realtime: each robot's feedback stream checked on its own (its seq is its own),
        # their shed loops in one log (the latency report counts loops, not streams).
        self.feedback_in = Inbound(Stage.FEEDBACK_TX, name="force_feedback")
        self.feedback_ins = [self.feedback_in] + [
            Inbound(Stage.FEEDBACK_TX, name=f"force_feedback of robot {robot}",
                    shed_log=self.feedback_in.shed_log)
            for robot in range(1, len(config.robot_ids()))
        ]  # fmt: skip
        self.feedback_superseded = 0  # replaced before the next step rendered it

    # -- inputs ------------------------------------------------------------------------
    def on_state(self, rec: np.ndarray, robot: int = 0) -> None:
        """PLANT_STATE of ``robot`` (lockstep: the clock; its ``seq`` is the plant tick).
        Robot 0's plant starts a run; with several robots the clock is the slowest
        one's (:meth:`_robots_state`)."""
        seq = int(rec["seq"])
        with self.cond:
            if robot:
                self._other_robot_state(seq, robot)
                return
            if seq == 0 and int(rec["t_source_ns"]) != self._run_start_ns:
                self._run_start_ns = int(rec["t_source_ns"])
                self._new_run()
            elif seq <= self._robot_seq[0]:
                self._resend_sample(seq, 0)
                return
            elif self._robot_seq[0] < 0:  # joined a run already under way
                self._first_tick = seq
                self._last_tick = seq - 1
            self._robot_seq[0] = seq
            self._sim_offset_ns = int(rec["sim_time_ns"]) - seq * self.tick_ns
            self._state_seq = self._robots_state()
            if self.lockstep:
                self._try_steps()
                if self._last_tick < seq:
                    self.lockstep_waits += 1

    def _other_robot_state(self, seq: int, robot: int) -> None:
        """PLANT_STATE ``seq`` of a robot other than robot 0 (lock held)."""
        if seq <= self._robot_seq[robot]:
            self._resend_sample(seq, robot)
            return
        self._robot_seq[robot] = seq
        self._state_seq = self._robots_state()
        if self.lockstep:
            self._try_steps()

    def _resend_sample(self, seq: int, robot: int) -> None:
        """A re-sent state of ``robot`` (lock held): the sample of its tick again, if it
        is kept (lockstep)."""
        sent = self._robot_sent[robot].at(seq)
        if sent is not None:
            self.republished_states += 1
            self.outputs.resend(sent, robot)

    def _keep_sent(self, robot: int, rec: np.ndarray) -> None:
        """Lockstep: a copy of the sample ``robot`` was sent, kept by its tick (lock held)."""
        if self.lockstep:
            self._robot_sent[robot].put(int(rec["tick"]), rec.copy())

    def _robots_state(self) -> int:
        """The newest tick every running robot's state has reached (lock held; -1:
        robot 0 has sent none). A robot not heard from yet holds the clock at -1 but for
        robot 0 alone, which starts the run."""
        running = [seq for r, seq in enumerate(self._robot_seq) if r not in self._finished]
        if not running or self._robot_seq[0] < 0:
            return self._robot_seq[0]
        return min(running)

    def on_finished(self, robot: int) -> None:
        """``robot``'s plant finished its run (its FINISHED or ABORTED event): the clock
        no longer waits for its states and feedback, and it gets no more samples."""
        with self.cond:
            if robot in self._finished:
                return
            self._finished.add(robot)
            if len(self._finished) == self.robots or not self.lockstep:
                return
            self._state_seq = self._robots_state()
            self._try_steps()

    def on_feedback(self, rec: np.ndarray, rx_ns: int, robot: int = 0) -> None:
        """FORCE_FEEDBACK of ``robot`` received at ``rx_ns`` (the clock's time)."""
        force = np.array(rec["device_f_n"], dtype=np.float64)
        force_norm_n = math.hypot(*force.tolist())
        if force_norm_n > self.max_feedback_n:
            with self.cond:
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
        with self.cond:
            model = self._local_model(rec, force)
            if not self.lockstep:
                self._feedback_realtime(rec, model, rx_ns, robot)
                return
            tick = int(rec["tick"])
            if tick < self._last_tick:
                return  # late: its step has been taken
            feedback = self._robot_feedback[robot]
            feedback[tick] = model
            if len(feedback) > self.feedback_keep:
                del feedback[min(feedback)]
            self._try_steps()

    def _local_model(self, rec: np.ndarray, force: np.ndarray) -> LocalContactModel:
        """The local contact model a FORCE_FEEDBACK brings (lock held): its force at its
        reference handle position with its stiffness, cut to the stiffest the device
        renders passively (counted); with wave variables the robot's wave, held."""
        if self.wave_b:  # the handle renders its own spring; the wave is what comes
            return LocalContactModel.constant(np.array(rec["wave_v"], dtype=np.float64))
        k_n_per_m = np.array(rec["device_k_n_per_m"], dtype=np.float64).reshape(3, 3)
        bound = self.max_model_stiffness_n_per_m
        # The Frobenius norm bounds the spectral one from above: the SVD (costly at this
        # rate) only for a model that may be too stiff.
        size = float(np.sqrt((k_n_per_m * k_n_per_m).sum()))
        if size > bound:
            size = float(np.linalg.norm(k_n_per_m, 2))
        if size > bound:
            self.models_softened += 1
            k_n_per_m *= self.max_model_stiffness_n_per_m / size
        p_ref_m = np.array(rec["device_p_ref_m"], dtype=np.float64)
        return LocalContactModel(force, p_ref_m, k_n_per_m)

    def on_hand(self, rec: np.ndarray, robot: int = 0) -> None:
        """HAND_INPUT meant for ``robot``, keyed by the plant tick it applies from."""
        self.hand_inputs.put(int(rec["valid_from_tick"]), (rec, robot))
        with self.cond:
            self._operator_absent = False
            if self.lockstep:
                self._try_steps()

    def _feedback_realtime(
        self, rec: np.ndarray, model: LocalContactModel, rx_ns: int, robot: int = 0
    ) -> None:
        """Hold the model: rendered from the device's first servo period after it came
        (or from the next tick's, without ``render_on_arrival``); keep its trace (lock
        held). Another robot's than the one driven: its tick noted (the clock when the
        handle switches to it), nothing rendered."""
        if not self.feedback_ins[robot].accept(rec, self.clock.now_ns()):
            return  # older than what the handle already feels, or shed as too old
        tick = int(rec["tick"])
        self._robot_seq[robot] = tick
        if robot != self.selected:
            self.unselected_feedback += 1  # the handle feels the robot it drives
            return
        if tick < self._state_seq:  # the plant started over: a new run
            self._new_run()
        elif self._state_seq < 0:  # this loop's first feedback: the run is under way
            self.runs += 1
        self._state_seq = tick
        self._state_sim_ns = int(rec["sim_time_ns"])
        trace = np.array(rec["trace_ns"])
        trace[Stage.FEEDBACK_RX] = rx_ns
        if self.render_on_arrival:
            # The servo period it is first rendered in begins at the next boundary of the
            # device's render grid (the device renders a tick's periods when it ends).
            grid_ns = self._last_deadline_ns
            # (one that came before the tick last rendered, but after it was rendered: from
            # that tick's end on)
            periods = max(0, -(-(rx_ns - grid_ns) // self.render_period_ns)) if grid_ns else 0
            rendered_ns = grid_ns + periods * self.render_period_ns if grid_ns else rx_ns
            self.hold.receive(model, rendered_ns)
            trace[Stage.FEEDBACK_RENDERED] = rendered_ns
            self.trace_log.append(trace)
        else:
            self.hold.receive(model, self._last_deadline_ns + self.tick_ns)
            if self._pending_trace is not None:
                self.feedback_superseded += 1
            self._pending_trace = trace

    # -- run boundaries ----------------------------------------------------------------
    def _new_run(self) -> None:
        """Device reset, inputs forgotten (caller holds the lock)."""
        self.device.reset()
        self.hold.clear()
        self.slew.reset()
        self.passivity.reset()
        self.hand_inputs.clear()
        for feedback in self._robot_feedback:
            feedback.clear()
        for sent in self._robot_sent:
            sent.clear()
        self._robot_seq[1:] = [-1] * (self.robots - 1)
        self._finished.clear()
        self.selected = 0
        self._in_flight.clear()
        self.record["device_p_m"] = 0.0  # the device is back at the centre
        self._wave_u_sum = np.zeros(3)
        self.wave_bank.reset()
        self._banked_received_ns = None
        self._first_tick = 0
        self._last_tick = -1
        self._hand_blocked_since_ns = None
        self._operator_absent = False
        self._last_missing_valid_from = None
        self._hand_stale = False
        self.runs += 1

    # -- lockstep ----------------------------------------------------------------------
    def _hand_for(self, tick: int) -> tuple[HandFor | None, bool]:
        """(hand input that applies at ``tick`` or None, still waiting for it)."""
        valid_from = self.hand_schedule.valid_from_for(tick)
        if valid_from is None:
            return None, False  # before the operator's first input can apply
        rec = self.hand_inputs.wait_for(valid_from, 0.0)
        if rec is not None:
            return rec, False
        newest = self.hand_inputs.newest_tick()
        # An input for a later tick came first: this one will never come (one operator
        # sends in order; a restarted one starts after the last of its predecessor's).
        if not self._operator_absent and (newest is None or newest < valid_from):
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
            if tick > self._first_tick and not self._feedback_complete(tick - 1):
                return  # the feedback of the tick before is the barrier, delayed or not
            hand, waiting = self._hand_for(tick)
            if waiting:
                if self._hand_blocked_since_ns is None:
                    self._hand_blocked_since_ns = self.clock.now_ns()
                    self.cond.notify_all()  # the run thread times the wait
                return
            self._hand_blocked_since_ns = None
            rec = self._select(hand, tick)
            t_ns = tick * self.tick_ns
            delivered = None
            for robot, feedback in enumerate(self._robot_feedback):
                force = feedback.pop(tick - 1 - self.backward_ticks, None)
                if robot == self.selected:
                    delivered = force
            if delivered is not None:
                self.hold.receive(delivered, t_ns - self.tick_ns)
            sim_ns = self._sim_offset_ns + tick * self.tick_ns
            sample = self._step(tick, sim_ns, rec, t_ns)
            self._send(self._over_the_link())
            self._account_sample(sample)
            self._last_tick = tick

    def _feedback_complete(self, tick: int) -> bool:
        """Whether the feedback of ``tick`` is in from every running robot (lock held)."""
        return all(
            tick in feedback
            for robot, feedback in enumerate(self._robot_feedback)
            if robot not in self._finished
        )

    def _select(self, hand: HandFor | None, tick: int) -> np.ndarray | None:
        """The hand's record, after switching the handle to the robot it is meant for
        (lock held). A switch waits for the handle to rest in the rate deadband (it
        commands nothing there): a handle held off-centre would drive the new robot at
        once; meanwhile the hand still moves the robot selected before."""
        if hand is None:
            return None
        rec, robot = hand
        if robot == self.selected or not 0 <= robot < self.robots:
            return rec
        offset_m = math.hypot(*self.record["device_p_m"].tolist())
        if offset_m > self.deadband_m:
            self.switch_deferred_steps += 1
            # The hand's motion brings the handle back; its buttons are the other
            # robot's, so the robot still driven keeps its own (a held cube stays held).
            kept = rec.copy()
            kept["buttons"] = self._buttons[self.selected]
            return kept
        logger.info("tick %d: the handle drives robot %d (was %d)", tick, robot, self.selected)
        self.switches.append({"tick": tick, "robot": robot})
        self.selected = robot
        self.hold.clear()  # the feedback held is the other robot's
        if not self.lockstep and self._robot_seq[robot] >= 0:
            # Its ticks are the clock now (behind the other robot's: no new run).
            self._state_seq = self._robot_seq[robot]
        return rec

    def _send(self, sent: np.ndarray) -> None:
        """``sent`` to the selected robot; to every other running one a centred handle
        with its own buttons held (lock held, or the realtime loop's thread)."""
        driven = self.selected
        if driven not in self._finished:
            self._keep_sent(driven, sent)
            self.outputs.sample(sent, driven)
        if self.robots == 1:
            return
        self._buttons[driven] = int(sent["buttons"])  # held when it is not driven
        for robot, idle in enumerate(self._idle):
            if robot == driven or robot in self._finished:
                continue
            idle[...] = sent
            for field in ("device_p_m", "device_v_m_s", "device_f_n", "wave_u"):
                idle[field] = 0.0
            idle["buttons"] = self._buttons[robot]
            self._keep_sent(robot, idle)
            self.outputs.sample(idle, robot)

    def _over_the_link(self) -> np.ndarray:
        """What the robot's site takes at this tick (lock held, after :meth:`_step`): the
        sample taken ``forward_ticks`` ago (the run's first while the link fills), under
        this tick's seq, tick and stamps; with no delay, :attr:`record` itself."""
        if not self.forward_ticks:
            return self.record
        self._in_flight.append(self.record.copy())
        sent = self._in_flight[0].copy()
        for name in ("seq", "t_source_ns", "trace_ns", "sim_time_ns", "tick"):
            sent[name] = self.record[name]
        return sent

    def poll_hand_wait(self) -> float:
        """Give up on a hand input overdue by ``HAND_INPUT_WAIT_S`` (lock held); the time
        until the next check is due (s, 0: at once)."""
        since_ns = self._hand_blocked_since_ns
        if since_ns is None:
            return STOP_POLL_S
        left_ns = since_ns + round(HAND_INPUT_WAIT_S * NS_PER_S) - self.clock.now_ns()
        if left_ns <= 0:
            self._give_up_on_hand()
            return 0.0
        return min(STOP_POLL_S, left_ns / NS_PER_S)

    def run_lockstep(self, stop: threading.Event) -> None:
        """Steps happen in the input methods; this thread only times out a missing hand
        input (the condition is notified when a tick starts waiting for one)."""
        with self.cond:
            while not stop.is_set():
                timeout_s = self.poll_hand_wait()
                if timeout_s > 0:
                    self.cond.wait(timeout_s)

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
    def run_realtime(self, stop: threading.Event) -> None:
        """One bus period per deadline of the clock until ``stop``."""
        self.timer = LoopTimer(self.tick_ns, self.clock)
        while not stop.is_set():
            deadline_ns = self.timer.deadline_ns(self.timer.wait())
            if self.timer.count == 1:
                self._first_wake_ns = self.timer.last_wake_ns
            self.step_realtime(deadline_ns)

    def step_realtime(self, deadline_ns: int) -> None:
        """The bus period that ends at ``deadline_ns``: its servo periods rendered with
        the models as they arrived, the handle sampled at its end, with the newest inputs."""
        with self.cond:
            tick = max(self._state_seq, 0)
            hand = self.hand_inputs.latest_at(tick) if self._state_seq >= 0 else None
            rec = self._select(hand, tick)
            sample = self._step(
                tick, self._state_sim_ns, rec, deadline_ns - self.tick_ns, deadline_ns
            )
            self._last_deadline_ns = deadline_ns
        # Outside the lock: a feedback that arrives meanwhile is rendered at once. Only
        # this thread steps in realtime, so the record stays as filled.
        self._send(self.record)
        self._account_sample(sample)

    # -- shared ------------------------------------------------------------------------
    def _render(
        self, model: LocalContactModel, handle_d_m: np.ndarray, received_ns: int | None
    ) -> np.ndarray:
        """The force to send the motors for one servo period from the local model held
        (received at ``received_ns``) and the handle's position (lock held): the model's
        force there, stabilised (:meth:`_stabilised`); with wave variables the robot's
        wave, passed on within the energy the waves brought (:class:`WaveEnergyBank`),
        decoded against the handle's rate (teleop/control/wave.py) into the channel's
        resistance, rendered with the handle's own workspace spring, and the wave toward
        the robot that goes with it added to the period's (the sample sends their mean)."""
        received = model.force_at(handle_d_m)
        if not self.wave_b:
            return self._stabilised(received)
        if received_ns != self._banked_received_ns:  # a wave that came: its energy
            self._banked_received_ns = received_ns
            if received_ns is not None:
                self.wave_bank.receive(received)
        received = self.wave_bank.pass_on(received, self.render_period_s)
        clutch = bool(int(self.record["buttons"]) & _CLUTCH)
        rate = handle_rate_m_s(handle_d_m, clutch, self.teleop_cfg)
        self._wave_u_sum += handle_wave(rate, received, self.wave_b)
        resistance_n = handle_resistance_n(rate, received, self.wave_b)
        spring_n = workspace_force(handle_d_m, self.teleop_cfg)
        return self._stabilised(spring_n - resistance_n)

    def _stabilised(self, force_n: np.ndarray) -> np.ndarray:
        """The force to send the motors: the stabiliser's correction of the force the
        device can render (saturated at its peak first: a correction of a force above
        the peak would be clipped away with it, and a saturated push would go on giving
        energy out), after the rate limit (:class:`ForceSlew`)."""
        return self.passivity.control(self.slew.limit(saturate_force(force_n, self.peak_force_n)))

    def _step(
        self,
        tick: int,
        sim_time_ns: int,
        hand: np.ndarray | None,
        t_ns: int,
        deadline_ns: int = 0,
    ) -> DeviceSample:
        """One bus period of the device: each of its servo periods renders the local
        model held then at the handle's position and advances the device; then fill
        :attr:`record` with the sample at the period's end (caller holds the lock; the
        caller sends the record, then :meth:`_account_sample` counts the returned
        sample: the statistics wait until the sample is on its way).

        ``t_ns`` is the start of the period rendered, on the feedback clock (monotonic
        in realtime, sim time in lockstep); ``deadline_ns`` the tick's deadline in
        realtime (the plant steps on it), 0 in lockstep.
        """
        if self._pending_trace is not None:
            self._pending_trace[Stage.FEEDBACK_RENDERED] = self.clock.now_ns()
            self.trace_log.append(self._pending_trace)
            self._pending_trace = None
        held, hand_stale = held_hand(hand, tick, self.hand_stale_ticks)
        if hand_stale:
            self.hand_held_steps += 1
            if not self._hand_stale:
                self.hand_holds += 1
                logger.info(
                    "hand input of tick %d is stale at tick %d (newest input: tick %s): "
                    "the hand centres the handle and keeps its buttons",
                    int(hand["valid_from_tick"]),  # type: ignore[index]
                    tick,
                    self.hand_inputs.newest_tick(),
                )
        self._hand_stale = hand_stale
        handle_d_m = self.record["device_p_m"].copy()  # where the last sample left it
        stale = False
        for render in range(self.renders_per_tick):
            render_ns = t_ns + render * self.render_period_ns
            model, render_stale, received_ns = self.hold.model_at(render_ns)
            stale |= render_stale
            if render_stale or self.stale_spells.open:
                felt_n = math.hypot(*model.force_at(handle_d_m).tolist())
                self.stale_spells.render(render_ns, render_stale, received_ns, felt_n)
            self.device.send_force(self._render(model, handle_d_m, received_ns))
            sample = self.device.next_sample(held)
            self.passivity.observe(sample.f_n, sample.v_m_s)
            handle_d_m = sample.p_m
        sample_ns = self.clock.now_ns()
        self.steps += 1
        rec = self.record
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
        rec["passivity_observed_j"] = self.passivity.observed_j
        rec["passivity_dissipated_j"] = self.passivity.dissipated_j
        rec["wave_u"] = self._wave_u_sum / self.renders_per_tick
        self._wave_u_sum[:] = 0.0
        rec["buttons"] = int(sample.buttons)
        return sample

    def _account_sample(self, sample: DeviceSample) -> None:
        """Statistics of the sample just sent (and its stamp, in realtime)."""
        self.max_force_n = max(self.max_force_n, math.hypot(*sample.f_n.tolist()))
        self.max_abs_position_m = max(self.max_abs_position_m, *map(abs, sample.p_m.tolist()))
        if not self.lockstep:
            rec = self.record
            self.sample_log.append((int(rec["seq"]), int(rec["trace_ns"][Stage.HAPTIC_SAMPLE])))

    def _rate_hz(self) -> float | None:
        """Device steps per second of the clock over the realtime run (None in lockstep)."""
        if self.timer is None or self.timer.count < 2:
            return None
        elapsed_ns = self.timer.last_wake_ns - self._first_wake_ns
        return (self.timer.count - 1) * NS_PER_S / elapsed_ns if elapsed_ns > 0 else None

    def summary(self) -> dict[str, Any]:
        """Counters, feedback bookkeeping and the realtime loop's statistics (JSON-ready)."""
        return {
            "steps": self.steps,
            "runs": self.runs,
            "stale_feedback_events": self.hold.stale_events,
            # What the handle felt from stale feedback: per spell, missing and felt (ms).
            "stale_spells": self.stale_spells.summary(),
            "max_rendered_force_n": self.max_force_n,
            "max_abs_position_m": self.max_abs_position_m,
            "lockstep_waits": self.lockstep_waits,
            "missing_hand_inputs": self.missing_hand_inputs,
            "hand_holds": self.hand_holds,
            "hand_held_steps": self.hand_held_steps,
            "oversized_feedback": self.oversized_feedback,
            "republished_states": self.republished_states,
            "feedback_lost": sum(inbound.seq.lost for inbound in self.feedback_ins),
            "feedback_reordered": sum(inbound.seq.reordered for inbound in self.feedback_ins),
            "feedback_superseded": self.feedback_superseded,
            "feedback_shed": sum(inbound.shed for inbound in self.feedback_ins),
            # lost, reordered, jumps, ... (robot 0's stream; per robot in a run of several)
            "feedback_stream": self.feedback_in.counts(),
            "feedback_streams": [inbound.counts() for inbound in self.feedback_ins],
            "feedback_rendered": len(self.trace_log) + self.trace_log.dropped,
            "trace_rows_not_kept": self.trace_log.dropped,
            "rate_hz": self._rate_hz(),
            # the emulated link's delay each way (site.emulated_round_trip_ms)
            "link_delay_ticks": {"forward": self.forward_ticks, "backward": self.backward_ticks},
            # several robots: when the handle changed robot, and how long a switch waited
            # for the handle to come back into its deadband
            "robot_switches": list(self.switches),
            "switch_deferred_steps": self.switch_deferred_steps,
            "unselected_feedback": self.unselected_feedback,
            "passivity": self.passivity.summary(self.config.teleop.stabiliser),
            # wave variables: the energy the robot's waves brought, and what the handle's
            # end held back of waves passed on beyond it (a varying delay)
            "wave_bank": self.wave_bank.summary() if self.wave_b else None,
            "max_stable_stiffness_n_per_m": self.max_model_stiffness_n_per_m,
            # the local contact model: servo periods rendered per bus period, models whose
            # stiffness was cut to the passive bound, servo periods the rate limit cut
            "renders_per_tick": self.renders_per_tick,
            "models_softened": self.models_softened,
            "force_rate_limited_renders": self.slew.limited_steps,
            "loop": self.timer.summary() if self.timer is not None else {},
        }
