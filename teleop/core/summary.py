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
run writes). :class:`RunSummary` is the typed record of it, one attribute per field in
the description's order and type (a test holds the two together): what
:func:`read_run_summary` returns and what the verdict (teleop.core.criteria), the report
and the sweep read; the JSON is met only in its :meth:`RunSummary.from_json` and
:meth:`RunSummary.to_json`. The services' own summaries are under ``services`` (one
object per service, its fields its own).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
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


@dataclass(frozen=True)
class Criterion:
    """One success criterion of one task (teleop.core.criteria): ``status`` pass, fail or
    unavailable, ``detail`` the figure or why it failed."""

    name: str
    status: str
    detail: str

    @classmethod
    def from_json(cls, content: Mapping[str, object]) -> Criterion:
        return cls(str(content["name"]), str(content["status"]), str(content["detail"]))

    def to_json(self) -> dict[str, str]:
        return {"name": self.name, "status": self.status, "detail": self.detail}


@dataclass(frozen=True)
class PhaseTime:
    """One phase of the operator's task as it began: its index among the task's phases
    (the scenario's, or a person's task's), its name and the sim time it began at (s)."""

    phase: int
    name: str
    sim_time_s: float

    @classmethod
    def from_json(cls, content: Mapping[str, object]) -> PhaseTime:
        phase, sim_time_s = content.get("phase"), json_number(content.get("sim_time_s"))
        return cls(
            phase=phase if isinstance(phase, int) and not isinstance(phase, bool) else -1,
            name=str(content.get("name", "")),
            sim_time_s=math.nan if sim_time_s is None else sim_time_s,
        )

    def to_json(self) -> dict[str, object]:
        return {"phase": self.phase, "name": self.name, "sim_time_s": self.sim_time_s}


@dataclass(frozen=True)
class FaultOutcome:
    """One injected fault (``teleop run --kill / --freeze``) and what followed, as the
    summary's ``faults`` has it (measured by teleop.run.faults; docs/faults.md): when
    (``t_s``, sim time), the freeze asked for and the time frozen, until the tool was
    braked, the service restarted and the loop resumed (from the injection; None: not
    measured, or never), the run's success; ``error``: the fault could not be injected."""

    service: str
    kind: str
    t_s: float | None = None
    freeze_s: float | None = None
    frozen_s: float | None = None
    brake_ms: float | None = None
    restart_s: float | None = None
    resumed_s: float | None = None
    success: bool | None = None
    error: str = ""

    @classmethod
    def from_json(cls, content: Mapping[str, object]) -> FaultOutcome:
        success = content.get("success")
        return cls(
            service=str(content.get("service", "")),
            kind=str(content.get("kind", "")),
            t_s=json_number(content.get("t_s")),
            freeze_s=json_number(content.get("freeze_s")),
            frozen_s=json_number(content.get("frozen_s")),
            brake_ms=json_number(content.get("brake_ms")),
            restart_s=json_number(content.get("restart_s")),
            resumed_s=json_number(content.get("resumed_s")),
            success=success if isinstance(success, bool) else None,
            error=str(content.get("error") or ""),
        )

    def to_json(self) -> dict[str, object]:
        """The JSON object: every field, ``error`` only when there is one."""
        out: dict[str, object] = {f.name: getattr(self, f.name) for f in fields(self)}
        if not self.error:
            del out["error"]
        return out


