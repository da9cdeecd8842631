"""A services run's summary, assembled from what each service wrote on close and what
the launcher heard (:class:`teleop.run.run_watch.RunWatch`): each robot's task figures and
verdict (:func:`robot_section`; several robots: a section each under ``robots``), the
run's real-time health, the drops by receiver, the machine, the faults and every
service's own summary under ``services``. Reads files only: no bus, no processes."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

from teleop.bus import graph
from teleop.bus.graph import EYEVIEW, PLANT
from teleop.bus.service import read_summary
from teleop.core.config import Config
from teleop.core.criteria import TaskFigures, judge_task
from teleop.core.rundir import LOG_DIR, idle_poll_status_path, summary_path
from teleop.core.service_summaries import (
    ControllerSummary,
    Drops,
    EyeViewSummary,
    HapticSummary,
    OperatorSummary,
    PlantSummary,
    RecorderSummary,
    ServiceSummary,
    record_of,
)
from teleop.core.summary import CONTROLLER, GRASP, PATH, RunSummary, copied_fields, json_value
from teleop.run.failure import RunError
from teleop.run.fault_run import FaultRun
from teleop.run.idle_poll import POLLING, IdlePoll, read_status
from teleop.run.run_watch import RunWatch
from teleop.run.verdict import (
    Health,
    drop_lines,
    machine_section,
    realtime_health,
    refused_privileges,
)

R = TypeVar("R", bound=ServiceSummary)
T = TypeVar("T")


def service_summaries(
    run_dir: Path, services: Sequence[str], killed: frozenset[str]
) -> dict[str, dict[str, object]]:
    """Each service's summary JSON by name, as it wrote it (RunError for one that wrote
    none). A service killed on purpose (``killed``) whose new incarnation was stopped
    while still starting has only its killed process's running summary, or none if that
    one was killed before its first (teleop.bus.service): the run's figures then go
    without it."""
    summaries = {}
    for name in services:
        summary = read_summary(run_dir, name)
        if summary is None and name in killed:
            continue
        if summary is None:
            path = summary_path(run_dir, name)
            raise RunError(f"{name} wrote no summary ({path}); see {run_dir / LOG_DIR}")
        summaries[name] = summary
    return summaries


def service_records(summaries: Mapping[str, Mapping[str, object]]) -> dict[str, ServiceSummary]:
    """The services' summaries by name as the records of their roles."""
    return {name: record_of(graph.role_of(name), s) for name, s in summaries.items()}


def dropped_by_receiver(launcher: Drops, records: Mapping[str, ServiceSummary]) -> dict[str, Drops]:
    """The bad records each receiver dropped (restarted services: their earlier
    processes' too), by kind and reason, and the first detail of each."""
    dropped_by = {"launcher": launcher}
    for name, record in records.items():
        counts: dict[str, int] = {}
        first: dict[str, str] = {}
        for incarnation in record.incarnations:
            drops = incarnation.drops
            for key, count in drops.counts.items():
                counts[key] = counts.get(key, 0) + count
            for key, detail in drops.first.items():
                first.setdefault(key, detail)
        dropped_by[name] = Drops(counts, first)
    return dropped_by


def idle_poll_report(cpus: Sequence[int], run_dir: Path) -> IdlePoll:
    """After a run: the CPUs whose poller polled, and why the others did not."""
    statuses = {cpu: read_status(idle_poll_status_path(run_dir, cpu)) for cpu in cpus}
    return IdlePoll(
        cpus=tuple(cpu for cpu, status in statuses.items() if status == POLLING),
        failed={cpu: s for cpu, s in statuses.items() if s != POLLING},
    )


