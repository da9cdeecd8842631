"""When the plant steps: one pacer per timing mode, chosen once (:func:`make_pacer`).

Every pacer drives the same :class:`teleop.sim.stepping.PlantStepCore` (apply or brake,
step, publish, checkpoint) and keeps its own state under its own lock:

- :class:`TickPacer`, realtime on the plant's tick: a :class:`LoopTimer` paces the
  steps, one per period on average, after a stall skipping ticks, never bursting; each
  step applies the newest command.
- :class:`DeviceClockPacer`, realtime teleoperation with ``plant.apply_on_arrival``:
  each command enters a step the moment it arrives, in the Zenoh callback; the steps
  follow the haptic device's periods, one per device period, counted on the device's
  clock and placed on the plant's by the commands' arrivals (:class:`DeviceClockGrid`; the
  device samples once per bus period, ``loop.rate_hz``: a device period is a tick), so
  a command never waits for the plant's tick, and a period without a command is stepped
  with the last one.
- :class:`LockstepPacer`: the plant publishes a state and steps when the command that
  answers it (``state_seq``) arrives, inside the command callback, so a cycle costs no
  thread hand-off: deterministic, as fast as plant + controller allow. Told the
  instants of a run's faults (:class:`LockstepHolds`), it waits at each for the
  launcher's release, so a fault lands on its tick however late the launcher hears.

All three run on an injected clock: the tests drive each on the fake clock.
"""

from __future__ import annotations

import collections
import itertools
import threading
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from typing import Protocol

import numpy as np

from teleop.bus.messages import Stage
from teleop.bus.session import Latest
from teleop.bus.stamps import LinkClock
from teleop.core.clock import NS_PER_S, Clock, LoopTimer
from teleop.core.config import LOCKSTEP_RESEND_S, Config
from teleop.core.ring import Ring
from teleop.sim.checkpoint import CheckpointStore
from teleop.sim.stepping import Abort, PacingFigures, PlantOutputs, PlantStepCore


class Pacer(Protocol):
    """When the plant steps, in one timing mode: the one interface of the three pacers."""

    core: PlantStepCore

    def on_command(self, rec: np.ndarray, rx_ns: int) -> None:
        """A JOINT_COMMAND for this arm arrived at ``rx_ns`` (on a Zenoh thread): admitted
        by the core, then stepped with or kept for a step, as the mode has it."""
        ...

    def run(self, stop: threading.Event, *, resumed: bool) -> None:
        """Publish the run's first state and step until the run's end or ``stop``;
        ``resumed``: the core resumed a checkpoint (the arm may be moving)."""
        ...

    def figures(self) -> PacingFigures:
        """What this pacing adds to the run's summary."""
        ...


def make_pacer(
    config: Config,
    outputs: PlantOutputs,
    clock: Clock,
    store: CheckpointStore | None = None,
    holds_ns: Sequence[int] = (),
) -> Pacer:
    """The step core and the pacer of the configured timing mode, chosen once.

    Lockstep in lockstep mode, held at the sim instants ``holds_ns`` until released
    (:class:`LockstepHolds`; a realtime plant keeps time, it cannot be held: ValueError).
    In realtime teleoperation the haptic device's clock paces the commands (with
    ``plant.apply_on_arrival``); in path following each command answers the plant's own
    state, so the plant's tick is the loop's only clock and the newest command is the one
    to apply.
    """
    if config.run.mode == "lockstep":
        sent = SentTicks(outputs, config.plant.lockstep_states_in_flight)
        core = PlantStepCore(config, sent, clock, store)
        return LockstepPacer(core, sent, LockstepHolds(holds_ns))
    if holds_ns:
        raise ValueError("a plant is held at fault instants in lockstep only (run.mode)")
    core = PlantStepCore(config, outputs, clock, store)
    if config.plant.apply_on_arrival and config.run.teleoperated:
        return DeviceClockPacer(core)
    return TickPacer(core)


