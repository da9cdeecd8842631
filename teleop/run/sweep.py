"""``teleop sweep``: many random reachable tasks, run on every core, judged and tabled.

A sweep draws its tasks with :mod:`teleop.run.tasks` (seeded: the same seed gives the
same tasks), runs each in a worker process (``workers``, one per core by default) and
judges it by the run's own criteria (:mod:`teleop.core.criteria`): path following in
process, as ``teleop run path-following --inprocess``; grasp as a lockstep services run,
as ``teleop run grasp --mode lockstep``.

A criterion whose figure the run does not report is *unavailable*, never passed: a task
succeeds only when every criterion was measured and met. Every failure carries its
reasons (the failed criteria, the operator's failure reason, the run's events, or the
error that stopped the run). A line per finished task goes to stderr while it runs; the
report is a JSON file (every task's figures, its command line, the success rate, the
failures by reason, the clearance distribution) and a markdown table.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import sys
import time
import traceback
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from teleop.core import markdown
from teleop.core.config import SCENARIOS, Config, load_config, scenario_spec
from teleop.core.criteria import FAIL, UNAVAILABLE, event_reasons, judge_summary
from teleop.core.rundir import RECORDING_FILE, RUN_SUMMARY_FILE
from teleop.core.summary import Criterion, RunSummary, write_run_summary
from teleop.run.tasks import (
    Generated,
    GraspTask,
    PathTask,
    random_grasp_tasks,
    random_path_tasks,
)

Task = PathTask | GraspTask

KINDS = SCENARIOS  # a sweep runs tasks of one scenario
# Report files in the output directory.
REPORT_JSON = "sweep.json"
REPORT_MARKDOWN = "sweep.md"
# A grasp run whose services did not all come up is started again this many times.
STARTUP_RETRIES = 2
# Percentiles of the clearance distribution in the report.
CLEARANCE_PERCENTILES = (0, 5, 25, 50, 75, 100)

# --- Running one task (in a worker) ---------------------------------------------------------


@dataclass(frozen=True)
class Job:
    """What a worker needs to run one task: picklable, no models."""

    kind: str
    task: Task
    config_file: str | None
    overrides: tuple[str, ...]  # the sweep's own --set values, before the task's
    run_dir: str
    keep_recordings: bool = False  # grasp: keep each run's Rerun recording


@dataclass(frozen=True)
class TaskRecord:
    """One task judged: a line of the sweep's report (its ``results``). ``figures``: the
    run's figures the report keeps (None: the run did not end, ``error`` says why);
    ``startup_retries``: the times its stack did not come up (:func:`_run_started`)."""

    index: int
    params: Mapping[str, object]
    seed: int
    command: str
    success: bool
    criteria: tuple[Criterion, ...]
    reasons: tuple[str, ...]
    wall_s: float
    figures: Mapping[str, object] | None = None
    error: str | None = None
    startup_retries: int = 0

    def to_json(self) -> dict[str, object]:
        record: dict[str, object] = {
            "index": self.index,
            "params": dict(self.params),
            "seed": self.seed,
            "command": self.command,
        }
        if self.startup_retries:
            record["startup_retries"] = self.startup_retries
        record.update(
            success=self.success,
            criteria=[c.to_json() for c in self.criteria],
            reasons=list(self.reasons),
        )
        if self.error is not None:
            record["error"] = self.error
        if self.figures is not None:
            record["figures"] = dict(self.figures)
        record["wall_s"] = self.wall_s
        return record


def run_job(job: Job) -> TaskRecord:
    """Run one task and judge it; never raises (an error is the task's failure reason)."""
    start = time.perf_counter()
    task = job.task
    params, command = task.params(), task.command(job.overrides, job.config_file)
    retries: list[int] = []
    try:
        summary = _run_started(job, retries)
    except Exception as exc:  # the task failed to run: that is its result
        return TaskRecord(
            task.index, params, task.seed, command, success=False, criteria=(),
            reasons=(f"error: {type(exc).__name__}: {exc}",),
            wall_s=time.perf_counter() - start, error=traceback.format_exc(limit=5),
            startup_retries=len(retries),
        )  # fmt: skip
    success, criteria, reasons = judge_record(RunSummary.from_json(summary))
    return TaskRecord(
        task.index, params, task.seed, command, success, criteria, reasons,
        wall_s=time.perf_counter() - start,
        figures={key: summary[key] for key in kind_of(job.kind).figures if key in summary},
        startup_retries=len(retries),
    )  # fmt: skip


def judge_record(summary: RunSummary) -> tuple[bool, tuple[Criterion, ...], tuple[str, ...]]:
    """A task's success, criteria and reasons from its run's summary: the run's own
    verdict (criteria.judge_summary), and every criterion measured besides. The reasons
    say why a task failed: the failed criteria, then what the run said went wrong (the
    operator's reason, its events, else its problems)."""
    verdict = judge_summary(summary)
    success = verdict.success and verdict.complete
    reasons: list[str] = []
    if not success:
        told = event_reasons(summary) or list(verdict.problems)
        reasons = [*verdict.failed, *told]
        if not reasons:
            reasons = [f"unmeasured: {', '.join(verdict.unmeasured)}"]
    return success, verdict.criteria, tuple(reasons)


def _run_started(job: Job, retries: list[int]) -> dict[str, object]:
    """:func:`_run`, again (at most STARTUP_RETRIES times) when its stack did not come
    up: a program not RUNNING, or a service not ready, within the launcher's time-outs
    (a machine loaded by other work) means the task never ran, which is no outcome of
    the task. Each retry is appended to ``retries`` (the record's ``startup_retries``)."""
    from teleop.run.failure import ServiceFailed
    from teleop.run.supervise import StartTimeout

    while True:
        try:
            return _run(job)
        except (ServiceFailed, StartTimeout) as exc:
            startup = isinstance(exc, StartTimeout) or exc.startup
            if not startup or len(retries) == STARTUP_RETRIES:
                raise
            retries.append(len(retries) + 1)


def _run(job: Job) -> dict[str, object]:
    return kind_of(job.kind).run(job, [*job.overrides, *job.task.overrides()])


def _run_in_process(job: Job, overrides: list[str]) -> dict[str, object]:
    """An autonomous task, as ``teleop run <scenario> --inprocess``."""
    from teleop.run.experiments import run_path_following_inprocess

    config = load_config(job.config_file, [*overrides, f'run.scenario="{job.kind}"'])
    return run_path_following_inprocess(config, progress=None)


def _run_on_services(job: Job, overrides: list[str]) -> dict[str, object]:
    """A teleoperated task, as ``teleop run <scenario> --mode lockstep``."""
    from teleop.run.stack import run_on_services

    overrides = [*overrides, f'run.scenario="{job.kind}"', 'run.mode="lockstep"']
    config = load_config(job.config_file, overrides)
    run_dir = Path(job.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    summary = run_on_services(config, job.config_file, overrides, run_dir, None)
    write_run_summary(run_dir / RUN_SUMMARY_FILE, summary)
    if not job.keep_recordings:  # tens of MB each; the summary and the logs stay
        Path(str(summary.get("rrd") or run_dir / RECORDING_FILE)).unlink(missing_ok=True)
    return summary


def _mm(value: Any) -> str:
    return "-" if value is None else f"{float(value) * 1e3:.3f}"


def _num(value: Any, fmt: str) -> str:
    return "-" if value is None else format(float(value), fmt)


def _yes(value: bool) -> str:
    return "yes" if value else "no"


def _path_row(p: Mapping[str, Any], f: Mapping[str, Any]) -> tuple[object, ...]:
    return (p["center_m"], p["radius_m"], p["path_speed_m_s"], _mm(f.get("path_error_rms_m")),
            _mm(f.get("path_error_max_m")), _num(f.get("path_progress"), ".3f"),
            _mm(f.get("min_clearance_m")), f.get("arm_contacts", "-"))  # fmt: skip


def _scene_row(p: Mapping[str, Any], f: Mapping[str, Any]) -> tuple[object, ...]:
    return (p["cube_p_m"][:2], p["bin_p_m"][:2],
            f"{p['obstacle_p_m']} r {p['obstacle_radius_m']}", _yes(p["obstacle_in_the_way"]),
            _num(f.get("duration_s"), ".1f"), _num(f.get("max_device_force_n"), ".2f"),
            _mm(f.get("min_clearance_m")), f.get("arm_contacts", "-"))  # fmt: skip


@dataclass(frozen=True)
class SweepKind:
    """How a sweep draws, runs and tables the tasks of a scenario: random paths for an
    autonomous one (run in process), random scenes for a teleoperated one (run on the
    services, lockstep). Chosen once from the scenario's ``teleoperated``."""

    tasks: str  # what a task is, plural: the name of the count option (``--paths``)
    generate: Callable[[Config, int, int], Generated]
    run: Callable[[Job, list[str]], dict[str, object]]
    figures: tuple[str, ...]  # the run's figures kept per task in the report
    columns: tuple[str, ...]  # the report's table, between the task and the verdict
    row: Callable[[Mapping[str, Any], Mapping[str, Any]], tuple[object, ...]]


PATHS = SweepKind(
    "paths",
    random_path_tasks,
    _run_in_process,
    ("path_error_rms_m", "path_error_max_m", "path_progress", "stalled_s", "min_clearance_m",
     "arm_contacts", "min_manipulability", "commands_clamped", "realtime_factor",
     "final_state_sha256"),
    ("centre (m)", "radius (m)", "speed (m/s)", "RMS (mm)", "max (mm)", "progress",
     "clearance (mm)", "contacts"),
    _path_row,
)  # fmt: skip
SCENES = SweepKind(
    "scenes",
    random_grasp_tasks,
    _run_on_services,
    ("success", "object_in_box", "duration_s", "max_device_force_n", "max_contact_force_n",
     "min_clearance_m", "arm_contacts", "obstacle_min_clearance_m", "max_obstacle_force_n",
     "phases", "final_state_sha256"),
    ("cube (m)", "bin (m)", "obstacle (m)", "in the way", "time (s)", "device (N)",
     "clearance (mm)", "contacts"),
    _scene_row,
)  # fmt: skip
SWEEP_KINDS = (PATHS, SCENES)


def kind_of(scenario: str) -> SweepKind:
    """The sweep of ``scenario`` (ValueError naming the scenarios for another name)."""
    if scenario not in KINDS:
        raise ValueError(f"sweep kind {scenario!r}: one of {', '.join(KINDS)}")
    return SCENES if scenario_spec(scenario).teleoperated else PATHS


# --- The sweep ------------------------------------------------------------------------------


def default_workers() -> int:
    """One worker per core this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def generate(kind: str, count: int, seed: int, config_file: str | None,
             overrides: Sequence[str]) -> Generated:  # fmt: skip
    """The sweep's tasks (see :mod:`teleop.run.tasks`)."""
    return kind_of(kind).generate(load_config(config_file, list(overrides)), count, seed)


ProgressFn = Callable[[str], None]


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def progress_line(done: int, total: int, record: TaskRecord, elapsed_s: float) -> str:
    """One line per finished task: count, outcome, first reason, time left."""
    eta_s = elapsed_s / done * (total - done)
    outcome = "ok" if record.success else "FAILED: " + "; ".join(record.reasons[:2])
    width = len(str(total))
    return (
        f"[{done:{width}d}/{total}] task {record.index:{width}d} {outcome}"
        f"   ({elapsed_s:.0f} s, about {eta_s:.0f} s left)"
    )


def run_sweep(
    kind: str,
    count: int,
    seed: int,
    out_dir: Path,
    *,
    config_file: str | None = None,
    overrides: Sequence[str] = (),
    workers: int | None = None,
    keep_recordings: bool = False,
    progress: ProgressFn | None = _stderr,
) -> dict[str, Any]:
    """Generate ``count`` tasks of ``kind`` from ``seed``, run them on ``workers``
    processes, write ``sweep.json`` and ``sweep.md`` into ``out_dir``; returns the report."""
    kind_of(kind)  # an unknown kind fails before any work
    workers = workers or default_workers()
    generated = generate(kind, count, seed, config_file, overrides)
    out_dir.mkdir(parents=True, exist_ok=True)
    jobs = [
        Job(
            kind,
            task,
            config_file,
            tuple(overrides),
            str(out_dir / f"task{task.index:03d}"),
            keep_recordings,
        )  # fmt: skip
        for task in generated.tasks
    ]
    if progress is not None:
        progress(f"sweep {kind}: {len(jobs)} reachable tasks of {generated.candidates} drawn "
                 f"(seed {seed}), {workers} worker(s); reports in {out_dir}")  # fmt: skip
        for job in jobs:
            progress(f"  task {job.task.index}: {job.task.command(job.overrides, config_file)}")
    start = time.perf_counter()
    records: list[TaskRecord] = []
    interrupted = False
    # spawn: each worker builds its own models; nothing of this process's state leaks in.
    with multiprocessing.get_context("spawn").Pool(workers) as pool:
        try:
            for record in pool.imap_unordered(run_job, jobs):
                records.append(record)
                if progress is not None:
                    elapsed = time.perf_counter() - start
                    progress(progress_line(len(records), len(jobs), record, elapsed))
        except KeyboardInterrupt:  # Ctrl-C: report the tasks finished so far, then stop
            interrupted = True
            pool.terminate()
    records.sort(key=lambda r: r.index)
    report = make_report(kind, seed, workers, generated, records, time.perf_counter() - start)
    report["overrides"] = list(overrides)
    report["interrupted"] = interrupted
    report["tasks_drawn"] = len(jobs)
    (out_dir / REPORT_JSON).write_text(json.dumps(report, indent=2) + "\n")
    (out_dir / REPORT_MARKDOWN).write_text(report_markdown(report))
    if interrupted:
        raise KeyboardInterrupt
    return report


def _distribution(values: Sequence[float]) -> dict[str, float] | None:
    if not values:
        return None
    return {f"p{p}": float(np.percentile(values, p)) for p in CLEARANCE_PERCENTILES}


def reason_kind(reason: str) -> str:
    """A failure reason without its numbers, for counting: ``path error RMS``,
    ``event STALL``, ``operator: timeout in carry``, ``operator: the target out of reach
    in descend``."""
    if reason.startswith("event "):
        return " ".join(reason.split()[:2])
    if reason.startswith(("operator: ", "plant: ")):
        return reason.split(" (")[0]
    return reason.split(":")[0]


def make_report(kind: str, seed: int, workers: int, generated: Generated,
                records: Sequence[TaskRecord], wall_s: float) -> dict[str, Any]:  # fmt: skip
    """The report (JSON): per-task records plus the success rate, failures by reason, the
    distribution of the minimum clearance and what the generator rejected."""
    successes = sum(r.success for r in records)
    by_reason: Counter[str] = Counter()
    for r in records:
        for reason in r.reasons:
            by_reason[reason_kind(reason)] += 1
    clearances = [
        float(clearance)
        for r in records
        if (clearance := (r.figures or {}).get("min_clearance_m")) is not None
    ]
    unavailable = sorted({c.name for r in records for c in r.criteria if c.status == UNAVAILABLE})
    return {
        "kind": kind,
        "seed": seed,
        "tasks": len(records),
        "workers": workers,
        "successes": successes,
        "success_rate": successes / len(records) if records else None,
        # Tasks that failed no measured criterion and reported no failure event.
        "passed_measured": sum(
            1
            for r in records
            if r.criteria
            and not any(c.status == FAIL for c in r.criteria)
            and not any(not reason.startswith("unmeasured") for reason in r.reasons)
        ),
        "criteria_unavailable": unavailable,
        "failures_by_reason": dict(by_reason.most_common()),
        "silent_failures": sum(1 for r in records if not r.success and not r.reasons),
        "min_clearance_m": _distribution(clearances),
        "generator": {
            "candidates": generated.candidates,
            "rejected": dict(generated.rejected.most_common()),
        },
        "wall_s": wall_s,
        "results": [r.to_json() for r in records],
    }


def _percentiles_mm(distribution: Mapping[str, float] | None) -> str:
    if not distribution:
        return "not reported"
    return ", ".join(f"{k} {v * 1e3:.1f}" for k, v in distribution.items())


def report_markdown(report: Mapping[str, Any]) -> str:
    """The report as a markdown page: the totals, then one row per task."""
    rate = report["success_rate"]
    lines = [
        f"# Sweep: {report['kind']}, {report['tasks']} tasks, seed {report['seed']}",
        "",
        *(
            [f"Interrupted: {report['tasks']} of {report['tasks_drawn']} tasks finished.", ""]
            if report.get("interrupted")
            else []
        ),
        f"- success: {report['successes']} / {report['tasks']}"
        + (f" ({rate:.0%})" if rate is not None else ""),
        f"- failures by reason: {report['failures_by_reason'] or 'none'}",
        f"- criteria not measured by this build: {report['criteria_unavailable'] or 'none'}"
        + (
            f" (tasks passing every measured one: {report['passed_measured']})"
            if report["criteria_unavailable"]
            else ""
        ),
        f"- min clearance (mm), percentiles: {_percentiles_mm(report['min_clearance_m'])}",
        f"- generator: {report['generator']['candidates']} candidates drawn, rejected "
        f"{report['generator']['rejected'] or 'none'}",
        f"- wall time {report['wall_s']:.0f} s on {report['workers']} worker(s)",
        "",
    ]
    kind = kind_of(report["kind"])
    rows = [
        (r["index"], *kind.row(r["params"], r.get("figures", {})), _yes(r["success"]),
         "; ".join(r["reasons"]))
        for r in report["results"]
    ]  # fmt: skip
    header = ("task", *kind.columns, "ok", "reasons")
    lines += markdown.table(header, rows)
    lines += ["", "Run one task again by hand:", ""]
    lines += [f"    {r['command']}" for r in report["results"]]
    return "\n".join(lines) + "\n"
