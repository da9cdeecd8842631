"""A services run's summary, assembled from what each service wrote on close and what
the launcher heard (:class:`teleop.run.run_watch.RunWatch`): each robot's task figures and
verdict (:func:`robot_section`; several robots: a section each under ``robots``), the
run's real-time health, the drops by receiver, the machine, the faults and every
service's own summary under ``services``. Reads files only: no bus, no processes."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from teleop.bus import graph
from teleop.bus.graph import EYEVIEW, PLANT
from teleop.bus.service import read_summary
from teleop.core.config import Config
from teleop.core.criteria import TaskFigures, judge_task
from teleop.core.rundir import LOG_DIR, idle_poll_status_path, summary_path
from teleop.core.summary import CONTROLLER, GRASP, PATH, copied_fields
from teleop.run.failure import RunError
from teleop.run.fault_run import FaultRun
from teleop.run.idle_poll import POLLING, read_status
from teleop.run.run_watch import RunWatch
from teleop.run.verdict import drop_lines, machine_section, realtime_health, refused_privileges


def service_summaries(
    run_dir: Path, services: Sequence[str], killed: frozenset[str]
) -> dict[str, dict[str, Any]]:
    """Each service's summary by name (RunError for one that wrote none). A service
    killed on purpose (``killed``) whose new incarnation was stopped while still starting
    has only its killed process's running summary, or none if that one was killed before
    its first (teleop.bus.service): the run's figures then go without it."""
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


def dropped_by_receiver(
    launcher: Mapping[str, Any], summaries: Mapping[str, Mapping[str, Any]]
) -> dict[str, dict[str, Any]]:
    """The bad records each receiver dropped (restarted services: their earlier
    processes' too), by kind and reason, and the first detail of each."""
    dropped_by: dict[str, dict[str, Any]] = {"launcher": dict(launcher)}
    for name, s in summaries.items():
        for incarnation in (*s.get("earlier_incarnations", []), s):
            mine = dropped_by.setdefault(name, {"counts": {}, "first": {}})
            for key, count in (incarnation.get("dropped_by_reason") or {}).items():
                mine["counts"][key] = mine["counts"].get(key, 0) + count
            for key, detail in (incarnation.get("dropped_first") or {}).items():
                mine["first"].setdefault(key, detail)
    return dropped_by


def idle_poll_report(cpus: Sequence[int], run_dir: Path) -> dict[str, Any]:
    """After a run: the CPUs whose poller polled, and why the others did not."""
    statuses = {cpu: read_status(idle_poll_status_path(run_dir, cpu)) for cpu in cpus}
    return {
        "idle_poll_cpus": [cpu for cpu, status in statuses.items() if status == POLLING],
        "idle_poll_failed": {cpu: s for cpu, s in statuses.items() if s != POLLING},
    }


