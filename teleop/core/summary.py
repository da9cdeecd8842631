"""The run summary: the one record a run leaves, versioned, its top-level fields described
once here.

``teleop run`` writes it (``<run-dir>/summary.json`` or ``--summary-json``), a sweep's
task too, and ``teleop report`` and the sweep read it back. Written and read through
this module only: :func:`write_run_summary` stamps :data:`SUMMARY_VERSION`,
:func:`read_run_summary` refuses a record of another version or no summary at all (one
line: what it is, what to do). :data:`SUMMARY_FIELDS` gives every top-level field its
JSON type, the runs that have it and its meaning: the table in docs/running.md is
generated from it (``python -m teleop.core.summary``; a test fails when they drift) and
:func:`summary_problems` checks a summary against it (the tests check every summary a
run writes). The services' own summaries are under ``services`` (one object per service,
its fields its own).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from teleop.core import markdown

# Bumped when a field changes meaning or type or goes away (a new field does not bump it).
SUMMARY_VERSION = 2
VERSION_FIELD = "summary_version"

# Which runs have a field.
ALL = "every run"
SERVICES = "on the services"  # teleop run (not --inprocess), teleop sweep grasp
PATH = "path following"
GRASP = "grasp"
INPROCESS = "in process"  # teleop run path-following --inprocess, teleop sweep path-following
# A service a field is copied from (SummaryField.by).
CONTROLLER = "controller"

# JSON types, as Python's json module reads them.
_TYPES: Mapping[str, tuple[type, ...]] = {
    "boolean": (bool,),
    "integer": (int,),
    "number": (int, float),
    "string": (str,),
    "array": (list,),
    "object": (dict,),
}


class SummaryError(ValueError):
    """Not a run summary this build reads; the message says why and what to do."""


@dataclass(frozen=True)
class SummaryField:
    """One top-level field of the run summary."""

    name: str
    type: str  # a JSON type (:data:`_TYPES`)
    runs: str  # which runs have it: ALL, SERVICES, PATH, GRASP, INPROCESS
    doc: str
    nullable: bool = False  # null where the run has no figure for it
    # The service whose summary gives it, copied as it is by the launcher ("": another
    # source, or assembled); :func:`copied_fields`.
    by: str = ""

    def accepts(self, value: Any) -> bool:
        if value is None:
            return self.nullable
        if self.type in ("integer", "number") and isinstance(value, bool):
            return False
        return isinstance(value, _TYPES[self.type])


F = SummaryField
SUMMARY_FIELDS: tuple[SummaryField, ...] = (
    F(VERSION_FIELD, "integer", ALL, f"this record's version ({SUMMARY_VERSION})"),
    # What ran.
    F("scenario", "string", ALL, "path-following or grasp"),
    F("mode", "string", ALL, "realtime, lockstep or inprocess"),
    F("seed", "integer", ALL, "run.seed"),
    F("operator", "string", GRASP, "who drove the handle (run.operator): scripted, or a "
      "person's keyboard, gamepad, spacemouse or web page (docs/operators.md)"),
    F("duration_s", "number", ALL, "path following: run.duration_s; grasp: the operator's "
      "task time (s)", nullable=True),
    # The verdict (teleop.core.criteria).
    F("success", "boolean", ALL, "no criterion failed and the run reported no problem"),
    F("criteria", "array", ALL, "the task's criteria: name, status (pass, fail, "
      "unavailable: no figure for it) and detail; teleop.core.criteria"),
    F("problems", "array", ALL, "what the run itself said went wrong: the motion's stalls "
      "and contacts, an operator that did not finish, a plant that ended the run"),
    F("reasons", "array", ALL, "why the run failed, one line each: the failed criteria's "
      "details, then the problems (empty on a success)"),
    F("motion_problems", "array", ALL, "the controller's own account of the motion's "
      "problems (a part of problems)"),
    # The motion, measured by the controller.
    F("arm_contacts", "integer", ALL, "steps with an unintended contact of the arm or "
      "gripper (any makes success false)", nullable=True, by=CONTROLLER),
    F("min_clearance_m", "number", ALL, "the arm's least clearance to the scene, itself "
      "and its fingers (m)", nullable=True, by=CONTROLLER),
    F("min_clearance_scene_m", "number", ALL, "... to the table, bin and obstacles (m)",
      nullable=True, by=CONTROLLER),
    F("min_clearance_self_m", "number", ALL, "... to its own links (m)", nullable=True,
      by=CONTROLLER),
    F("min_clearance_finger_m", "number", ALL, "... of the fingers (m)", nullable=True,
      by=CONTROLLER),
    F("singularity_crossings", "integer", ALL, "times the arm went near a singularity",
      nullable=True, by=CONTROLLER),
    F("events", "array", ALL, "the controller's events (STALL, CONTACT, SINGULARITY) with "
      "their sim time", nullable=True, by=CONTROLLER),
    F("final_state_sha256", "string", ALL, "hash of the plant's final state: equal for "
      "equal lockstep runs", nullable=True),
    F("realtime_factor", "number", ALL, "sim time over wall time", nullable=True),
    F("steps", "integer", ALL, "plant steps", nullable=True),
    F("wall_s", "number", ALL, "the plant's wall time (s)", nullable=True),
    F("commands_clamped", "integer", ALL, "commands the plant cut to the robot's limits "
      "(each joint's drive range, the tool's speed at plant.tool_speed_limit_m_s)",
      nullable=True),
    F("commands_clamped_by_reason", "object", ALL, "physics steps the plant cut or slowed a "
      "command in, by reason: joint_range, tool_speed, approach (a step may count under "
      "several); docs/running.md, The limits a controller meets", nullable=True),
    F("commands_applied", "integer", ALL, "commands of its controller the plant applied "
      "(none: the run failed)", nullable=True),
    # Path following.
    F("settle_s", "number", PATH, "the path error counts from here (run.settle_s)",
      nullable=True, by=CONTROLLER),
    F("compensation", "boolean", PATH, "dynamic compensation on", nullable=True, by=CONTROLLER),
    F("path_error_rms_m", "number", PATH, "distance to the path after settle_s, RMS (m)",
      nullable=True, by=CONTROLLER),
    F("path_error_max_m", "number", PATH, "... its largest value (m)", nullable=True,
      by=CONTROLLER),
    F("path_progress", "number", PATH, "share of the path travelled", nullable=True, by=CONTROLLER),
    F("stalled_s", "number", PATH, "time the tool made no progress (s)", nullable=True,
      by=CONTROLLER),
    F("stalls", "integer", INPROCESS, "STALL events", nullable=True),
    F("min_manipulability", "number", PATH, "the arm's least manipulability",
      nullable=True, by=CONTROLLER),
    # Grasp.
    F("object_in_box", "boolean", GRASP, "the cube ended in the bin", nullable=True),
    F("object_bin_distance_m", "number", GRASP, "how far the cube's centre ended from "
      "the inside of the bin (m; 0: in it)", nullable=True),
    F("max_device_force_n", "number", GRASP, "largest force rendered on the handle (N; "
      "the device saturates at 8 N)", nullable=True),
    F("passivity", "object", GRASP, "the energy the force feedback exchanged with the "
      "operator's hand (J, teleop.devices.haptic.passivity): energy_in_j, energy_out_j, "
      "observed_j and its least value observer_min_j (below zero: the channel gave "
      "energy out), dissipated_j by the stabiliser (teleop.stabiliser)", nullable=True),
    F("max_contact_force_n", "number", GRASP, "largest contact force on the gripper (N)",
      nullable=True),
    F("obstacle_min_clearance_m", "number", GRASP, "the tool's least distance to a virtual "
      "obstacle (m)", nullable=True),
    F("tool_speed_max_m_s", "number", GRASP, "largest tool speed the plant measured in "
      "any step (m/s), whatever was commanded", nullable=True),
    F("velocity_tracking_rms_m_s", "number", GRASP, "the tool's velocity against the "
      "operator's reference, RMS (m/s)", nullable=True),
    F("stale_feedback_events", "integer", GRASP, "times the handle faded out a stale "
      "force", nullable=True),
    F("max_obstacle_force_n", "number", GRASP, "largest obstacle repulsion fed back (N)",
      nullable=True),
    F("held_weight_n", "number", GRASP, "the held cube's weight as fed back (N)",
      nullable=True),
    F("phases", "array", GRASP, "the operator's phases with their times", nullable=True),
    F("operator_failure", "string", GRASP, "why the operator gave up", nullable=True),
    # The run on the services.
    F("overrun_fraction", "number", SERVICES, "plant steps that started late",
      nullable=True),
    F("realtime_verdict", "string", SERVICES, "clean, degraded or lost "
      "(docs/running.md, the verdict's bounds)"),
    F("realtime_problems", "array", SERVICES, "why the verdict is not clean"),
    F("stale_commands", "integer", SERVICES, "watchdog brakes", nullable=True),
    F("commands_received", "integer", SERVICES, "commands that reached the plant",
      nullable=True),
    F("command_stream", "object", SERVICES, "commands not admitted, by reason "
      "(docs/protocol.md, Where every command goes)", nullable=True),
    F("protective_stop", "object", SERVICES, "the plant's stops on contact force and tool "
      "speed: limits, count, steps_held, each stop", nullable=True),
    F("failure", "string", SERVICES, "why the plant ended the run", nullable=True),
    F("plant_resumes", "array", SERVICES, "the plant's restarts that resumed the run"),
    F("restarted_services", "object", SERVICES, "restarts per service"),
    F("dropped_messages", "integer", SERVICES, "bad records dropped by any service"),
    F("unlinked_peers", "object", SERVICES, "pairs of services that never linked"),
    F("skipped_states", "integer", SERVICES, "states the controller skipped for a newer "
      "one (realtime)", nullable=True),
    F("outside", "array", SERVICES, "services run outside the stack (--without)"),
    F("summaries_missing", "array", SERVICES, "services that left no summary"),
    F("stack_wall_s", "number", SERVICES, "wall time of the whole stack (s)"),
    F("idle_poll_cpus", "array", SERVICES, "CPUs kept polling (realtime)"),
    F("idle_poll_failed", "object", SERVICES, "CPUs whose poller failed, with its status"),
    F("machine", "object", SERVICES, "CPUs, user, privileges granted and refused"),
    F("refused_privileges", "array", SERVICES, "realtime privileges the kernel refused"),
    F("eye_view", "object", SERVICES, "frames rendered and received, render time, latency",
      nullable=True),
    F("faults", "array", SERVICES, "what followed each injected fault (--kill, --freeze)"),
    F("rrd", "string", SERVICES, "the Rerun recording (of several robots: one of them "
      "all, each robot's entities under its id)", nullable=True),
    F("cpu_s_per_sim_s", "object", SERVICES, "CPU seconds per simulated second of the "
      "robot's own processes (plant, controller, eye view), start-up included"),
    F("robots", "object", SERVICES, "a run of several robots (run.robots): a section per "
      "robot id with that robot's task, verdict and plant fields of this table, and its "
      "scenario (criteria.judge_summary judges a section as a run)"),
    F("run_dir", "string", SERVICES, "the run directory"),
    F("services", "object", SERVICES, "each service's own summary, by name"),
)  # fmt: skip
FIELDS_BY_NAME: Mapping[str, SummaryField] = {f.name: f for f in SUMMARY_FIELDS}


def summary_problems(summary: Mapping[str, Any]) -> list[str]:
    """What in ``summary`` the schema does not describe: unknown fields, and values of
    another type (empty: it conforms)."""
    problems = []
    for name, value in summary.items():
        spec = FIELDS_BY_NAME.get(name)
        if spec is None:
            problems.append(f"{name}: not a summary field (teleop.core.summary)")
        elif not spec.accepts(value):
            problems.append(f"{name}: {type(value).__name__}, not {spec.type}")
    return problems


def summary_text(summary: Mapping[str, Any]) -> str:
    """``summary`` as the JSON a run leaves, stamped with :data:`SUMMARY_VERSION`."""
    return json.dumps({VERSION_FIELD: SUMMARY_VERSION, **summary}, indent=2) + "\n"


def write_run_summary(path: Path, summary: Mapping[str, Any]) -> None:
    """Write ``summary`` to ``path`` (its directory made), versioned."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(summary_text(summary))


