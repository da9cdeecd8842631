"""The plant's protective stop: a contact-force limit and a measured tool-speed limit.

Collaborative robots stop when they press too hard or move too fast, whatever they were
told (power and force limiting, ISO/TS 15066). The plant does the same on its own
measurements, after every physics step:

- the contact force the scene (the table, the bin, the arm itself) puts on the gripper
  above ``plant.contact_force_limit_n`` (N; what a free object such as a held cube puts
  on it does not count: its weight and inertia are no press on the scene), or
- the tool point's measured speed above ``plant.tool_speed_stop_m_s`` (the commands are
  already cut to ``plant.tool_speed_limit_m_s``; a tool faster than that is pushed, or
  not following its drives),

trips the stop: the drives hold the arm where it is (the brake), and keep holding while
the command asks for motion. The command that caused the stop has to stop first: the
stop releases once the commands have asked for a tool motion of at most
``plant.protective_release_m_s`` for ``plant.protective_release_s`` in a row (a slow
press whose command dips below that speed now and then is not released and stopped in
turn), and the arm follows the commands again. The contact force goes on being measured
and sent to the operator as usual, so a person at the handle feels what stopped the arm.

Pure bookkeeping (no MuJoCo): :class:`teleop.sim.plant.Plant` feeds it its measurements
and asks it whether to hold; the plant's stepping core announces the transitions as
PROTECTIVE_STOP and PROTECTIVE_RELEASE events and lists every stop in the summary.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any, NamedTuple


def allowed_approach_m_s(separation_m: float, touch_m_s: float, time_s: float) -> float:
    """The speed (m/s) at which the gripper may close in on the scene ``separation_m``
    away (speed and separation monitoring): ``touch_m_s`` plus the separation covered in
    ``time_s``. Commanded at it, the gap closes exponentially with time constant
    ``time_s`` (slow beside the velocity loops, which follow it) until the gripper meets
    the scene at ``touch_m_s``: a contact the force limit stops within its margin,
    instead of an impact it cannot."""
    return touch_m_s + max(separation_m, 0.0) / time_s


class StopCause(enum.IntEnum):
    """Why the plant stopped (the PROTECTIVE_STOP event's value)."""

    CONTACT_FORCE = 1
    TOOL_SPEED = 2


@dataclass
class Stop:
    """One protective stop: when it tripped, on what, and when it released."""

    cause: StopCause
    step: int  # the step after which it tripped
    measured: float  # the force (N) or speed (m/s) that tripped it
    released_step: int | None = None  # the first step that followed a command again
    steps_held: int = 0  # steps the brake held the arm through it

    def summary(self, timestep_s: float) -> dict[str, Any]:
        return {
            "cause": self.cause.name.lower(),
            "t_s": round(self.step * timestep_s, 6),
            "measured": self.measured,
            "released_t_s": None
            if self.released_step is None
            else round(self.released_step * timestep_s, 6),
            "steps_held": self.steps_held,
        }


class Transition(NamedTuple):
    """A stop that tripped (``released`` False) or released."""

    stop: Stop
    released: bool


class ProtectiveStop:
    """Trips on a measurement beyond a limit, holds while commanded to move, releases on
    ``release_steps`` commands in a row that ask for (almost) no motion. Transitions
    since the last :meth:`take_transitions` are kept for the caller to announce."""

    def __init__(
        self,
        contact_force_limit_n: float,
        tool_speed_stop_m_s: float,
        release_m_s: float,
        release_steps: int = 1,
    ) -> None:
        self.contact_force_limit_n = contact_force_limit_n
        self.tool_speed_stop_m_s = tool_speed_stop_m_s
        self.release_m_s = release_m_s
        self.release_steps = release_steps  # still commands in a row that release a stop
        self._still_steps = 0  # of which so far, since the latched stop tripped
        self.stops: list[Stop] = []
        self._transitions: list[Transition] = []  # not yet announced

    @property
    def latched(self) -> bool:
        """Whether the arm is held (a stop tripped and no command released it yet)."""
        return bool(self.stops) and self.stops[-1].released_step is None

    def measure(self, step: int, contact_force_n: float, tool_speed_m_s: float) -> bool:
        """The measurements after ``step``; whether they tripped a stop now (a latched
        stop does not trip again)."""
        if self.latched:
            return False
        if contact_force_n > self.contact_force_limit_n:
            stop = Stop(StopCause.CONTACT_FORCE, step, contact_force_n)
        elif tool_speed_m_s > self.tool_speed_stop_m_s:
            stop = Stop(StopCause.TOOL_SPEED, step, tool_speed_m_s)
        else:
            return False
        self.stops.append(stop)
        self._transitions.append(Transition(stop, released=False))
        self._still_steps = 0
        return True

    def holds(self, step: int, commanded_tool_speed_m_s: float) -> bool:
        """Whether a step with a command asking for this tool motion (m/s, the motion
        part of the command, before any cut) must be held by the brake; the
        ``release_steps``-th command in a row that asks for no more than the release
        speed releases a latched stop from ``step``."""
        if not self.latched:
            return False
        stop = self.stops[-1]
        if commanded_tool_speed_m_s <= self.release_m_s:
            self._still_steps += 1
            if self._still_steps >= self.release_steps:
                stop.released_step = step
                self._transitions.append(Transition(stop, released=True))
                return False
        else:
            self._still_steps = 0
        stop.steps_held += 1
        return True

    def held(self) -> None:
        """A step the brake held for another reason (no command: the watchdog) while
        the stop is latched."""
        if self.latched:
            self.stops[-1].steps_held += 1

    def take_transitions(self) -> list[Transition]:
        """The stops that tripped or released since the last call, in order."""
        taken, self._transitions = self._transitions, []
        return taken

    def summary(self, timestep_s: float) -> dict[str, Any]:
        return {
            "contact_force_limit_n": self.contact_force_limit_n,
            "tool_speed_stop_m_s": self.tool_speed_stop_m_s,
            "release_m_s": self.release_m_s,
            "release_steps": self.release_steps,
            "count": len(self.stops),
            "steps_held": sum(stop.steps_held for stop in self.stops),
            "stops": [stop.summary(timestep_s) for stop in self.stops],
        }