@dataclass(frozen=True)
class RunSummary:
    """The run summary as a typed record: one attribute per :data:`SUMMARY_FIELDS` entry,
    in its order, of its JSON type (a test holds the two together). None: the run did not
    write the field, or wrote null. Arrays are tuples; the criteria are
    :class:`Criterion`, the phases :class:`PhaseTime`, the faults :class:`FaultOutcome`;
    a robot's section under
    ``robots`` is a RunSummary of its own; the objects whose layout belongs to another
    module (the services' own summaries, the machine, the protective stops) stay JSON
    objects.

    ``written``: the fields the run wrote, in its order (default: those not None). It
    keeps a field the run left out apart from one it wrote as null (an in-process run
    has no ``realtime_verdict``; a services run's ``failure`` is null), so
    :meth:`to_json` gives back the JSON :meth:`from_json` read."""

    summary_version: int | None = None
    # What ran.
    scenario: str | None = None
    mode: str | None = None
    seed: int | None = None
    operator: str | None = None
    duration_s: float | None = None
    # The verdict.
    success: bool | None = None
    criteria: tuple[Criterion, ...] | None = None
    problems: tuple[str, ...] | None = None
    reasons: tuple[str, ...] | None = None
    motion_problems: tuple[str, ...] | None = None
    # The motion, measured by the controller.
    arm_contacts: int | None = None
    min_clearance_m: float | None = None
    min_clearance_scene_m: float | None = None
    min_clearance_self_m: float | None = None
    min_clearance_finger_m: float | None = None
    singularity_crossings: int | None = None
    events: tuple[Mapping[str, object], ...] | None = None
    final_state_sha256: str | None = None
    realtime_factor: float | None = None
    steps: int | None = None
    wall_s: float | None = None
    commands_clamped: int | None = None
    commands_clamped_by_reason: Mapping[str, int] | None = None
    commands_applied: int | None = None
    # Path following.
    settle_s: float | None = None
    compensation: bool | None = None
    path_error_rms_m: float | None = None
    path_error_max_m: float | None = None
    path_progress: float | None = None
    stalled_s: float | None = None
    stalls: int | None = None
    min_manipulability: float | None = None
    # Grasp.
    object_in_box: bool | None = None
    object_bin_distance_m: float | None = None
    max_device_force_n: float | None = None
    passivity: Mapping[str, float | str | int] | None = None
    max_contact_force_n: float | None = None
    obstacle_min_clearance_m: float | None = None
    tool_speed_max_m_s: float | None = None
    velocity_tracking_rms_m_s: float | None = None
    stale_feedback_events: int | None = None
    max_obstacle_force_n: float | None = None
    held_weight_n: float | None = None
    phases: tuple[PhaseTime, ...] | None = None
    operator_failure: str | None = None
    # The run on the services.
    overrun_fraction: float | None = None
    realtime_verdict: str | None = None
    realtime_problems: tuple[str, ...] | None = None
    stale_commands: int | None = None
    commands_received: int | None = None
    command_stream: Mapping[str, float] | None = None
    protective_stop: Mapping[str, object] | None = None
    failure: str | None = None
    plant_resumes: tuple[Mapping[str, object], ...] | None = None
    restarted_services: Mapping[str, int] | None = None
    dropped_messages: int | None = None
    unlinked_peers: Mapping[str, Sequence[str]] | None = None
    skipped_states: int | None = None
    outside: tuple[str, ...] | None = None
    summaries_missing: tuple[str, ...] | None = None
    stack_wall_s: float | None = None
    idle_poll_cpus: tuple[int, ...] | None = None
    idle_poll_failed: Mapping[str, str] | None = None
    machine: Mapping[str, object] | None = None
    refused_privileges: tuple[str, ...] | None = None
    eye_view: Mapping[str, object] | None = None
    faults: tuple[FaultOutcome, ...] | None = None
    rrd: str | None = None
    cpu_s_per_sim_s: Mapping[str, float] | None = None
    robots: Mapping[str, RunSummary] | None = None
    run_dir: str | None = None
    services: Mapping[str, Mapping[str, object]] | None = None

    written: tuple[str, ...] = field(default=(), repr=False)

    def __post_init__(self) -> None:
        if not self.written:
            present = tuple(f.name for f in SUMMARY_FIELDS if getattr(self, f.name) is not None)
            object.__setattr__(self, "written", present)

    @classmethod
    def from_json(cls, content: Mapping[str, object]) -> RunSummary:
        """The record of a summary's JSON (as a run writes it, or a robot's section of
        one). SummaryError if a field has another type than :data:`SUMMARY_FIELDS` gives
        it; a field this build does not know is left out (a newer build's, same version)."""
        wrong = [p for p in summary_problems(content) if "not a summary field" not in p]
        if wrong:
            raise SummaryError(f"not a run summary of this build: {'; '.join(wrong)}")
        values: dict[str, object] = {}
        for name, value in content.items():
            spec = FIELDS_BY_NAME.get(name)
            if spec is None:
                continue
            if name == "criteria" and value is not None:
                value = tuple(Criterion.from_json(c) for c in _objects(name, value))
            elif name == "phases" and value is not None:
                value = tuple(PhaseTime.from_json(c) for c in _objects(name, value))
            elif name == "faults" and value is not None:
                value = tuple(FaultOutcome.from_json(c) for c in _objects(name, value))
            elif name == "robots" and value is not None:
                value = {rid: cls.from_json(s) for rid, s in _object(name, value).items()}
            elif spec.type == "array" and value is not None:
                value = tuple(_array(name, value))
            values[name] = value
        return cls(**values, written=tuple(values))

    def to_json(self) -> dict[str, object]:
        """The JSON object of this record: the fields it was written with, in their order."""
        return {name: json_value(getattr(self, name)) for name in self.written}

    def section(self, robot_id: str) -> RunSummary:
        """Robot ``robot_id``'s section of a run of several robots over the run's own fields
        (its scenario, mode, the stack's figures), without ``robots``: what a run of that
        robot alone would say of it. KeyError if the run has no such robot."""
        own = (self.robots or {})[robot_id]
        merged = {n: getattr(self, n) for n in self.written if n != "robots"}
        merged.update({n: getattr(own, n) for n in own.written})
        return RunSummary(**merged, written=tuple(merged))