# -- realtime, plant tick ----------------------------------------------------------------
class TickPacer:
    """Realtime on the plant's own tick: each step applies the newest command.

    The command callback only stores the newest command (a :class:`Latest`, under its own
    lock); the run thread steps, on its :class:`LoopTimer`'s deadlines.
    """

    def __init__(self, core: PlantStepCore) -> None:
        self.core = core
        self.commands = Latest()  # the newest admitted command, for the next tick
        self.timer: LoopTimer | None = None

    def on_command(self, rec: np.ndarray, rx_ns: int) -> None:
        # No shedding: the watchdog judges a command's age at the step.
        if self.core.admit(rec, shed=False):
            self.commands(rec, rx_ns)

    def run(self, stop: threading.Event, *, resumed: bool) -> None:
        self.start()
        self.timer = LoopTimer(self.core.period_ns, self.core.clock)
        while not stop.is_set() and self.core.should_step():
            self.timer.wait()
            self.tick()

    def start(self) -> None:
        """Send the run's first state, the one the first command answers."""
        self.core.publish_state()
        self.core.prepare_next_step()

    def tick(self) -> None:
        """One step, with the newest command."""
        latest = self.commands.get()
        command, rx_ns = latest if latest is not None else (None, 0)
        self.core.step(command, rx_ns)
        self.core.prepare_next_step()

    def figures(self) -> PacingFigures:
        timer = self.timer.summary() if self.timer is not None else {}
        return PacingFigures(
            overrun_fraction=timer.get("overrun_fraction", 0.0),
            skipped_ticks=timer.get("skipped", 0),
            loop=timer,
        )


# -- realtime, on the haptic device's clock ----------------------------------------------
# Apply on arrival: a device period whose command has not come this many periods after
# the period began is stepped without it (with the last command, or braking). A command
# normally reaches the plant well within a period or two of its handle sample (see
# docs/latency.md); one that comes after its period was stepped is merged into the next
# step instead of taking one of its own.
OWN_STEP_AFTER_PERIODS = 2
# Apply on arrival: periods stepped back to back at most to catch up (periods before a
# command that got none, or the run thread after a stall); older ones are skipped, never
# run in a burst.
CATCH_UP_MAX_PERIODS = 2
# Apply on arrival: a command this many periods away from the plant's next one (either
# way) means the device's clock started over (a restarted haptic service): re-lock to it.
RELOCK_PERIODS = 1000


class DeviceClockGrid:
    """The realtime plant's steps on the haptic device's periods (times in ns of the
    device's monotonic clock).

    The device samples the handle on absolute deadlines ``t0 + k * period`` of its own
    monotonic clock, and each teleoperation command carries the deadline of the period
    whose sample it answers (``device_deadline_ns``). The plant takes exactly one step
    per device period, as a fieldbus slave follows the master's distributed clock:
    ``next_ns`` is the period of the next step. A command for that period steps at once;
    one for a later period first steps the periods in between, which got no command
    (shed upstream or skipped by the device), with the last command; one for a period
    already stepped is late and only becomes the command held for the next step. A
    period without a command is stepped by the plant's own thread
    ``OWN_STEP_AFTER_PERIODS`` periods after it began. So commands never wait for a
    window, sim time stays on the device's clock (no drift either way), and the plant
    still keeps wall-clock time when no command comes at all.

    Before the first command the grid runs from ``start_ns`` (the plant's clock, no
    device's known yet); :meth:`lock` puts the next step on the first command's period.
    Pure arithmetic, no clock of its own: the pacer places the device's periods on the
    plant's clock (:class:`teleop.bus.stamps.LinkClock`, where the fastest command would
    have brought them) only to time its own steps, as two hosts share no clock.
    """

    def __init__(self, period_ns: int, start_ns: int) -> None:
        if period_ns <= 0:
            raise ValueError(f"period_ns must be > 0, got {period_ns}")
        self.period_ns = period_ns
        self.next_ns = start_ns  # start of the device period the next step covers
        self.skipped = 0  # periods never stepped (stalls longer than the catch-up)
        self.locks = 0  # times the grid (re-)locked to a command's period

    @property
    def locked(self) -> bool:
        return self.locks > 0

    def lock(self, deadline_ns: int) -> None:
        """The next step covers the device period that starts at ``deadline_ns``."""
        self.next_ns = deadline_ns
        self.locks += 1

    def periods_ahead(self, deadline_ns: int) -> int:
        """Periods from the next step's to the one starting at ``deadline_ns`` (negative:
        already stepped)."""
        return round((deadline_ns - self.next_ns) / self.period_ns)

    @property
    def own_step_ns(self) -> int:
        """When the plant steps the next period itself if no command came for it."""
        return self.next_ns + OWN_STEP_AFTER_PERIODS * self.period_ns

    def stepped(self) -> None:
        """The next period was stepped."""
        self.next_ns += self.period_ns

    def skip(self, periods: int) -> None:
        """Give up ``periods`` periods without stepping them (a stall)."""
        self.skipped += periods
        self.next_ns += periods * self.period_ns