def run_summary(
    config: Config,
    run_dir: Path,
    started: Sequence[str],
    outside: Sequence[str],
    watch: RunWatch,
    faults: FaultRun | None,
    polled_cpus: Sequence[int],
    wall_s: float,
) -> dict[str, Any]:
    """The run's summary (docs/running.md, the summary's fields); ``polled_cpus``: the CPUs
    the run asked idle pollers for."""
    specs = faults.specs if faults is not None else ()
    killed = frozenset(spec.service for spec in specs if spec.kind == "kill")
    summaries = service_summaries(run_dir, started, killed)
    robot_ids = watch.robot_ids
    plants = graph.instances([PLANT], robot_ids)
    # A pair of peers that never linked: what one sent the other is lost (Service.become_ready).
    unlinked = {n: s["unlinked_peers"] for n, s in summaries.items() if s.get("unlinked_peers")}
    dropped_by = dropped_by_receiver(watch.drops.by_key(), summaries)
    summary: dict[str, Any] = {
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
    if len(robot_ids) == 1:  # one robot: its section is the run's
        summary.update(sections[robot_ids[0]])
    else:
        summary.update(robots_verdict(config.run.scenario, sections))
    idle_poll = idle_poll_report(polled_cpus, run_dir)
    machine = machine_section(summaries, polled_cpus, idle_poll)
    plant_summaries = [summaries.get(name, {}) for name in plants]
    summary.update(
        {
            **run_health(config.run.mode, plant_summaries, dropped_by, unlinked, faults),
            "outside": list(outside),
            "summaries_missing": [name for name in started if name not in summaries],
            # Services whose earlier processes wrote a summary (restarted after it).
            "restarted_services": {
                name: len(s["earlier_incarnations"])
                for name, s in summaries.items()
                if s.get("earlier_incarnations")
            },
            "dropped_messages": sum(sum(d["counts"].values()) for d in dropped_by.values()),
            "unlinked_peers": unlinked,
            "stack_wall_s": wall_s,
            **idle_poll,
            "machine": machine,
            "refused_privileges": refused_privileges(machine),
            "faults": faults.report(summary.get("success")) if faults is not None else [],
            "run_dir": str(run_dir),
            "services": summaries,
        }
    )
    return summary


def run_health(
    mode: str,
    plants: Sequence[Mapping[str, Any]],
    dropped_by: Mapping[str, Mapping[str, Any]],
    unlinked: Mapping[str, Any],
    faults: FaultRun | None = None,
) -> dict[str, Any]:
    """The run's real-time verdict (teleop.run.verdict.realtime_health) from its plants'
    summaries, the bad records its receivers dropped (:func:`dropped_by_receiver`) and the
    services that never linked; the brakes an injected fault caused are the fault's, not a
    loss of real time."""
    fault_braked = faults.braked_states() if faults is not None else 0
    health = realtime_health(
        mode,
        overrun_fraction=max(p.get("overrun_fraction", 0.0) for p in plants),
        realtime_factor=min(p.get("realtime_factor") or 0.0 for p in plants),
        watchdog_brakes=sum(p.get("stale_commands", 0) for p in plants)
        - (faults.brakes() if faults else 0),
        braked_steps=max(0, sum(p.get("stale_steps", 0) for p in plants) - fault_braked),
        steps=sum(p.get("steps", 0) for p in plants),
        drops=drop_lines(dropped_by),
        unlinked_peers=dict(unlinked),
    )
    return health.to_json()


def robot_view(
    summaries: Mapping[str, dict[str, Any]], robot_id: str, robot_ids: Sequence[str]
) -> dict[str, dict[str, Any]]:
    """The services' summaries as one robot's run saw them, by service: its own plant,
    controller and eye view (``<service>-<robot_id>`` in a run of several robots), and
    the station's services, whose per-robot figures (a section per robot under
    ``robots``: the operator's task, the recorder's file) are this robot's."""
    view: dict[str, dict[str, Any]] = {}
    for name, summary in summaries.items():
        role, robot = graph.role_of(name), graph.robot_of(name)
        if robot is not None and robot != robot_id:
            continue
        own = summary.get("robots", {}).get(robot_id) if len(robot_ids) > 1 else None
        view[role] = {**summary, **own} if isinstance(own, dict) else summary
    return view


def robot_section(
    config: Config, view: Mapping[str, dict[str, Any]], task_done: list[float]
) -> dict[str, Any]:
    """One robot's figures, verdict and plant figures, from its services' summaries
    (:func:`robot_view`) and the operator's TASK_DONE values for it."""
    plant, controller = view.get("plant", {}), view.get("controller", {})
    if config.run.teleoperated:
        figures, problems = grasp_figures(view, task_done)
    else:
        figures = {
            "duration_s": config.run.duration_s,
            **{key: controller.get(key) for key in copied_fields(CONTROLLER, PATH)},
        }
        # A run that stalls or collides is not a good run either (teleop.control.path).
        problems = list(controller.get("motion_problems", []))
        figures["motion_problems"] = problems
    if plant.get("aborted") or plant.get("failure"):
        # The plant ended the run on a failure: whatever the task's figures say, it did
        # not go on to its end.
        problems = [*problems, f"plant: {plant.get('failure') or 'aborted'}"]
    figures["commands_received"] = plant.get("commands_received")
    figures["commands_applied"] = plant.get("commands_applied")
    # The task's criteria (teleop.core.criteria) and the problems: the one verdict, which
    # the summary holds enough to give again (criteria.judge_summary).
    verdict = judge_task(config.run.scenario, TaskFigures.from_json(figures), problems).to_json()
    sim_s = (plant.get("steps") or 0) * config.tick_s
    return {
        **figures,
        **verdict,
        "steps": plant.get("steps"),
        "wall_s": plant.get("wall_s"),
        "realtime_factor": plant.get("realtime_factor"),
        "overrun_fraction": plant.get("overrun_fraction"),
        "commands_clamped": plant.get("commands_clamped"),
        "commands_clamped_by_reason": plant.get("commands_clamped_by_reason"),
        "command_stream": plant.get("command_stream"),
        "stale_commands": plant.get("stale_commands"),
        # The plant's own stops on contact force and tool speed (teleop.sim.protective).
        "protective_stop": plant.get("protective_stop"),
        # The plant ended the run on a failure (its reason), and its restarts.
        "failure": plant.get("failure"),
        "plant_resumes": plant.get("resumes", []),
        "skipped_states": controller.get("skipped_states"),
        "final_state_sha256": plant.get("final_state_sha256"),
        # CPU seconds per simulated second of this robot's own processes (start-up in).
        "cpu_s_per_sim_s": {
            role: round(view[role]["cpu_s"] / sim_s, 4)
            for role in graph.PER_ROBOT
            if role in view and sim_s > 0 and view[role].get("cpu_s") is not None
        },
        "eye_view": eye_view_summary(view),
        "rrd": view.get("recorder", {}).get("rrd_path"),
    }


def robots_verdict(scenario: str, sections: Mapping[str, dict[str, Any]]) -> dict[str, Any]:
    """A run of several robots: a section per robot (each judged by itself, its
    ``scenario`` with it so criteria.judge_summary judges it again the same way) and the
    run's verdict: every robot's task succeeded; its problems, each with its robot."""
    return {
        "robots": {rid: {"scenario": scenario, **s} for rid, s in sections.items()},
        "success": all(s.get("success") for s in sections.values()),
        "problems": [f"{rid}: {p}" for rid, s in sections.items() for p in s.get("problems", [])],
        "reasons": [f"{rid}: {r}" for rid, s in sections.items() for r in s.get("reasons", [])],
        "failure": next((s["failure"] for s in sections.values() if s.get("failure")), None),
        "rrd": next((s["rrd"] for s in sections.values() if s.get("rrd")), None),
    }


def eye_view_summary(summaries: dict[str, dict[str, Any]]) -> dict[str, Any] | None:
    """Frames rendered and received (over SHM), render time, CPU shares, latency."""
    eyeview = summaries.get(EYEVIEW)
    if eyeview is None:
        return None
    recorder = summaries.get("recorder", {})
    received = recorder.get("eye_view", {})
    return {
        "frames_published": eyeview["frames_published"],
        "frames_received": received.get("received"),
        "frames_received_shm": received.get("received_shm"),
        "logged_bytes_per_frame": received.get("logged_bytes_per_frame"),
        "render_ms_p50": eyeview["render_ms_p50"],
        "renderer_cpu_share": eyeview["cpu_share"],
        "recorder_cpu_share": recorder.get("cpu_share"),
        "latency_ms": {k: v for k, v in received.items() if k.endswith("_ms")},
    }


def grasp_figures(
    summaries: dict[str, dict[str, Any]], task_done: list[float]
) -> tuple[dict[str, Any], list[str]]:
    """The teleoperation task's figures of merit, from the services that measured them
    (an outside service's are None; an outside operator's success is its TASK_DONE's),
    and the problems the run reported: the motion's, and an operator that did not finish."""
    plant, controller = summaries.get("plant", {}), summaries.get("controller", {})
    haptic, operator = summaries.get("haptic", {}), summaries.get("operator")
    said_success = operator.get("success") if operator is not None else task_done[-1:] == [1.0]
    operator = operator or {}
    problems = controller.get("motion_problems", [])
    figures = {
        "motion_problems": problems,
        **{key: controller.get(key) for key in copied_fields(CONTROLLER, GRASP)},
        "object_in_box": plant.get("object_in_box"),
        "object_bin_distance_m": plant.get("object_bin_distance_m"),
        "duration_s": operator.get("task_duration_s"),
        "max_device_force_n": haptic.get("max_rendered_force_n"),
        # The energy the force exchanged with the hand, and what the stabiliser dissipated.
        "passivity": haptic.get("passivity"),
        "max_contact_force_n": plant.get("max_contact_force_n"),
        "obstacle_min_clearance_m": plant.get("obstacle_min_clearance_m"),
        "tool_speed_max_m_s": plant.get("tool_speed_max_m_s"),
        "velocity_tracking_rms_m_s": controller.get("velocity_tracking_rms_m_s"),
        "stale_feedback_events": haptic.get("stale_feedback_events"),
        "max_obstacle_force_n": controller.get("max_obstacle_force_n"),
        "held_weight_n": controller.get("held_weight_n"),
        "phases": operator.get("phases"),
        "operator_failure": operator.get("failure") or None,  # why the operator gave up
    }
    gave_up = f": {figures['operator_failure']}" if figures["operator_failure"] else ""
    said = [] if said_success else [f"the operator did not finish the task{gave_up}"]
    return figures, [*problems, *said]
