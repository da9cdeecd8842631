"""The operator's hand over several robots (teleop.devices.scripted.loop.ScriptedStation):
which loop an arrival goes to, and when the hand moves on. The loops here are stand-ins
that note what they are handed (the station's contract with ScriptedLoop); the whole
operator on two robots runs in tests/e2e/test_robots.py."""

from __future__ import annotations

from typing import Any

from teleop.devices.scripted.loop import PoseArrival, RunStarted, ScriptedStation


class NotingLoop:
    """What ScriptedStation calls of an ScriptedLoop; its task is done at ``done_at``."""

    def __init__(self, done_at: int | None = None, lockstep: bool = True) -> None:
        self.done_at = done_at
        self.lockstep = lockstep
        self.arrivals: list[tuple[int, bool]] = []
        self.taken_over: list[int] = []
        self.started = 0

    @property
    def done_reported(self) -> bool:
        return self.done_at is not None and any(t >= self.done_at for t, _ in self.arrivals)

    def left_behind(self, m: int) -> bool:
        return not self.lockstep

    def on_arrival(self, m: int, catch_up: bool = False) -> None:
        self.arrivals.append((m, catch_up))

    def take_over(self, tick: int) -> None:
        self.taken_over.append(tick)

    def on_started(self) -> None:
        self.started += 1
        self.arrivals.clear()  # a new run: the task starts over

    def summary(self) -> dict[str, Any]:
        return {"arrivals": len(self.arrivals)}


def poses(ticks: range, robots: int = 2) -> list[PoseArrival]:
    return [PoseArrival(robot, tick, tick) for tick in ticks for robot in range(robots)]


def test_the_hand_drives_one_robot_then_the_next_from_where_it_left_off():
    first, second = NotingLoop(done_at=50), NotingLoop()
    station = ScriptedStation([first, second])  # type: ignore[list-item]
    decided: list[int] = []
    # One batch across the hand-over: what came after it goes to the next robot.
    station.take(poses(range(0, 100, 10)), decided.append)
    assert [t for t, _ in first.arrivals] == [0, 10, 20, 30, 40, 50]
    assert second.taken_over == [50]
    assert [t for t, _ in second.arrivals] == [50, 60, 70, 80, 90]  # 50: its own pose
    assert station.active == 1 and len(decided) == 11
    station.take(poses(range(100, 120, 10)))
    assert [t for t, _ in first.arrivals][-1] == 50  # observed, no longer driven
    assert [t for t, _ in second.arrivals][-2:] == [100, 110]
    assert station.summary(["arm0", "arm1"]) == {
        "robots": {"arm0": {"arrivals": 6}, "arm1": {"arrivals": 7}}
    }


def test_the_last_robot_keeps_the_hand_and_a_new_run_starts_with_robot_zero():
    first, second = NotingLoop(done_at=20), NotingLoop(done_at=0)
    station = ScriptedStation([first, second])  # type: ignore[list-item]
    station.take(poses(range(0, 40, 10)))
    assert station.active == 1 and second.done_reported  # done too, no robot after it
    station.take([RunStarted(1), RunStarted(0), *poses(range(0, 10, 10))])
    assert first.started == 1 and second.started == 1
    assert station.active == 0 and first.arrivals[-1] == (0, False)


def test_a_late_operator_decides_the_driven_robots_newest_pose_only():
    """Realtime, behind: of the driven robot's poses queued, only the newest is decided
    (the other robot's poses do not count as newer ones)."""
    first, second = NotingLoop(lockstep=False), NotingLoop(lockstep=False)
    station = ScriptedStation([first, second])  # type: ignore[list-item]
    station.take(poses(range(0, 40, 10)))
    assert first.arrivals == [(30, True)] and second.arrivals == []


def test_one_robot_is_its_loops_summary():
    station = ScriptedStation([NotingLoop()])  # type: ignore[list-item]
    station.take(poses(range(0, 20, 10), robots=1))
    assert station.summary(["arm0"]) == {"arrivals": 2}