@dataclass
class ArrivalCounts:
    """What happened to the commands of the device-clock pacing."""

    steps_on_arrival: int = 0  # steps a command started the moment it arrived
    steps_without_command: int = 0  # device periods stepped without a new command
    stalls: int = 0  # times the plant fell behind by more than the catch-up (skipped)
    commands_late: int = 0  # came after their period was stepped: merged into the next
    commands_stale: int = 0  # arrived too old to apply (the watchdog brakes instead)


class DeviceClockPacer:
    """Realtime teleoperation: each command steps its device period as it arrives.

    The command callback steps (:meth:`on_command`); the run thread steps the device
    periods no command came for (see :class:`DeviceClockGrid`). Both under ``cond``,
    which also wakes the run thread when a command moved its next own step.
    """

    def __init__(self, core: PlantStepCore) -> None:
        self.core = core
        self.cond = threading.Condition()  # the run thread and the command callback
        self.grid: DeviceClockGrid | None = None  # from the run's start (:meth:`begin`)
        # The device's clock as the commands' deadlines and arrivals show it.
        self.device_clock = LinkClock()
        self.counts = ArrivalCounts()
        self._running = False  # commands step the plant (between begin and the run's end)
        self._held_command: np.ndarray | None = None  # the newest applied, for own steps

    def on_command(self, rec: np.ndarray, rx_ns: int) -> None:
        # Applied on arrival: a backlog (older than the shed age) is shed on admission.
        if self.core.admit(rec, shed=self._running):
            self._arrive(rec, rx_ns)

    def run(self, stop: threading.Event, *, resumed: bool) -> None:
        core = self.core
        core.publish_state()  # the run's first state, the one the first command answers
        core.prepare_next_step()
        with self.cond:
            self.begin()
            try:
                while not stop.is_set() and core.should_step():
                    now_ns = core.clock.now_ns()
                    wait_ns = self.own_step_due(now_ns)
                    if wait_ns > 0:
                        self.cond.wait(wait_ns / NS_PER_S)
                    else:
                        self.own_step(now_ns)
            finally:
                self._running = False

    def begin(self) -> None:
        """From now on, commands step the plant as they arrive (in their callback), on a
        new device clock grid. The caller holds ``cond``, or is a test or benchmark
        driving the pacer directly."""
        self.grid = DeviceClockGrid(self.core.period_ns, self.core.clock.now_ns())
        self.device_clock.reset()
        self._held_command = None
        self.core.restart_commands()
        self._running = True

    def own_step_due(self, now_ns: int) -> int:
        """Nanoseconds until the run thread steps the next period itself (<= 0: now)."""
        assert self.grid is not None
        return self.device_clock.local_ns(self.grid.own_step_ns) - now_ns

    def own_step(self, now_ns: int) -> None:
        """Step the next device period without a new command; after a stall, skip the
        periods beyond the catch-up instead of bursting through them."""
        grid = self.grid
        assert grid is not None
        behind = -self.own_step_due(now_ns) // self.core.period_ns
        if behind > CATCH_UP_MAX_PERIODS:
            self.counts.stalls += 1
            grid.skip(int(behind) - CATCH_UP_MAX_PERIODS)
        self._step(None, 0)

    def _arrive(self, command: np.ndarray, rx_ns: int) -> None:
        """A command arrived: step its device period now (after any before it that got
        no command), or hold it for the next step if its period is past."""
        with self.cond:
            grid = self.grid
            if not self._running or grid is None:
                return
            deadline_ns = int(command["device_deadline_ns"])
            ahead = 0  # a command not paced by a device steps the next period
            if deadline_ns > 0:
                if self.device_clock.observe(deadline_ns, rx_ns):
                    if not grid.locked or abs(grid.periods_ahead(deadline_ns)) > RELOCK_PERIODS:
                        grid.lock(deadline_ns)
                    ahead = grid.periods_ahead(deadline_ns)
                else:  # stamped in the device clock's future: the next step applies it
                    ahead = -1
            if ahead < 0:  # its period was stepped without it: the next step applies it
                self.counts.commands_late += 1
                self.core.log_dropped(command)
                self._held_command = command
                return
            if ahead > CATCH_UP_MAX_PERIODS:  # the periods before it are too far behind
                self.counts.stalls += 1
                grid.skip(ahead - CATCH_UP_MAX_PERIODS)
                ahead = CATCH_UP_MAX_PERIODS
            for _ in range(ahead):
                if self.core.should_step():
                    self._step(None, 0)
            if self.core.should_step():
                self.counts.steps_on_arrival += 1
                self._step(command, rx_ns)
            self.cond.notify_all()  # the run thread's next own step moved

    def _step(self, command: np.ndarray | None, rx_ns: int) -> None:
        """Step the grid's next device period with ``command`` (None: with the one held,
        braking if that is stale); the caller holds ``cond``."""
        assert self.grid is not None
        if command is not None:
            self._held_command = command
        else:
            self.counts.steps_without_command += 1
        applied = self.core.step(self._held_command, rx_ns, traced=command is not None)
        self.core.prepare_next_step()
        if not applied and command is not None:
            self.counts.commands_stale += 1
            self.core.log_dropped(command)
        self.grid.stepped()

    def figures(self) -> PacingFigures:
        grid = self.grid
        if grid is None:  # the run never started pacing
            return PacingFigures()
        core = self.core
        command_in = core.command_in
        return PacingFigures(
            overrun_fraction=self.counts.stalls / max(core.plant.step_count, 1),
            skipped_ticks=grid.skipped,
            arrival={
                **asdict(self.counts),
                "grid_locks": grid.locks,
                "device_clock_refused": self.device_clock.refused,
                "device_clock_relearnt": self.device_clock.relearnt,
                "commands_lost": command_in.seq.lost,
                "commands_reordered": command_in.seq.reordered,
                "commands_shed": command_in.shed,
            },
        )