def run_summary(
    config: Config,
    run_dir: Path,
    started: Sequence[str],
    outside: Sequence[str],
    watch: RunWatch,
    faults: FaultRun | None,
    polled_cpus: Sequence[int],
    wall_s: float,
) -> dict[str, object]:
    """The run's summary JSON (docs/running.md, the summary's fields; its record:
    teleop.core.summary.RunSummary); ``polled_cpus``: the CPUs the run asked idle pollers
    for."""
    specs = faults.specs if faults is not None else ()
    killed = frozenset(spec.service for spec in specs if spec.kind == "kill")
    summaries = service_summaries(run_dir, started, killed)
    records = service_records(summaries)
    robot_ids = watch.robot_ids
    plants = graph.instances([PLANT], robot_ids)
    # A pair of peers that never linked: what one sent the other is lost (Service.become_ready).
    unlinked = {n: list(r.unlinked_peers) for n, r in records.items() if r.unlinked_peers}
    dropped_by = dropped_by_receiver(watch.drops.by_key(), records)
    summary: dict[str, object] = {
        "scenario": config.run.scenario,
        "mode": config.run.mode,
        "seed": config.run.seed,
    }
    if config.run.teleoperated:
        summary["operator"] = config.run.operator
    sections = {
        rid: robot_section(config, robot_view(summaries, rid, robot_ids), watch.task_done[rid])
        for rid in robot_ids
    }
    # One robot: its section is the run's.
    verdict = (
        sections[robot_ids[0]]
        if len(robot_ids) == 1
        else robots_verdict(config.run.scenario, sections)
    )
    summary.update(verdict)
    idle_poll = idle_poll_report(polled_cpus, run_dir)
    machine = machine_section(records, polled_cpus, idle_poll)
    plant_records = [_plant(records.get(name)) for name in plants]
    health = run_health(config.run.mode, plant_records, dropped_by, unlinked, faults)
    success = verdict["success"] is True
    summary.update(
        {
            **health.to_json(),
            "outside": list(outside),
            "summaries_missing": [name for name in started if name not in summaries],
            # Services whose earlier processes wrote a summary (restarted after it).
            "restarted_services": {
                name: len(r.earlier_incarnations)
                for name, r in records.items()
                if r.earlier_incarnations
            },
            "dropped_messages": sum(sum(d.counts.values()) for d in dropped_by.values()),
            "unlinked_peers": unlinked,
            "stack_wall_s": wall_s,
            **idle_poll.to_json(),
            "machine": machine.to_json(),
            "refused_privileges": refused_privileges(machine),
            "faults": [o.to_json() for o in faults.report(success)] if faults else [],
            "run_dir": str(run_dir),
            "services": summaries,
        }
    )
    return summary


def run_health(
    mode: str,
    plants: Sequence[PlantSummary],
    dropped_by: Mapping[str, Drops],
    unlinked: Mapping[str, Sequence[str]],
    faults: FaultRun | None = None,
) -> Health:
    """The run's real-time verdict (teleop.run.verdict.realtime_health) from its plants'
    summaries, the bad records its receivers dropped (:func:`dropped_by_receiver`) and the
    services that never linked; the brakes an injected fault caused are the fault's, not a
    loss of real time."""
    fault_braked = faults.braked_states() if faults is not None else 0
    return realtime_health(
        mode,
        overrun_fraction=max(_or(p.overrun_fraction, 0.0) for p in plants),
        realtime_factor=min(p.realtime_factor or 0.0 for p in plants),
        watchdog_brakes=sum(_or(p.stale_commands, 0) for p in plants)
        - (faults.brakes() if faults else 0),
        braked_steps=max(0, sum(_or(p.stale_steps, 0) for p in plants) - fault_braked),
        steps=sum(_or(p.steps, 0) for p in plants),
        drops=drop_lines(dropped_by),
        unlinked_peers=dict(unlinked),
    )


@dataclass(frozen=True)
class RobotView:
    """The services' summaries as one robot's run saw them (:func:`robot_view`): its own
    plant, controller and eye view, and the station's services (their figures for this
    robot). None: the run has no summary of it (left outside, or killed before its
    first)."""

    plant: PlantSummary | None = None
    controller: ControllerSummary | None = None
    haptic: HapticSummary | None = None
    operator: OperatorSummary | None = None
    recorder: RecorderSummary | None = None
    eyeview: EyeViewSummary | None = None
    by_role: Mapping[str, ServiceSummary] = field(default_factory=dict)  # every one of them