def read_run_summary(path: Path) -> dict[str, Any]:
    """The run summary in ``path``; SummaryError (one line) if it cannot be read, is no
    run summary, or is of another version."""
    path = Path(path)
    try:
        content = json.loads(path.read_text())
    except OSError as exc:
        raise SummaryError(f"{path}: {exc.strerror}") from None
    except ValueError as exc:
        raise SummaryError(f"{path}: not JSON ({exc})") from None
    if not isinstance(content, dict) or "scenario" not in content:
        raise SummaryError(f"{path}: not a run summary (teleop run's summary.json)")
    version = content.get(VERSION_FIELD)
    if version != SUMMARY_VERSION:
        raise SummaryError(
            f"{path}: summary version {version}, this build reads {SUMMARY_VERSION}: "
            "run it again with this build"
        )
    return content


def copied_fields(service: str, runs: str) -> tuple[str, ...]:
    """The fields a run of ``runs`` (PATH or GRASP) copies as they are from ``service``'s
    summary (SummaryField.by), in the table's order."""
    return tuple(f.name for f in SUMMARY_FIELDS if f.by == service and f.runs in (ALL, runs))


def summary_table() -> str:
    """The fields table of docs/running.md (Markdown)."""
    rows = [
        (f"`{f.name}`", f.type + (" or null" if f.nullable else ""), f.runs, f.doc)
        for f in SUMMARY_FIELDS
    ]
    return "\n".join(markdown.table(("field", "type", "runs", "what"), rows))


if __name__ == "__main__":
    print(summary_table())