# -- lockstep ----------------------------------------------------------------------------
# Lockstep cycle breakdown: the newest cycles kept (a ring; 65 simulated s at 250 Hz).
CYCLE_STATS_CAPACITY = 1 << 14


class LockstepCycleStats:
    """Where a lockstep cycle's wall time goes, from the stamps the records carry.

    One cycle: the plant sends state k (``PLANT_STATE_TX``), the controller receives
    it and answers (``CONTROLLER_RX``, ``CONTROLLER_TX``), the plant receives the
    command (``PLANT_RX``), steps (``PLANT_APPLIED``) and sends state k + 1 + d (d:
    ``plant.lockstep_delay_steps``). All stamps are this host's monotonic clock, so the
    segments are exact and add up to the cycle. With d states in flight besides the
    pending one, the plant's ``period`` (between two states sent) is about the cycle
    divided by d + 1 when neither plant nor controller is the bottleneck.
    """

    SEGMENTS = ("to_controller", "controller", "to_plant", "plant_rx", "plant_step")

    def __init__(self, capacity: int = CYCLE_STATS_CAPACITY) -> None:
        # Per cycle: each segment's duration, then the whole cycle's (ns).
        self._durations_ns = Ring(capacity, len(self.SEGMENTS) + 1)
        self._periods_ns = Ring(capacity)  # between two consecutive states sent
        self._last_sent_ns = 0

    _STAGES = [Stage.CONTROLLER_RX, Stage.CONTROLLER_TX, Stage.PLANT_RX, Stage.PLANT_APPLIED,
               Stage.PLANT_STATE_TX]  # fmt: skip

    def add(self, answered_state_tx_ns: int, trace_ns: np.ndarray) -> None:
        """Record one cycle from the new state's stamps (they include the command's); a
        cycle with a stamp missing is left out."""
        stamps = [answered_state_tx_ns, *(int(trace_ns[s]) for s in self._STAGES)]
        if min(stamps) <= 0:
            return
        self._durations_ns.append([b - a for a, b in itertools.pairwise(stamps)] +
                                  [stamps[-1] - stamps[0]])  # fmt: skip
        if self._last_sent_ns:
            self._periods_ns.append(stamps[-1] - self._last_sent_ns)
        self._last_sent_ns = stamps[-1]

    def summary(self) -> dict[str, float]:
        """Median microseconds of each segment and of the whole cycle over the newest
        cycles kept ({} if none)."""
        if not len(self._durations_ns):
            return {}
        names = (*self.SEGMENTS, "cycle")
        result = {
            name: round(self._durations_ns.percentiles([50.0], column)[0] / 1e3, 1)
            for column, name in enumerate(names)
        }
        if len(self._periods_ns):
            result["period"] = round(self._periods_ns.percentiles([50.0])[0] / 1e3, 1)
        return result


