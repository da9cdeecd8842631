"""What a services run prints while it runs, and the short summary at its end.

:class:`RunProgress` turns what the launcher sees (sim time from the tool pose, the
operator's PHASE events) into a progress line: the task as it is (phase, sim time, task
time), not a fraction of a fixed duration (a grasp ends when the operator is done, long
before ``run.duration_s``). :func:`human_summary` turns the merged summary into a dozen
lines for a person; the full JSON goes to a file. Both are pure.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from teleop.core.config import TELEOPERATED
from teleop.core.criteria import judge_summary
from teleop.core.summary import FaultOutcome, PhaseTime, RunSummary
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


def human_summary(summary: Mapping[str, object], summary_path: str | None) -> list[str]:
    """About a dozen lines for a person from ``summary``, the JSON a run writes: outcome,
    task time, errors, forces, timing, privileges refused, where the recording, logs and
    full summary are. A run of several robots: the outcome, then each robot's lines."""
    run = RunSummary.from_json(summary)
    if run.robots:
        outcome = "success: every robot's task done" if run.success else "FAILED"
        lines = [f"{run.scenario} ({run.mode}), {len(run.robots)} robots: {outcome}"]
        for robot_id in run.robots:  # the one recording of all: said once
            lines.append(f"robot {robot_id}:")
            lines += ["  " + line for line in _task_lines(replace(run.section(robot_id), rrd=None))]
        if run.rrd:
            lines.append(f"  recording          {run.rrd} (every robot)")
    else:
        lines = _task_lines(run)
    if "realtime_verdict" in run.written:  # a services run judged itself
        # A lockstep run keeps no real time: its verdict is only about missing data.
        label = "data" if run.mode == "lockstep" else "real time"
        lines.append(f"  {label:18s} {run.realtime_verdict}")
    lines += [f"    - {problem}" for problem in run.realtime_problems or ()]
    for fault in run.faults or ():
        lines.append(f"  fault              {fault_line(fault)}")
    if run.refused_privileges:
        lines.append("  privileges refused (docs/running.md, Privileges):")
        lines += [f"    - {line}" for line in run.refused_privileges]
    recorder = (run.services or {}).get("recorder") or {}
    viewer = str(recorder.get("viewer", ""))
    if viewer.startswith("not spawned"):  # --spawn asked for one
        lines.append(f"  live viewer        {viewer}: open the recording (teleop view)")
    if run.run_dir:
        lines.append(f"  logs               {run.run_dir}/logs")
    if summary_path:
        lines.append(f"  full summary       {summary_path}")
    return lines


def _reason_lines(summary: RunSummary) -> list[str]:
    """Why a failed run failed, a line each (the summary's ``reasons``: its failed
    criteria, then its problems); none for a success."""
    if summary.success is not False:
        return []
    reasons: Sequence[str] | None = summary.reasons
    if reasons is None:  # a summary written before it had reasons: judge it again
        reasons = judge_summary(summary).reasons if summary.scenario is not None else []
    reasons = reasons or ["no reason recorded: see the full summary"]
    return [f"  {'why' if i == 0 else '':18s} {reason}" for i, reason in enumerate(reasons)]


def _task_lines(summary: RunSummary) -> list[str]:
    """One robot's lines: outcome, task, timing, stops, its recording."""
    if summary.scenario in TELEOPERATED:
        lines = _grasp_lines(summary)
    else:
        lines = _path_lines(summary)
    lines.append(_timing_line(summary))
    lines += _stop_lines(summary)
    if summary.rrd:
        lines.append(f"  recording          {summary.rrd}")
    return lines


def _grasp_lines(summary: RunSummary) -> list[str]:
    """A teleoperated task's outcome, its reasons, task time, tracking, forces, clearance."""
    outcome = "success: the cube is in the bin" if summary.success else "FAILED"
    return [
        f"{summary.scenario} ({summary.mode}): {outcome}",
        *_reason_lines(summary),
        f"  task time          {_num(summary.duration_s, '.1f', ' s')}"
        f"   phases {_phases_reached(summary.phases)}",
        f"  velocity tracking  {_num(summary.velocity_tracking_rms_m_s, '.4f')} m/s RMS",
        f"  forces             contact max "
        f"{_num(summary.max_contact_force_n, '.2f', ' N')}, device max "
        f"{_num(summary.max_device_force_n, '.2f', ' N')}, held weight "
        f"{_num(summary.held_weight_n, '.2f', ' N')}",
        _clearance_line(summary),
    ]