def _array(name: str, value: object) -> list[object]:
    if not isinstance(value, list | tuple):
        raise SummaryError(f"{name}: {type(value).__name__}, not array")
    return list(value)


def _object(name: str, value: object) -> Mapping[str, Mapping[str, object]]:
    if not isinstance(value, Mapping) or not all(isinstance(v, Mapping) for v in value.values()):
        raise SummaryError(f"{name}: not an object of objects")
    return value


def _objects(name: str, value: object) -> list[Mapping[str, object]]:
    items = _array(name, value)
    if not all(isinstance(item, Mapping) for item in items):
        raise SummaryError(f"{name}: not an array of objects")
    return items


def json_number(value: object) -> float | None:
    """A number of a summary's JSON as written (an int stays an int), None if not one (a
    boolean is no number here, though Python counts it an int)."""
    return value if isinstance(value, int | float) and not isinstance(value, bool) else None


def json_value(value: object) -> object:
    """A field's value as JSON: tuples as arrays, records as their objects."""
    if isinstance(value, Criterion | FaultOutcome | PhaseTime | RunSummary):
        return value.to_json()
    if isinstance(value, tuple):
        return [json_value(item) for item in value]
    if isinstance(value, Mapping) and any(isinstance(v, RunSummary) for v in value.values()):
        return {key: json_value(item) for key, item in value.items()}
    return value


def summary_text(summary: Mapping[str, Any]) -> str:
    """``summary`` as the JSON a run leaves, stamped with :data:`SUMMARY_VERSION`."""
    return json.dumps({VERSION_FIELD: SUMMARY_VERSION, **summary}, indent=2) + "\n"


def write_run_summary(path: Path, summary: Mapping[str, Any]) -> None:
    """Write ``summary`` to ``path`` (its directory made), versioned."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(summary_text(summary))


def read_run_summary(path: Path) -> RunSummary:
    """The run summary in ``path`` as its record; SummaryError (one line) if it cannot be
    read, is no run summary, is of another version, or has a field of another type."""
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
    try:
        return RunSummary.from_json(content)
    except SummaryError as exc:
        raise SummaryError(f"{path}: {exc}") from None


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
