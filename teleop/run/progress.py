"""What a services run prints while it runs, and the short summary at its end.

:class:`RunProgress` turns what the launcher sees (sim time from the tool pose, the
operator's PHASE events) into a progress line: the task as it is (phase, sim time, task
time), not a fraction of a fixed duration (a grasp ends when the operator is done, long
before ``run.duration_s``). :func:`human_summary` turns the merged summary into a dozen
lines for a person; the full JSON goes to a file. Both are pure.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from teleop.core.config import TELEOPERATED
from teleop.core.criteria import judge_summary
from teleop.sim.proximity import FAR_DISTANCE_M

# A progress line at least every this many seconds of sim time, and at each new phase.
PROGRESS_PERIOD_S = 5.0


@dataclass
class RunProgress:
    """Progress of one run: ``phase_names`` are the scenario's phases in order (empty:
    a run without an operator, such as path following, over ``duration_s``)."""

    duration_s: float
    phase_names: Sequence[str] = ()
    phase: int = -1  # index of the current phase; -1: none begun yet
    task_start_s: float | None = None  # sim time of the first phase
    _next_s: float = field(default=0.0, repr=False)
    _shown_phase: int = field(default=-1, repr=False)

    def on_phase(self, index: int, sim_s: float) -> None:
        """The operator began phase ``index`` at ``sim_s``."""
        if self.task_start_s is None:
            self.task_start_s = sim_s
        self.phase = index

    def line(self, sim_s: float) -> str:
        """The progress line at ``sim_s``."""
        if not self.phase_names:
            share = sim_s / self.duration_s if self.duration_s > 0 else 0.0
            return f"  sim {sim_s:6.1f} s of {self.duration_s:g} s ({share:4.0%})"
        text = f"  sim {sim_s:6.1f} s"
        if self.task_start_s is None:
            return f"{text}   task not started"
        name = self.phase_names[self.phase] if 0 <= self.phase < len(self.phase_names) else "?"
        task_s = sim_s - self.task_start_s
        return (
            f"{text}   task {task_s:5.1f} s   phase {self.phase + 1}/{len(self.phase_names)} {name}"
        )

    def due(self, sim_s: float) -> str | None:
        """The line to print now (a new phase began, or PROGRESS_PERIOD_S of sim time
        passed since the last one), else None."""
        if sim_s < self._next_s and self.phase == self._shown_phase:
            return None
        self._next_s = (sim_s // PROGRESS_PERIOD_S + 1) * PROGRESS_PERIOD_S
        self._shown_phase = self.phase
        return self.line(sim_s)


def _mm(value_m: float | None) -> float | None:
    return None if value_m is None else value_m * 1000.0


def _num(value: Any, fmt: str, unit: str = "") -> str:
    if value is None:
        return "n/a"
    return f"{value:{fmt}}{unit}"


def human_summary(summary: Mapping[str, Any], summary_path: str | None) -> list[str]:
    """About a dozen lines for a person: outcome, task time, errors, forces, timing,
    privileges refused, where the recording, logs and full summary are. A run of several
    robots: the outcome, then each robot's lines."""
    robots = summary.get("robots")
    if robots:
        outcome = "success: every robot's task done" if summary.get("success") else "FAILED"
        lines = [
            f"{summary.get('scenario')} ({summary.get('mode')}), {len(robots)} robots: {outcome}"
        ]
        shared = {k: v for k, v in summary.items() if k != "robots"}
        for robot_id, section in robots.items():  # the one recording of all: said once
            lines.append(f"robot {robot_id}:")
            lines += ["  " + line for line in _task_lines({**shared, **section, "rrd": None})]
        if summary.get("rrd"):
            lines.append(f"  recording          {summary['rrd']} (every robot)")
    else:
        lines = _task_lines(summary)
    lockstep = summary.get("mode") == "lockstep"
    verdict = summary.get("realtime_verdict", "clean")
    if "realtime_verdict" in summary:  # a services run judged itself
        # A lockstep run keeps no real time: its verdict is only about missing data.
        lines.append(f"  {'data' if lockstep else 'real time':18s} {verdict}")
    lines += [f"    - {problem}" for problem in summary.get("realtime_problems", [])]
    for fault in summary.get("faults") or []:
        lines.append(f"  fault              {fault_line(fault)}")
    refused = summary.get("refused_privileges") or []
    if refused:
        lines.append("  privileges refused (docs/running.md, Privileges):")
        lines += [f"    - {line}" for line in refused]
    viewer = (summary.get("services") or {}).get("recorder", {}).get("viewer", "")
    if viewer.startswith("not spawned"):  # --spawn asked for one
        lines.append(f"  live viewer        {viewer}: open the recording (teleop view)")
    if summary.get("run_dir"):
        lines.append(f"  logs               {summary['run_dir']}/logs")
    if summary_path:
        lines.append(f"  full summary       {summary_path}")
    return lines


def _reason_lines(summary: Mapping[str, Any]) -> list[str]:
    """Why a failed run failed, a line each (the summary's ``reasons``: its failed
    criteria, then its problems); none for a success."""
    if summary.get("success") is not False:
        return []
    reasons = summary.get("reasons")
    if reasons is None:  # a summary written before it had reasons: judge it again
        reasons = judge_summary(summary).reasons if "scenario" in summary else []
    reasons = reasons or ["no reason recorded: see the full summary"]
    return [f"  {'why' if i == 0 else '':18s} {reason}" for i, reason in enumerate(reasons)]