def _path_lines(summary: RunSummary) -> list[str]:
    """Path following's outcome, its reasons, path error, manipulability, motion, clearance."""
    outcome = f"{summary.scenario} ({summary.mode}): {summary.duration_s} s simulated"
    if summary.success is False:
        outcome += ", FAILED"
    return [
        outcome,
        *_reason_lines(summary),
        f"  path error         RMS {_num(_mm(summary.path_error_rms_m), '.3f', ' mm')}, "
        f"max {_num(_mm(summary.path_error_max_m), '.3f', ' mm')} "
        f"(after {summary.settle_s} s)",
        f"  manipulability     min {_num(summary.min_manipulability, '.3f')}",
        f"  motion             path_progress {_num(summary.path_progress, '.3f')}, "
        f"stalled {_num(summary.stalled_s, '.1f', ' s')}",
        _clearance_line(summary),
    ]


def _timing_line(summary: RunSummary) -> str:
    """How the run kept time: lockstep's speed (the machine's, not a verdict) or the
    realtime factor, with a services run's overruns, brakes and drops."""
    lockstep = summary.mode == "lockstep"
    if lockstep:
        # A person's run goes at most at their clock's pace (teleop.devices.person.loop).
        person = summary.operator not in (None, "scripted")
        timing = (
            f"  timing             lockstep (deterministic, "
            f"{'paced by the person' if person else 'not paced'}): "
            f"{_num(summary.realtime_factor, '.2f')} x real time"
        )
    else:
        timing = f"  timing             realtime factor {_num(summary.realtime_factor, '.3f')}"
    if "overrun_fraction" in summary.written:  # a services run
        if not lockstep:
            timing += (
                f", overruns {_num(summary.overrun_fraction, '.2%')}, watchdog brakes "
                f"{summary.stale_commands}"
            )
        timing += f", dropped {summary.dropped_messages}"
    return timing


def _stop_lines(summary: RunSummary) -> list[str]:
    """The plant's approach slowing, protective stops, abort and restarts, a line each."""
    lines = []
    protective = summary.protective_stop or {}
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
    if summary.failure:
        lines.append(f"  ABORTED            {summary.failure}")
    for resume in summary.plant_resumes or ():
        lines.append(
            f"  plant restarted    resumed at {resume['sim_time_s']:.3f} s sim time, "
            f"{resume['steps_lost']} steps lost, {_num(resume['wall_gap_s'], '.2f', ' s')} gap"
        )
    return lines


def _clearance_line(summary: RunSummary) -> str:
    """The arm's clearance and unintended contacts, and the virtual obstacles' clearance
    when the scene has any (a summary without one carries proximity's far distance)."""
    line = (
        f"  clearance          arm {_num(_mm(summary.min_clearance_m), '.1f', ' mm')} "
        f"(min), contacts {_num(summary.arm_contacts, 'd')}"
    )
    obstacle_m = summary.obstacle_min_clearance_m
    if obstacle_m is not None and obstacle_m < FAR_DISTANCE_M:
        line += f", obstacle {obstacle_m * 1000.0:.1f} mm"
    return line


def fault_line(fault: FaultOutcome) -> str:
    """One injected fault and what followed (teleop.run.faults), for a person."""
    what = f"{fault.kind} {fault.service} at {_num(fault.t_s, '.2f', ' s')}"
    if fault.error:
        return f"{what}: {fault.error}"
    return (
        f"{what}: braked {_num(fault.brake_ms, '.1f', ' ms')}, restarted "
        f"{_num(fault.restart_s, '.2f', ' s')}, resumed "
        f"{_num(fault.resumed_s, '.2f', ' s')} (from the fault)"
    )


def _phases_reached(phases: Sequence[PhaseTime] | None) -> str:
    """How many phases the operator began, and the last one's name."""
    if not phases:
        return "none begun"
    return f"{len(phases)} begun, the last: {phases[-1].name}"