def robot_view(
    summaries: Mapping[str, Mapping[str, object]], robot_id: str, robot_ids: Sequence[str]
) -> RobotView:
    """The services' summaries as one robot's run saw them: its own plant, controller and
    eye view (``<service>-<robot_id>`` in a run of several robots), and the station's
    services, whose per-robot figures (a section per robot under ``robots``: the
    operator's task, the recorder's file) are this robot's."""
    by_role: dict[str, ServiceSummary] = {}
    for name, summary in summaries.items():
        role, robot = graph.role_of(name), graph.robot_of(name)
        if robot is not None and robot != robot_id:
            continue
        sections = summary.get("robots") if len(robot_ids) > 1 else None
        own = sections.get(robot_id) if isinstance(sections, Mapping) else None
        by_role[role] = record_of(role, {**summary, **own} if isinstance(own, Mapping) else summary)
    return RobotView(
        plant=_role(by_role, "plant", PlantSummary),
        controller=_role(by_role, "controller", ControllerSummary),
        haptic=_role(by_role, "haptic", HapticSummary),
        operator=_role(by_role, "operator", OperatorSummary),
        recorder=_role(by_role, "recorder", RecorderSummary),
        eyeview=_role(by_role, EYEVIEW, EyeViewSummary),
        by_role=by_role,
    )


def _role(by_role: Mapping[str, ServiceSummary], role: str, record: type[R]) -> R | None:
    found = by_role.get(role)
    return found if isinstance(found, record) else None


def _plant(record: ServiceSummary | None) -> PlantSummary:
    """A plant's record; an empty one for a plant without a summary (killed)."""
    return record if isinstance(record, PlantSummary) else PlantSummary()


def _or(value: T | None, default: T) -> T:
    return default if value is None else value


def robot_section(config: Config, view: RobotView, task_done: list[float]) -> dict[str, object]:
    """One robot's figures, verdict and plant figures (JSON), from its services' summaries
    (:func:`robot_view`) and the operator's TASK_DONE values for it."""
    plant, controller = view.plant or PlantSummary(), view.controller or ControllerSummary()
    figures: dict[str, object]
    if config.run.teleoperated:
        figures, problems = grasp_figures(view, task_done)
    else:
        figures = {
            "duration_s": config.run.duration_s,
            **{
                key: json_value(getattr(controller, key)) for key in copied_fields(CONTROLLER, PATH)
            },
        }
        # A run that stalls or collides is not a good run either (teleop.control.path).
        problems = list(_or(controller.motion_problems, ()))
        figures["motion_problems"] = problems
    if plant.aborted or plant.failure:
        # The plant ended the run on a failure: whatever the task's figures say, it did
        # not go on to its end.
        problems = [*problems, f"plant: {plant.failure or 'aborted'}"]
    figures["commands_received"] = plant.commands_received
    figures["commands_applied"] = plant.commands_applied
    # The task's criteria (teleop.core.criteria) and the problems: the one verdict, which
    # the summary holds enough to give again (criteria.judge_summary).
    verdict = judge_task(config.run.scenario, TaskFigures.from_json(figures), problems).to_json()
    sim_s = (plant.steps or 0) * config.tick_s
    return {
        **figures,
        **verdict,
        "steps": plant.steps,
        "wall_s": plant.wall_s,
        "realtime_factor": plant.realtime_factor,
        "overrun_fraction": plant.overrun_fraction,
        "commands_clamped": plant.commands_clamped,
        "commands_clamped_by_reason": plant.commands_clamped_by_reason,
        "command_stream": plant.command_stream,
        "stale_commands": plant.stale_commands,
        # The plant's own stops on contact force and tool speed (teleop.sim.protective).
        "protective_stop": plant.protective_stop,
        # The plant ended the run on a failure (its reason), and its restarts.
        "failure": plant.failure,
        "plant_resumes": list(_or(plant.resumes, ())),
        "skipped_states": controller.skipped_states,
        "final_state_sha256": plant.final_state_sha256,
        # CPU seconds per simulated second of this robot's own processes (start-up in).
        "cpu_s_per_sim_s": {
            role: round(cpu_s / sim_s, 4)
            for role in graph.PER_ROBOT
            if role in view.by_role
            and sim_s > 0
            and (cpu_s := view.by_role[role].cpu_s) is not None
        },
        "eye_view": eye_view_summary(view),
        "rrd": view.recorder.rrd_path if view.recorder is not None else None,
    }