def _task_lines(summary: Mapping[str, Any]) -> list[str]:
    """One robot's lines: outcome, task, timing, stops, its recording."""
    lines = []
    scenario, mode = summary.get("scenario"), summary.get("mode")
    if scenario in TELEOPERATED:
        outcome = "success: the cube is in the bin" if summary.get("success") else "FAILED"
        lines.append(f"{scenario} ({mode}): {outcome}")
        lines += _reason_lines(summary)
        lines.append(
            f"  task time          {_num(summary.get('duration_s'), '.1f', ' s')}"
            f"   phases {_phases_reached(summary.get('phases'))}"
        )
        lines.append(
            f"  velocity tracking  {_num(summary.get('velocity_tracking_rms_m_s'), '.4f')} m/s RMS"
        )
        lines.append(
            f"  forces             contact max "
            f"{_num(summary.get('max_contact_force_n'), '.2f', ' N')}, device max "
            f"{_num(summary.get('max_device_force_n'), '.2f', ' N')}, held weight "
            f"{_num(summary.get('held_weight_n'), '.2f', ' N')}"
        )
        lines.append(_clearance_line(summary))
    else:
        outcome = f"{scenario} ({mode}): {summary.get('duration_s')} s simulated"
        if summary.get("success") is False:
            outcome += ", FAILED"
        lines.append(outcome)
        lines += _reason_lines(summary)
        lines.append(
            f"  path error         RMS {_num(_mm(summary.get('path_error_rms_m')), '.3f', ' mm')}, "
            f"max {_num(_mm(summary.get('path_error_max_m')), '.3f', ' mm')} "
            f"(after {summary.get('settle_s')} s)"
        )
        lines.append(f"  manipulability     min {_num(summary.get('min_manipulability'), '.3f')}")
        lines.append(
            f"  motion             path_progress {_num(summary.get('path_progress'), '.3f')}, "
            f"stalled {_num(summary.get('stalled_s'), '.1f', ' s')}"
        )
        lines.append(_clearance_line(summary))
    lockstep = mode == "lockstep"
    if lockstep:  # not paced by the wall clock: its speed is the machine's, not a verdict
        # A person's run goes at most at their clock's pace (teleop.devices.person.loop).
        person = summary.get("operator") not in (None, "scripted")
        timing = (
            f"  timing             lockstep (deterministic, "
            f"{'paced by the person' if person else 'not paced'}): "
            f"{_num(summary.get('realtime_factor'), '.2f')} x real time"
        )
    else:
        timing = (
            f"  timing             realtime factor {_num(summary.get('realtime_factor'), '.3f')}"
        )
    if "overrun_fraction" in summary:  # a services run
        if not lockstep:
            timing += (
                f", overruns {_num(summary.get('overrun_fraction'), '.2%')}, watchdog brakes "
                f"{summary.get('stale_commands')}"
            )
        timing += f", dropped {summary.get('dropped_messages')}"
    lines.append(timing)
    protective = summary.get("protective_stop") or {}
    if protective.get("approach_slowed_steps"):
        lines.append(
            f"  approach slowed    {protective['approach_slowed_steps']} steps: the gripper "
            "closing in on the scene"
        )
    for stop in protective.get("stops", []):
        released = stop["released_t_s"]
        lines.append(
            f"  PROTECTIVE STOP    at {stop['t_s']:.3f} s sim time: "
            f"{stop['cause'].replace('_', ' ')} {stop['measured']:.3g} beyond its limit, "
            + ("still held at the end" if released is None else f"released at {released:.3f} s")
        )
    if summary.get("failure"):
        lines.append(f"  ABORTED            {summary['failure']}")
    for resume in summary.get("plant_resumes") or []:
        lines.append(
            f"  plant restarted    resumed at {resume['sim_time_s']:.3f} s sim time, "
            f"{resume['steps_lost']} steps lost, {_num(resume['wall_gap_s'], '.2f', ' s')} gap"
        )
    if summary.get("rrd"):
        lines.append(f"  recording          {summary['rrd']}")
    return lines


def _clearance_line(summary: Mapping[str, Any]) -> str:
    """The arm's clearance and unintended contacts, and the virtual obstacles' clearance
    when the scene has any (a summary without one carries proximity's far distance)."""
    line = (
        f"  clearance          arm {_num(_mm(summary.get('min_clearance_m')), '.1f', ' mm')} "
        f"(min), contacts {_num(summary.get('arm_contacts'), 'd')}"
    )
    obstacle_m = summary.get("obstacle_min_clearance_m")
    if obstacle_m is not None and obstacle_m < FAR_DISTANCE_M:
        line += f", obstacle {obstacle_m * 1000.0:.1f} mm"
    return line


def fault_line(fault: Mapping[str, Any]) -> str:
    """One injected fault and what followed (teleop.run.faults), for a person."""
    what = f"{fault.get('kind')} {fault.get('service')} at {_num(fault.get('t_s'), '.2f', ' s')}"
    if fault.get("error"):
        return f"{what}: {fault['error']}"
    return (
        f"{what}: braked {_num(fault.get('brake_ms'), '.1f', ' ms')}, restarted "
        f"{_num(fault.get('restart_s'), '.2f', ' s')}, resumed "
        f"{_num(fault.get('resumed_s'), '.2f', ' s')} (from the fault)"
    )


def _phases_reached(phases: Any) -> str:
    """How many phases the operator began, and the last one's name."""
    if not isinstance(phases, list) or not phases:
        return "none begun"
    last = phases[-1].get("name", "?") if isinstance(phases[-1], Mapping) else "?"
    return f"{len(phases)} begun, the last: {last}"
