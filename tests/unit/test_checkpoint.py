"""The plant's checkpoint and resume, without a bus: the file, the physics, the loop."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from teleop.bus.messages import JOINT_COMMAND, Event, Stage
from teleop.core.clock import FakeClock
from teleop.core.config import load_config
from teleop.sim.checkpoint import (
    HEADER_BYTES,
    SLOT_ACTIVE,
    SLOT_BYTES,
    SLOT_LENGTH,
    SLOT_STATE_SEQ,
    CheckpointError,
    CheckpointStore,
    Snapshot,
)
from teleop.sim.pacing import LockstepPacer
from teleop.sim.plant import Plant, initial_configuration
from teleop.sim.plant_loop import PlantLoop
from teleop.sim.stepping import Abort

from .test_stepping import Recorded

# A checkpoint every 10 ticks (bus periods) of the default loop rate.
CHECKPOINT_S = 10 * load_config(None).tick_s
LOCKSTEP = ('run.mode="lockstep"', f"plant.checkpoint_s={CHECKPOINT_S!r}")


def store_in(tmp_path: Path) -> CheckpointStore:
    return CheckpointStore(tmp_path / "plant.checkpoint")


def answer(seq: int, state_seq: int, now_ns: int, qd: float) -> np.ndarray:
    rec = JOINT_COMMAND.new()
    rec["seq"] = seq
    rec["state_seq"] = state_seq
    rec["n_joints"] = 6
    rec["qd_ref_rad_s"][:6] = qd
    rec["gripper_cmd"] = 0.5
    rec["trace_ns"][Stage.CONTROLLER_TX] = now_ns
    return rec


class Incarnation:
    """One plant process's loop on a run thread, driven by a lockstep 'controller'."""

    def __init__(self, tmp_path: Path, steps: int, *overrides: str) -> None:
        self.config = load_config(None, [*LOCKSTEP, *overrides])
        self.out, self.clock = Recorded(), FakeClock(start_ns=10**12)
        self.loop = PlantLoop(self.config, self.out, self.clock, store_in(tmp_path))
        assert isinstance(self.loop.pacer, LockstepPacer)
        self.pacer = self.loop.pacer
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.loop.run, args=(self.stop, steps))
        self.thread.start()

    def answer_until(self, step: int, first_command_seq: int) -> int:
        """Answer each pending state (the 'controller') until the plant reaches ``step``;
        the next command seq."""
        pacer, clock, seq = self.pacer, self.clock, first_command_seq
        core = pacer.core
        while core.plant.step_count < step and not core.finished:
            pending = pacer.pending_state
            if pending < 0 or not pacer.running:
                clock.advance(1)  # the run thread has not started lockstep yet
                continue
            clock.advance(1_000_000)
            self.loop.on_command(answer(seq, pending, clock.now_ns(), 0.2), clock.now_ns())
            seq += 1
        return seq

    def kill(self) -> None:
        self.stop.set()
        self.thread.join(timeout=30)
        assert not self.thread.is_alive()


def test_a_snapshot_survives_the_file_and_refuses_damage(tmp_path):
    store = store_in(tmp_path)
    assert not store.found and store.load("m" * 64) is None  # a fresh file: no snapshot
    for step in (7, 8):  # the second goes to the other slot
        store.save(Snapshot("m" * 64, step, 123, np.arange(5.0), np.ones(6), {"x": np.int64(1)}))
    store.marks[SLOT_STATE_SEQ] = 41
    del store  # the process's mapping gone: the file keeps what was stored
    again = store_in(tmp_path)
    back = again.load("m" * 64)
    assert again.found and again.progress().state_seq == 41
    assert back is not None and (back.step, back.t_ns, back.loop) == (8, 123, {"x": 1})
    assert np.array_equal(back.mujoco_state, np.arange(5.0))
    assert np.array_equal(back.hold_q_rad, np.ones(6))
    with pytest.raises(CheckpointError, match="another model"):
        again.load("n" * 64)
    assert again.path is not None
    active = int(again.marks[SLOT_ACTIVE])
    end = HEADER_BYTES + active * SLOT_BYTES + int(again.marks[SLOT_LENGTH + active])
    data = bytearray(again.path.read_bytes())
    data[end - 1] ^= 0xFF  # the last byte of the newest snapshot's body
    again.path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="damaged"):
        store_in(tmp_path).load("m" * 64)
    with pytest.raises(CheckpointError, match="not a plant checkpoint"):
        Snapshot.decode(b"something else")