def robots_verdict(scenario: str, sections: Mapping[str, dict[str, object]]) -> dict[str, object]:
    """A run of several robots: a section per robot (each judged by itself, its
    ``scenario`` with it so criteria.judge_summary judges it again the same way) and the
    run's verdict: every robot's task succeeded; its problems, each with its robot."""
    robots = {rid: {"scenario": scenario, **s} for rid, s in sections.items()}
    records = {rid: RunSummary.from_json(s) for rid, s in robots.items()}
    return {
        "robots": robots,
        "success": all(r.success for r in records.values()),
        "problems": [f"{rid}: {p}" for rid, r in records.items() for p in r.problems or ()],
        "reasons": [f"{rid}: {p}" for rid, r in records.items() for p in r.reasons or ()],
        "failure": next((r.failure for r in records.values() if r.failure), None),
        "rrd": next((r.rrd for r in records.values() if r.rrd), None),
    }


def eye_view_summary(view: RobotView) -> dict[str, object] | None:
    """Frames rendered and received (over SHM), render time, CPU shares, latency."""
    eyeview = view.eyeview
    if eyeview is None:
        return None
    recorder = view.recorder or RecorderSummary()
    received = recorder.eye_view_received
    return {
        "frames_published": eyeview.frames_published,
        "frames_received": received.received,
        "frames_received_shm": received.received_shm,
        "logged_bytes_per_frame": received.logged_bytes_per_frame,
        "render_ms_p50": eyeview.render_ms_p50,
        "renderer_cpu_share": eyeview.cpu_share,
        "recorder_cpu_share": recorder.cpu_share,
        "latency_ms": dict(received.latency_ms),
    }


def grasp_figures(view: RobotView, task_done: list[float]) -> tuple[dict[str, object], list[str]]:
    """The teleoperation task's figures of merit (JSON), from the services that measured
    them (an outside service's are None; an outside operator's success is its
    TASK_DONE's), and the problems the run reported: the motion's, and an operator that
    did not finish."""
    plant, controller = view.plant or PlantSummary(), view.controller or ControllerSummary()
    haptic = view.haptic or HapticSummary()
    operator = view.operator
    said_success = operator.success if operator is not None else task_done[-1:] == [1.0]
    operator = operator or OperatorSummary()
    problems = list(_or(controller.motion_problems, ()))
    figures: dict[str, object] = {
        "motion_problems": problems,
        **{key: json_value(getattr(controller, key)) for key in copied_fields(CONTROLLER, GRASP)},
        "object_in_box": plant.object_in_box,
        "object_bin_distance_m": plant.object_bin_distance_m,
        "duration_s": operator.task_duration_s,
        "max_device_force_n": haptic.max_rendered_force_n,
        # The energy the force exchanged with the hand, and what the stabiliser dissipated.
        "passivity": haptic.passivity,
        "max_contact_force_n": plant.max_contact_force_n,
        "obstacle_min_clearance_m": plant.obstacle_min_clearance_m,
        "tool_speed_max_m_s": plant.tool_speed_max_m_s,
        "velocity_tracking_rms_m_s": controller.velocity_tracking_rms_m_s,
        "stale_feedback_events": haptic.stale_feedback_events,
        "max_obstacle_force_n": controller.max_obstacle_force_n,
        "held_weight_n": controller.held_weight_n,
        "phases": json_value(operator.phases),
        "operator_failure": operator.failure or None,  # why the operator gave up
    }
    gave_up = f": {operator.failure}" if operator.failure else ""
    said = [] if said_success else [f"the operator did not finish the task{gave_up}"]
    return figures, [*problems, *said]
