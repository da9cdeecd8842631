"""The plant's pacers without a bus, each on the fake clock: plant tick, device clock,
lockstep, and the one choice among them."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from teleop.bus.messages import PLANT_STATE, RUN_EVENT, Event, Flag, Stage
from teleop.core.clock import NS_PER_S, FakeClock
from teleop.core.config import load_config
from teleop.sim.pacing import (
    CATCH_UP_MAX_PERIODS,
    OWN_STEP_AFTER_PERIODS,
    DeviceClockGrid,
    DeviceClockPacer,
    LockstepPacer,
    SentTicks,
    TickPacer,
    make_pacer,
)
from teleop.sim.plant_loop import PlantLoop

from .test_stepping import Recorded, command

TELEOP = ('run.scenario="grasp"', 'run.mode="realtime"')
# DeviceClockGrid alone: pure arithmetic, on any period.
PERIOD_NS = 1_000_000


def make(*overrides: str, holds_ns: tuple[int, ...] = ()):
    """The configured pacer at the start of a run (not yet paced), its outputs, its clock."""
    config = load_config(None, overrides)
    outputs, clock = Recorded(), FakeClock(start_ns=10**12)
    pacer = make_pacer(config, outputs, clock, holds_ns=holds_ns)
    pacer.core.begin_run(None)
    return pacer, outputs, clock


@pytest.mark.parametrize(
    ("overrides", "kind"),
    [
        (('run.mode="lockstep"',), LockstepPacer),
        (('run.mode="lockstep"', 'run.scenario="grasp"'), LockstepPacer),
        (TELEOP, DeviceClockPacer),
        ((*TELEOP, "plant.apply_on_arrival=false"), TickPacer),
        (('run.mode="realtime"', 'run.scenario="path-following"'), TickPacer),
    ],
)
def test_the_pacer_is_chosen_once_from_the_mode(overrides, kind):
    pacer, out, clock = make(*overrides)
    assert type(pacer) is kind
    # Only lockstep keeps what it sent, for a re-send.
    assert isinstance(pacer.core.outputs, SentTicks) == (kind is LockstepPacer)


# -- plant tick --------------------------------------------------------------------------
def test_plant_tick_pacing_brakes_on_a_stale_command_and_resumes():
    pacer, out, clock = make('run.mode="realtime"')
    assert isinstance(pacer, TickPacer)
    core = pacer.core
    pacer.start()
    period_ns = core.period_ns  # one tick (bus period)
    limit_ticks = round(core.config.plant.watchdog_s * NS_PER_S / period_ns)
    assert limit_ticks * period_ns == core.watchdog.limit_ns
    pacer.tick()  # no command yet: braking, no event
    assert out.records["plant_state"][-1]["flags"] == Flag.BRAKING and out.events() == []
    pacer.on_command(command(1, state_seq=1, now_ns=clock.now_ns()), clock.now_ns())
    # Applied while state 1 (the one answered) went out less than the limit ago.
    for _ in range(limit_ticks - 1):
        clock.advance(period_ns)
        pacer.tick()
    assert core.commands_applied == 1 and out.events() == []
    assert out.records["plant_state"][-1]["flags"] == Flag.NONE
    clock.advance(period_ns)
    pacer.tick()  # the command now answers a state sent the limit ago
    assert out.events() == [Event.WATCHDOG_BRAKE]
    assert out.records["plant_state"][-1]["flags"] == Flag.BRAKING
    fresh = command(2, state_seq=core.state_seq, now_ns=clock.now_ns())
    pacer.on_command(fresh, clock.now_ns())
    pacer.tick()
    assert out.events() == [Event.WATCHDOG_BRAKE, Event.WATCHDOG_RESUME]
    assert out.records["plant_state"][-1]["cmd_seq_applied"] == 2
    summary = core.summary(pacer.figures())
    assert (summary["stale_commands"], summary["commands_applied"]) == (1, 2)


class Stalling(Recorded):
    """Outputs whose put of one state takes ``stall_ns`` of the fake clock."""

    def __init__(self, clock: FakeClock, stall_seq: int, stall_ns: int) -> None:
        super().__init__()
        self.clock, self.stall_seq, self.stall_ns = clock, stall_seq, stall_ns

    def put(self, stream: str, rec: np.ndarray) -> bytes:
        if stream == "plant_state" and int(rec["seq"]) == self.stall_seq:
            self.clock.advance(self.stall_ns)
        return super().put(stream, rec)


def test_plant_tick_pacing_steps_once_a_period_and_skips_a_stall_never_bursting():
    config = load_config(None, ['run.mode="realtime"'])
    clock = FakeClock(start_ns=10**12)
    period_ns = round(config.tick_s * NS_PER_S)  # one tick (bus period)
    out = Stalling(clock, stall_seq=5, stall_ns=7 * period_ns // 2)  # 3.5 periods
    pacer = TickPacer(make_pacer(config, out, clock).core)
    assert pacer.core.period_ns == period_ns
    pacer.core.begin_run(20)
    start_ns = clock.now_ns()
    pacer.run(threading.Event(), resumed=False)
    sent_ns = np.array([int(s["t_source_ns"]) for s in out.records["plant_state"]])
    assert pacer.core.plant.step_count == 20 and len(sent_ns) == 21
    assert np.diff(sent_ns).min() == period_ns  # never two steps in one period
    figures = pacer.figures()
    assert figures.skipped_ticks == 3  # the periods the stall took, given up
    assert clock.now_ns() - start_ns == (20 + 3) * period_ns
    assert figures.loop["skipped"] == 3 and figures.arrival is None


# -- device clock ------------------------------------------------------------------------
def test_device_clock_grid_steps_each_device_period_once():
    grid = DeviceClockGrid(PERIOD_NS, start_ns=0)
    assert not grid.locked and grid.own_step_ns == OWN_STEP_AFTER_PERIODS * PERIOD_NS
    deadline_ns = 10_000_000  # the device's period, not the arrival time
    grid.lock(deadline_ns)
    assert grid.periods_ahead(deadline_ns) == 0
    grid.stepped()
    # The next device period is the next step's, whatever the arrival jitter.
    assert grid.periods_ahead(deadline_ns + PERIOD_NS) == 0
    # A command of a period already stepped is late; one two periods on has a gap.
    assert grid.periods_ahead(deadline_ns) == -1
    assert grid.periods_ahead(deadline_ns + 3 * PERIOD_NS) == 2
    # Without a command, the plant steps the period itself a fixed time after it began.
    assert grid.own_step_ns == deadline_ns + (1 + OWN_STEP_AFTER_PERIODS) * PERIOD_NS
    grid.skip(3)  # a stall
    assert grid.skipped == 3 and grid.periods_ahead(deadline_ns + 4 * PERIOD_NS) == 0
    with pytest.raises(ValueError):
        DeviceClockGrid(0, 0)


def begun(*overrides: str) -> tuple[DeviceClockPacer, Recorded, FakeClock]:
    pacer, out, clock = make(*TELEOP, *overrides)
    assert isinstance(pacer, DeviceClockPacer)
    pacer.core.publish_state()
    pacer.begin()
    return pacer, out, clock


# The device's clock, hours away from the plant's (another host, or a time namespace).
DEVICE_CLOCK_OFFSET_NS = 3 * 3600 * NS_PER_S
# From a device period's start to its command's arrival at the plant.
ARRIVAL_AFTER_NS = 300_000


def test_device_clock_pacing_steps_once_per_device_period_and_never_runs_ahead():
    """Commands step at once; a late one merges, a gap is filled, sim time follows the
    device's periods; the device's clock is another host's, hours away from the plant's."""
    pacer, out, clock = begun()
    core = pacer.core
    period_ns = core.period_ns  # the device's period: one tick (bus period)
    t0_ns = clock.now_ns()  # the plant's clock when the device's period 0 began
    device_t0_ns = t0_ns + DEVICE_CLOCK_OFFSET_NS

    def arrive(seq: int, periods: int, *, after_ns: int = ARRIVAL_AFTER_NS) -> None:
        """The command of the device's period ``periods``, arriving ``after_ns`` after
        that period began (never before what arrived already)."""
        clock.advance(max(0, t0_ns + periods * period_ns + after_ns - clock.now_ns()))
        deadline_ns = device_t0_ns + periods * period_ns
        rec = command(seq, max(core.state_seq, 0), clock.now_ns(), deadline_ns=deadline_ns)
        pacer.on_command(rec, clock.now_ns())

    for seq in range(3):  # the first commands: the plant learns the device's clock
        arrive(seq, seq)
    assert core.plant.step_count == pacer.counts.steps_on_arrival == 3
    arrive(3, 3, after_ns=ARRIVAL_AFTER_NS + period_ns // 2)  # jitter: still its period
    assert core.plant.step_count == 4
    arrive(4, 3)  # late (its period was stepped): no step of its own, held for the next
    assert core.plant.step_count == 4 and pacer.counts.commands_late == 1
    arrive(5, 5)  # two periods on: the period in between (no command) is stepped first
    assert core.plant.step_count == 6 and pacer.counts.steps_without_command == 1
    arrive(6, 22)  # after a long gap only CATCH_UP_MAX_PERIODS are stepped back to back
    assert core.plant.step_count == 7 + CATCH_UP_MAX_PERIODS
    grid = pacer.grid
    assert grid is not None and grid.locks == 1
    assert grid.skipped == 22 - 6 - CATCH_UP_MAX_PERIODS
    # Sim time follows the device's periods: the next step is its period 23, which the
    # plant steps itself if no command comes OWN_STEP_AFTER_PERIODS after it began, as
    # the fastest commands place the device's clock on the plant's.
    assert grid.periods_ahead(device_t0_ns + 23 * period_ns) == 0
    own_step_ns = t0_ns + ARRIVAL_AFTER_NS + (23 + OWN_STEP_AFTER_PERIODS) * period_ns
    assert pacer.own_step_due(clock.now_ns()) == own_step_ns - clock.now_ns()
    arrive(6, 23)  # not newer than the last: dropped, counted
    assert core.command_in.seq.reordered == 1
    summary = core.summary(pacer.figures())["arrival"]
    assert summary["commands_late"] == 1 and summary["commands_reordered"] == 1
    assert summary["device_clock_refused"] == summary["device_clock_relearnt"] == 0


@pytest.mark.parametrize("hours", [2 * 3, -3])
def test_a_device_restarted_on_another_clock_is_followed(hours: int):
    """A device restarted on another host, its deadlines hours away from the last
    device's: the plant follows its periods within a command or two, and learns where its
    clock lies."""
    pacer, out, clock = begun()
    core = pacer.core
    period_ns = core.period_ns
    device_t0_ns = clock.now_ns() + DEVICE_CLOCK_OFFSET_NS
    seq = 0

    def arrive(deadline_ns: int) -> None:
        nonlocal seq
        clock.advance(period_ns)
        seq += 1
        rec = command(seq, core.state_seq, clock.now_ns(), deadline_ns=deadline_ns)
        pacer.on_command(rec, clock.now_ns())

    for k in range(3):  # the first device
        arrive(device_t0_ns + k * period_ns)
    assert core.plant.step_count == 3
    new_t0_ns = device_t0_ns + hours * 3600 * NS_PER_S
    for k in range(4):
        arrive(new_t0_ns + k * period_ns)
    assert pacer.grid is not None and pacer.grid.locks == 2
    if hours > 0:
        # Its first two commands are stamped in the future of the clock the plant knew:
        # refused (the second least delay is the new clock's from the third), held for
        # the next step, never stepped on their own.
        assert pacer.device_clock.refused == 2 and pacer.counts.commands_late == 2
        assert pacer.counts.steps_on_arrival == 3 + 2
    else:
        # Behind the known clock: its periods are followed at once; the third command in a
        # row that far behind starts the clock afresh.
        assert pacer.device_clock.relearnt == 1 and pacer.counts.commands_late == 0
        assert pacer.counts.steps_on_arrival == 3 + 4
    # Its clock is learnt: each of its commands arrived 4 periods after its deadline (the
    # first device's clock started at the plant's, the test's clock 3 periods before).
    learnt_ns = 4 * period_ns - DEVICE_CLOCK_OFFSET_NS - hours * 3600 * NS_PER_S
    assert pacer.device_clock.offset_ns == learnt_ns


def test_device_clock_pacing_steps_periods_without_commands_itself_and_skips_stalls():
    pacer, out, clock = begun()
    core = pacer.core
    period_ns = core.period_ns  # one tick (bus period)
    assert pacer.own_step_due(clock.now_ns()) == OWN_STEP_AFTER_PERIODS * period_ns
    clock.advance(OWN_STEP_AFTER_PERIODS * period_ns)
    pacer.own_step(clock.now_ns())
    assert core.plant.step_count == 1 and pacer.counts.stalls == 0
    clock.advance(50 * period_ns)  # a stall: skip, never burst
    pacer.own_step(clock.now_ns())
    assert core.plant.step_count == 2 and pacer.counts.stalls == 1
    assert pacer.own_step_due(clock.now_ns()) > -CATCH_UP_MAX_PERIODS * period_ns
    figures = pacer.figures()
    assert figures.overrun_fraction == 0.5 and figures.skipped_ticks == pacer.grid.skipped


def test_device_clock_pacing_sheds_a_command_older_than_the_shed_age_and_logs_its_loop():
    pacer, out, clock = begun()
    core = pacer.core
    for seq in (1, 2):  # the link's pace: ages are times beyond its fastest records
        pacer.on_command(command(seq, core.state_seq, clock.now_ns()), clock.now_ns())
        clock.advance(core.period_ns)
    assert core.plant.step_count == 2
    old = command(3, core.state_seq, clock.now_ns() - 10 * core.command_in.shed_age_ns)
    pacer.on_command(old, clock.now_ns())
    assert core.plant.step_count == 2 and core.command_in.shed == 1
    assert len(core.command_in.shed_log) == 1


def test_device_clock_pacing_steps_nothing_outside_its_run():
    pacer, out, clock = make(*TELEOP)
    assert isinstance(pacer, DeviceClockPacer)
    core = pacer.core
    assert pacer.figures().arrival is None  # no grid yet: nothing to report
    core.publish_state()
    pacer.on_command(command(1, 0, clock.now_ns(), deadline_ns=clock.now_ns()), clock.now_ns())
    assert core.plant.step_count == 0 and core.commands_received == 1
    stopped = threading.Event()
    stopped.set()
    pacer.run(stopped, resumed=False)  # begins on a grid, ends at once
    assert pacer.grid is not None and pacer.figures().arrival is not None
    pacer.on_command(command(2, 1, clock.now_ns(), deadline_ns=clock.now_ns()), clock.now_ns())
    assert core.plant.step_count == 0 and core.commands_received == 2


# -- lockstep ----------------------------------------------------------------------------
def started(
    *overrides: str, holds_ns: tuple[int, ...] = ()
) -> tuple[LockstepPacer, Recorded, FakeClock]:
    pacer, out, clock = make('run.mode="lockstep"', *overrides, holds_ns=holds_ns)
    assert isinstance(pacer, LockstepPacer)
    pacer.start()
    return pacer, out, clock


def test_lockstep_steps_only_on_the_answer_to_the_pending_state():
    pacer, out, clock = started("plant.lockstep_delay_steps=1")
    core = pacer.core
    # State 0, then the delay step no command answers: state 1; state 0's answer is due.
    assert core.state_seq == 1 and pacer.pending_state == 0 and pacer.running
    pacer.on_command(command(1, state_seq=1, now_ns=clock.now_ns()), clock.now_ns())
    assert core.plant.step_count == 1 and core.unanswered_commands == 1
    clock.advance(core.period_ns)
    answer = command(2, state_seq=0, now_ns=clock.now_ns())
    state_0 = out.records["plant_state"][0]
    answer["trace_ns"][Stage.PLANT_STATE_TX] = state_0["trace_ns"][Stage.PLANT_STATE_TX]
    answer["trace_ns"][Stage.CONTROLLER_RX] = clock.now_ns()
    pacer.on_command(answer, clock.now_ns())
    assert core.plant.step_count == 2 and core.commands_applied == 1
    state = out.records["plant_state"][-1]
    assert int(state["seq"]) == 2 and int(state["cmd_seq_applied"]) == 2
    assert pacer.figures().lockstep_cycle_us  # the cycle's stamps are all there


def test_lockstep_re_sends_the_states_in_flight_byte_for_byte():
    pacer, out, clock = started("plant.lockstep_delay_steps=1")
    scene_ticks = pacer.core.scene

    def tick_streams(tick: int) -> list[str]:
        """A tick's records: its state, then its scene on the scene ticks."""
        scene = ["tool_pose", "objects"] if scene_ticks.is_sample(tick) else []
        return ["plant_state", *scene]

    def sent() -> set[tuple[str, bytes]]:
        return {
            (stream, rec.tobytes())
            for stream in ("plant_state", "tool_pose", "objects")
            for rec in out.records.get(stream, [])
        }

    assert not scene_ticks.is_sample(1)  # state 1 has no scene of its own
    pacer.core.publish_event(Event.GRASP, 1.0)
    pacer.republish_pending()
    # States 0 and 1 are in flight, state 0 with its tick's scene; no event is re-sent.
    assert [stream for stream, _ in out.resent] == tick_streams(0) + tick_streams(1)
    assert set(out.resent) == sent()
    out.resent.clear()
    pacer.on_command(command(1, state_seq=0, now_ns=clock.now_ns()), clock.now_ns())
    pacer.republish_pending()  # states 1 and 2 now, each with its tick's scene if any
    assert [stream for stream, _ in out.resent] == tick_streams(1) + tick_streams(2)
    states = [d for stream, d in out.resent if stream == "plant_state"]
    assert [int(np.frombuffer(d, PLANT_STATE.dtype)["seq"][0]) for d in states] == [1, 2]
    assert set(out.resent) <= sent()  # byte for byte as first sent