class SentTicks:
    """:class:`PlantOutputs` that also keep the records of the newest ``ticks`` states
    as sent (stream, bytes): a state opens its tick, the tick's scene records join it;
    events are not part of a tick."""

    def __init__(self, outputs: PlantOutputs, ticks: int) -> None:
        self.outputs = outputs
        self.ticks: collections.deque[list[tuple[str, bytes]]] = collections.deque(maxlen=ticks)

    def put(self, stream: str, rec: np.ndarray) -> bytes:
        if stream == "plant_state":
            self.ticks.append([])
        data = self.outputs.put(stream, rec)
        if stream != "plant_events":
            self.ticks[-1].append((stream, data))
        return data

    def put_bytes(self, stream: str, data: bytes) -> None:
        self.outputs.put_bytes(stream, data)

    def flush(self) -> None:
        self.outputs.flush()

    def resend(self) -> None:
        """Send every kept record again, byte for byte, oldest tick first."""
        for records in self.ticks:
            for stream, data in records:
                self.outputs.put_bytes(stream, data)


class LockstepHolds:
    """The sim instants at which a lockstep plant waits before stepping on, and which of
    them are released.

    ``teleop run --kill/--freeze`` in lockstep: the launcher hears the plant's states late
    (a normally scheduled process, batched copies) while the run races at several times
    real time, so a fault injected when it hears the instant would land seconds of sim
    time late on a busy machine. Told the instants, the plant holds at the first state at
    or past each until the launcher, having injected, releases it (a release token,
    graph.RELEASED_TOKEN). A release at instant t releases every hold at or before t: a
    restarted plant, resuming before an instant already passed, finds it released by the
    tokens still declared. A release can only let the run go on; the plant's own limits
    and watchdog steer the arm as ever.
    """

    def __init__(self, at_ns: Iterable[int]) -> None:
        self._at_ns = sorted({int(t) for t in at_ns})
        self.released_ns = -1  # every hold at or before this instant is released

    def holding(self, sim_time_ns: int) -> bool:
        """Whether a plant whose newest state is at ``sim_time_ns`` waits before stepping."""
        return any(self.released_ns < t <= sim_time_ns for t in self._at_ns)

    def release(self, at_ns: int) -> None:
        """Release every hold at or before ``at_ns``."""
        self.released_ns = max(self.released_ns, at_ns)

    def __bool__(self) -> bool:
        return bool(self._at_ns)