def test_a_restored_plant_takes_the_very_same_next_steps():
    config = load_config(None, ['run.scenario="grasp"'])
    first = Plant(config)
    first.reset(initial_configuration(config))
    rng = np.random.default_rng(0)
    commands = rng.normal(0.0, 0.3, size=(400, 6))
    for qd in commands[:200]:
        first.step(qd, 0.5)
    second = Plant(config)
    second.restore(first.integration_state(), first.step_count, first.gripper_cmd)
    assert second.sample().step == first.step_count
    for i, qd in enumerate(commands[200:]):
        gripper = 0.2 if i > 100 else 0.5
        first.step(qd, gripper)
        second.step(qd, gripper)
    assert first.state_sha256() == second.state_sha256()


def test_a_restarted_plant_resumes_its_run_where_the_stream_stopped(tmp_path):
    first = Incarnation(tmp_path, 200)
    command_seq = first.answer_until(35, 0)
    first.kill()  # stopped, as if killed: the next incarnation finds its files
    states = {int(r["seq"]): r for r in first.out.records["plant_state"]}
    last = max(states)
    assert first.loop.core.checkpoint_every_steps == 10
    assert last == 35 and first.loop.core.checkpoint_cost.taken == 4  # steps 0, 10, 20, 30

    second = Incarnation(tmp_path, 200)
    second.answer_until(60, command_seq)
    second.kill()
    resumed = second.out.records["plant_state"]
    # The stream goes on: next seq, step and sim time; no restart, no gap.
    assert [int(r["seq"]) for r in resumed[:3]] == [36, 37, 38]
    assert int(resumed[0]["sim_time_ns"]) == 36 * second.loop.core.period_ns
    # The world is the checkpoint's (step 30): 5 steps of physics lost.
    assert np.array_equal(resumed[0]["q_rad"], states[30]["q_rad"])
    events = second.out.records["plant_events"]
    assert [Event(int(e["event"])) for e in events] == [Event.RESUMED]
    assert float(events[0]["value"]) == 5.0 and int(events[0]["step"]) == 36
    summary = second.loop.summary()
    assert summary["resumes"][0]["checkpoint_step"] == 30
    assert summary["resumes"][0]["steps_lost"] == 5
    # Counters go on from the checkpoint; commands keep their sequence (none lost).
    assert summary["commands_applied"] > 30 and summary["command_stream"]["lost"] == 0
    assert summary["command_stream"]["restarts"] == 0


def test_a_restart_that_cannot_resume_aborts_the_run(tmp_path):
    (tmp_path / "plant.checkpoint").write_bytes(b"garbage")
    plant = Incarnation(tmp_path, 200)
    plant.thread.join(timeout=30)
    core = plant.loop.core
    assert core.aborted and not core.finished
    assert "cannot resume" in (core.failure or "")
    events = plant.out.records["plant_events"]
    assert [Event(int(e["event"])) for e in events] == [Event.ABORTED]
    assert float(events[0]["value"]) == Abort.RESUME_FAILED
    assert "plant_state" not in plant.out.records  # not a single state of a reset world


def test_lockstep_without_an_answer_ends_the_run_after_its_bound(tmp_path):
    plant = Incarnation(tmp_path, 200, "plant.lockstep_timeout_s=5")
    plant.answer_until(3, 0)
    pacer, core = plant.pacer, plant.loop.core
    assert pacer.waited(core.plant.step_count)  # within the bound: re-sent
    assert plant.out.resent
    plant.clock.advance(5_000_000_000)
    assert not pacer.waited(core.plant.step_count)
    plant.thread.join(timeout=30)
    assert core.aborted and not core.finished and "no answer" in (core.failure or "")
    assert Event(int(plant.out.records["plant_events"][-1]["event"])) is Event.ABORTED