def test_lockstep_without_an_answer_re_sends_then_ends_the_run_after_its_bound():
    pacer, out, clock = started("plant.lockstep_timeout_s=5")
    core = pacer.core
    assert pacer.waited(last_step=-1)  # it stepped since: nothing to do
    assert not out.resent
    assert pacer.waited(core.plant.step_count)  # within the bound: re-sent
    assert out.resent and not core.aborted
    clock.advance(5_000_000_000)
    assert not pacer.waited(core.plant.step_count)
    assert core.aborted and "no answer" in (core.failure or "") and not pacer.running
    assert out.events()[-1] is Event.ABORTED
    steps = core.plant.step_count
    pacer.on_command(command(1, pacer.pending_state, clock.now_ns()), clock.now_ns())
    assert core.plant.step_count == steps  # a late answer steps nothing


def _answer_pending(pacer: LockstepPacer, clock: FakeClock, seq: int) -> None:
    pacer.on_command(command(seq, pacer.pending_state, clock.now_ns()), clock.now_ns())


def test_lockstep_holds_at_a_fault_instant_until_released_then_steps_with_the_kept_answer():
    """Told a fault's instant, the plant waits at the first state at or past it (the
    observers' copy flushed, so the launcher sees it) and steps on with the answer it kept
    once released; a release at a later instant releases every hold up to it."""
    period_ns = load_config(None, ['run.mode="lockstep"']).tick_s * NS_PER_S
    hold_1, hold_2 = round(2.5 * period_ns), round(5 * period_ns)
    pacer, out, clock = started("plant.lockstep_delay_steps=0", holds_ns=(hold_2, hold_1))
    core = pacer.core
    for seq in range(1, 3):
        _answer_pending(pacer, clock, seq)
    flushes = out.flushes
    _answer_pending(pacer, clock, 3)  # state 3 (3 periods) is the first past hold 1
    assert core.plant.step_count == 3 and int(core.state_rec["sim_time_ns"]) >= hold_1
    assert out.flushes == flushes + 1  # the observers see it now
    _answer_pending(pacer, clock, 4)
    assert core.plant.step_count == 3 and out.flushes == flushes + 1  # held
    assert pacer.waited(core.plant.step_count) and out.resent  # still re-sends meanwhile
    pacer.release(hold_1 - 1)  # not yet this one
    assert core.plant.step_count == 3
    pacer.release(hold_1)
    assert core.plant.step_count == 4 and int(core.state_rec["cmd_seq_applied"]) == 4
    _answer_pending(pacer, clock, 5)
    pacer.release(hold_2 + round(10 * period_ns))  # released before the plant got there
    for seq in range(6, 10):
        _answer_pending(pacer, clock, seq)
    assert core.plant.step_count == 9