class LockstepPacer:
    """Lockstep: each step applies the answer to the pending state, in its callback.

    The command callback steps (:meth:`on_command`); the run thread takes the steps
    before the first answer, then only waits, re-sending the pending state if it goes
    unanswered and ending the run if it stays so (:meth:`waited`). Both under ``lock``.
    Step k applies the command answering state k - ``plant.lockstep_delay_steps``.
    At a hold (:class:`LockstepHolds`) the answer is kept until :meth:`release`.
    """

    def __init__(self, core: PlantStepCore, sent: SentTicks, holds: LockstepHolds) -> None:
        self.core = core
        self.sent = sent  # the core's outputs, keeping the states in flight for a re-send
        self.holds = holds  # none told: never held
        self._held: dict[int, tuple[np.ndarray, int]] = {}  # answers kept at a hold, by state
        self.lock = threading.Lock()  # the run thread and the command callback
        self.delay_steps = core.config.plant.lockstep_delay_steps
        self.cycle_stats = LockstepCycleStats()
        self._running = False  # answers step the plant (from the first state on)
        self._done = threading.Event()  # the run's last step was taken (or it aborted)
        self._last_step_ns = 0  # when the plant last stepped (the wait's bound)
        self._timeout_ns = round(core.config.plant.lockstep_timeout_s * NS_PER_S)

    @property
    def running(self) -> bool:
        """Whether an answer to the pending state steps the plant now."""
        return self._running

    @property
    def pending_state(self) -> int:
        """The state whose answer the next step applies."""
        return self.core.state_seq - self.delay_steps

    def on_command(self, rec: np.ndarray, rx_ns: int) -> None:
        # No shedding: lockstep waits for its answer however long it takes.
        if self.core.admit(rec, shed=False):
            self._cycle(rec, rx_ns)

    def run(self, stop: threading.Event, *, resumed: bool) -> None:
        self.start(braking=resumed)
        try:
            last_step = -1
            while not stop.is_set() and not self._done.wait(LOCKSTEP_RESEND_S):
                if not self.waited(last_step):
                    break
                last_step = self.core.plant.step_count
        finally:
            with self.lock:
                self._running = False

    def start(self, *, braking: bool = False) -> None:
        """Publish the first state, then take the first ``delay_steps`` steps, which no
        command answers (holding still; ``braking``: held by the brake, as after a
        restart, where the arm may be moving); the command callback may step from then on.

        All under the lock, with the callback already enabled: an answer that comes back
        while these steps run waits for the lock instead of finding lockstep not started
        (it would be lost, and the run would wait for it forever).
        """
        core = self.core
        with self.lock:
            self._done.clear()
            self._running = True
            core.publish_state()
            for _ in range(self.delay_steps):
                if not core.should_step():
                    break
                core.step_unanswered(braking=braking)
            self._last_step_ns = core.clock.now_ns()
            if not core.should_step():
                self._done.set()  # the steps before commands were the whole run
            self._flush_at_hold()

    def waited(self, last_step: int) -> bool:
        """Every LOCKSTEP_RESEND_S without the run ending: if the plant has not stepped
        since ``last_step``, re-send the pending state, or, once it has waited
        ``plant.lockstep_timeout_s`` for the answer, abort the run (False)."""
        core = self.core
        with self.lock:
            if core.plant.step_count != last_step:
                return True
            waited_ns = core.clock.now_ns() - self._last_step_ns
            if waited_ns < self._timeout_ns:
                self.republish_pending()
                # The controller went silent for a whole re-send period: if it was
                # restarted, its commands number afresh and it answers each state once,
                # too few for the sequence check to take it up by itself. The next
                # command answering the pending state is taken as is.
                core.restart_commands()
                return True
            self._running = False  # a late answer steps nothing now
            self._done.set()  # the run thread's wait ends
            timeout = f"(plant.lockstep_timeout_s = {core.config.plant.lockstep_timeout_s:g})"
            if self.holds.holding(self._sim_time_ns()):
                why = (f"lockstep: held at sim {self._sim_time_ns() / NS_PER_S:.3f} s for "
                       f"{waited_ns / NS_PER_S:.1f} s {timeout}: no release from the "
                       "launcher, which injects a fault there")  # fmt: skip
            else:
                why = (f"lockstep: no answer to state {self.pending_state} for "
                       f"{waited_ns / NS_PER_S:.1f} s {timeout}: the controller is gone or "
                       "stuck")  # fmt: skip
            core.abort(Abort.LOCKSTEP_TIMEOUT, why)
            return False

    def republish_pending(self) -> None:
        """Send the records of the states in flight again, byte for byte (same seq and
        stamps; a state carries its tick's contact and proximity): the pending tick's
        and, with a lockstep delay, those whose answers the plant still needs.

        A controller that has them ignores them (or its tick barrier drops them); one
        that missed them (e.g. not yet subscribed) gets the whole tick; a recorder logs
        the same samples at the same times.
        """
        self.sent.resend()

    def release(self, at_ns: int) -> None:
        """The launcher released the holds at or before sim instant ``at_ns`` (on a Zenoh
        thread): the answers kept at one are taken now, in the order they came."""
        with self.lock:
            self.holds.release(at_ns)
            held, self._held = self._held, {}
            for state_seq in sorted(held):  # the pending state's answer first
                self._cycle_locked(*held[state_seq])

    def _sim_time_ns(self) -> int:
        return int(self.core.state_rec["sim_time_ns"])

    def _cycle(self, command: np.ndarray, rx_ns: int) -> None:
        """Apply the command answering the pending state, step, publish the next state;
        at a hold, keep it until released."""
        with self.lock:
            self._cycle_locked(command, rx_ns)

    def _cycle_locked(self, command: np.ndarray, rx_ns: int) -> None:
        core = self.core
        if not self._running or self._done.is_set():
            return
        state_seq = int(command["state_seq"])
        if self.holds and self.holds.holding(self._sim_time_ns()):
            # Held: the first answer to each state in flight is kept, as it would have
            # been taken (the answers to the states after the pending one come meanwhile,
            # and are not sent twice).
            if self.pending_state <= state_seq <= core.state_seq and state_seq not in self._held:
                self._held[state_seq] = (command.copy(), rx_ns)
            else:
                core.unanswered_commands += 1
            return
        if state_seq != self.pending_state:
            core.unanswered_commands += 1
            return
        applied_ns = core.clock.now_ns()
        self._last_step_ns = applied_ns
        core.apply(command)
        if not core.should_step():
            self._done.set()
        answered_tx_ns = int(command["trace_ns"][Stage.PLANT_STATE_TX])  # its state's
        core.publish_state(command, rx_ns, applied_ns)
        self.cycle_stats.add(answered_tx_ns, core.state_rec["trace_ns"])
        self._flush_at_hold()

    def _flush_at_hold(self) -> None:
        """The newest state reached a hold: the observers' copy of the states goes out
        now (not when its batch fills), so the launcher sees the instant."""
        if self.holds and self.holds.holding(self._sim_time_ns()):
            self.core.outputs.flush()

    def figures(self) -> PacingFigures:
        return PacingFigures(lockstep_cycle_us=self.cycle_stats.summary())