def test_a_held_plant_keeps_the_answers_to_every_state_in_flight_and_takes_them_in_order():
    """With a state in flight besides the pending one, its answer comes during the hold
    too; the controller sends it once, so it is kept, not dropped as not yet due."""
    pacer, out, clock = started("plant.lockstep_delay_steps=1", holds_ns=(0,))
    core = pacer.core
    assert core.state_seq == 1 and pacer.pending_state == 0  # state 1 at sim > 0: held
    _answer_pending(pacer, clock, 1)
    pacer.on_command(command(2, state_seq=1, now_ns=clock.now_ns()), clock.now_ns())
    pacer.on_command(command(3, state_seq=0, now_ns=clock.now_ns()), clock.now_ns())
    assert core.plant.step_count == 1 and core.unanswered_commands == 1  # 0's answered
    pacer.release(0)
    assert core.plant.step_count == 3 and pacer.pending_state == 2
    assert [int(r["cmd_seq_applied"]) for r in out.records["plant_state"][-2:]] == [1, 2]


def test_a_plant_held_without_a_release_ends_the_run_saying_it_was_held():
    pacer, out, clock = started("plant.lockstep_timeout_s=5", "plant.lockstep_delay_steps=0",
                                holds_ns=(0,))  # fmt: skip
    _answer_pending(pacer, clock, 1)
    core = pacer.core
    assert core.plant.step_count == 0
    clock.advance(5 * NS_PER_S)
    assert not pacer.waited(core.plant.step_count)
    assert core.aborted and "no release from the launcher" in (core.failure or "")
    pacer.release(0)  # too late: the run is over
    assert core.plant.step_count == 0


def test_only_a_lockstep_plant_can_be_held():
    with pytest.raises(ValueError, match="lockstep only"):
        make(*TELEOP, holds_ns=(NS_PER_S,))


def test_a_lockstep_run_starts_steps_on_answers_and_finishes():
    """The loop's run: STARTED, the steps the answers drive (run thread waiting), FINISHED."""
    config = load_config(None, ['run.mode="lockstep"', "plant.lockstep_delay_steps=0"])
    out, clock = Recorded(), FakeClock(start_ns=10**12)
    loop = PlantLoop(config, out, clock)
    pacer, core = loop.pacer, loop.core
    assert isinstance(pacer, LockstepPacer)
    stop = threading.Event()
    runner = threading.Thread(target=loop.run, args=(stop, 3))
    runner.start()
    try:
        while core.state_seq < 0:  # state 0 published (answers wait for the lock)
            runner.join(timeout=0.001)
        # a command answering a state not sent yet is rejected before anything else
        loop.on_command(command(1, state_seq=5, now_ns=clock.now_ns()), clock.now_ns())
        assert core.plant.step_count == 0 and core.commands_future_state == 1
        for seq in range(3):
            loop.on_command(command(seq + 2, core.state_seq, clock.now_ns()), clock.now_ns())
        runner.join(timeout=30)
        assert not runner.is_alive()
    finally:
        stop.set()
        runner.join(timeout=30)
    assert core.finished and core.plant.step_count == 3 and core.commands_applied == 3
    assert out.events() == [Event.STARTED, Event.FINISHED]
    assert [int(r["seq"]) for r in out.records["plant_state"]] == [0, 1, 2, 3]
    assert out.flushes == 1
    assert PLANT_STATE.size and RUN_EVENT.size  # the records' layouts are the bus's
