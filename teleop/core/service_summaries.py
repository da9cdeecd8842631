"""The services' own summaries as typed records: what the launcher reads of the summary
each service writes at close (``<run-dir>/<service>.summary.json``, teleop.bus.service).

The run summary (:mod:`teleop.core.summary`) is assembled from these records; each
service's JSON goes under its ``services`` field as the service wrote it. One record per
role, over :class:`ServiceSummary`, the fields every service writes
(``Service.summary``): :class:`PlantSummary`, :class:`ControllerSummary`,
:class:`HapticSummary`, :class:`OperatorSummary`, :class:`RecorderSummary`,
:class:`EyeViewSummary`, :class:`HmdSummary`. A record holds the fields the run reads,
not every figure a service reports (those stay in its JSON, for people and the tests).

Where a run summary field is copied from a service's (``SummaryField.by``), the record
has that field under the same name and type: a test holds them to the description in
:data:`teleop.core.summary.SUMMARY_FIELDS`, and another holds each record to what its
service writes. None: the service did not write the field (an older build, a running
summary of a killed process, a service left outside the stack).
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TypeVar

from teleop.core.summary import PhaseTime, json_number, json_value

R = TypeVar("R", bound="ServiceSummary")


@dataclass(frozen=True)
class Drops:
    """The bad records a receiver dropped (teleop.bus.messages.DropCounter): ``counts``
    and the ``first`` one's detail, by ``"KIND:reason"``."""

    counts: Mapping[str, int]
    first: Mapping[str, str]

    @classmethod
    def from_json(cls, counts: object, first: object) -> Drops:
        return cls(dict(_mapping(counts)), {k: str(v) for k, v in _mapping(first).items()})

    def to_json(self) -> dict[str, dict[str, object]]:
        return {"counts": dict(self.counts), "first": dict(self.first)}


@dataclass(frozen=True)
class ServiceSummary:
    """The fields every service's summary has (teleop.bus.service.Service.summary), and
    those the reader of a run directory adds: ``pid``, ``running`` (a running summary: the
    process did not close) and ``earlier_incarnations`` (a restarted service's earlier
    processes, oldest first)."""

    service: str | None = None
    pid: int | None = None
    running: bool | None = None
    dropped_messages: int | None = None
    # Every rejected record, by record kind and reason, and the first of each.
    dropped_by_reason: Mapping[str, int] | None = None
    dropped_first: Mapping[str, str] | None = None
    cpu_s: float | None = None  # CPU time (user + system, all threads) at the summary
    cpu_s_ready: float | None = None
    unlinked_peers: tuple[str, ...] | None = None
    unknown_peers: tuple[str, ...] | None = None
    # Each privilege asked for and its outcome (teleop.bus.service.pin_to_cpus and others).
    privileges: Mapping[str, str] | None = None
    earlier_incarnations: tuple[ServiceSummary, ...] = ()

    @classmethod
    def from_json(cls: type[R], content: Mapping[str, object]) -> R:
        """The record of a service's summary JSON: the fields this record has (arrays as
        tuples, earlier incarnations as records of this class); the others are left out."""
        hints = typing.get_type_hints(cls)
        values: dict[str, object] = {}
        for f in dataclasses.fields(cls):
            if f.name not in content:
                continue
            value = content[f.name]
            if f.name == "earlier_incarnations":
                value = tuple(cls.from_json(_mapping(e)) for e in _sequence(value))
            elif value is not None and _is_tuple(hints[f.name]):
                item = _tuple_item(hints[f.name])
                items = _sequence(value)
                if hasattr(item, "from_json"):  # a record per item (PhaseTime)
                    items = [item.from_json(_mapping(i)) for i in items]
                value = tuple(items)
            values[f.name] = value
        return cls(**values)

    def to_json(self) -> dict[str, object]:
        """This record's fields as JSON (those not None; no earlier incarnations)."""
        return {
            f.name: json_value(getattr(self, f.name))
            for f in dataclasses.fields(self)
            if f.name != "earlier_incarnations" and getattr(self, f.name) is not None
        }

    @property
    def incarnations(self) -> tuple[ServiceSummary, ...]:
        """Every process of this service in the run, oldest first, this one last."""
        return (*self.earlier_incarnations, self)

    @property
    def drops(self) -> Drops:
        """The bad records this process dropped."""
        return Drops.from_json(self.dropped_by_reason, self.dropped_first)


@dataclass(frozen=True)
class PlantSummary(ServiceSummary):
    """The plant's (teleop.sim.stepping, services/plant.py)."""

    mode: str | None = None
    finished: bool | None = None  # the run went to its end
    steps: int | None = None
    wall_s: float | None = None
    realtime_factor: float | None = None
    overrun_fraction: float | None = None
    commands_received: int | None = None
    commands_applied: int | None = None
    commands_clamped: int | None = None
    commands_clamped_by_reason: Mapping[str, int] | None = None
    command_stream: Mapping[str, float] | None = None
    stale_commands: int | None = None  # watchdog brakes
    stale_steps: int | None = None  # steps braked by the watchdog
    final_state_sha256: str | None = None
    max_contact_force_n: float | None = None
    obstacle_min_clearance_m: float | None = None
    tool_speed_max_m_s: float | None = None
    protective_stop: Mapping[str, object] | None = None
    object_in_box: bool | None = None
    object_bin_distance_m: float | None = None
    aborted: bool | None = None
    failure: str | None = None  # why the plant ended the run
    resumes: tuple[Mapping[str, object], ...] | None = None  # its restarts that resumed


@dataclass(frozen=True)
class ControllerSummary(ServiceSummary):
    """The controller's (teleop.control.cycle, services/controller.py); the fields the run
    summary copies as they are (``SummaryField.by == "controller"``) under their names."""

    arm_contacts: int | None = None
    min_clearance_m: float | None = None
    min_clearance_scene_m: float | None = None
    min_clearance_self_m: float | None = None
    min_clearance_finger_m: float | None = None
    singularity_crossings: int | None = None
    events: tuple[Mapping[str, object], ...] | None = None
    settle_s: float | None = None
    compensation: bool | None = None
    path_error_rms_m: float | None = None
    path_error_max_m: float | None = None
    path_progress: float | None = None
    stalled_s: float | None = None
    min_manipulability: float | None = None
    motion_problems: tuple[str, ...] | None = None
    velocity_tracking_rms_m_s: float | None = None
    max_obstacle_force_n: float | None = None
    held_weight_n: float | None = None
    skipped_states: int | None = None  # states skipped for a newer one (realtime)


@dataclass(frozen=True)
class HapticSummary(ServiceSummary):
    """The haptic device's (teleop.devices.haptic.loop, services/haptic.py)."""

    max_rendered_force_n: float | None = None
    stale_feedback_events: int | None = None
    # The energy the force exchanged with the hand (teleop.devices.haptic.passivity).
    passivity: Mapping[str, float | str | int] | None = None


@dataclass(frozen=True)
class OperatorSummary(ServiceSummary):
    """The operator's, scripted or a person's (teleop.devices, services/operator.py): in
    a run of several robots, one robot's section over the rest (its ``robots`` entry)."""

    success: bool | None = None
    failure: str | None = None  # why it gave up ("": it did not)
    task_duration_s: float | None = None
    phases: tuple[PhaseTime, ...] | None = None


@dataclass(frozen=True)
class EyeViewReceived:
    """The eye view's frames as the recorder received them (its ``eye_view``)."""

    received: int | None = None
    received_shm: int | None = None
    logged_bytes_per_frame: float | None = None
    # Each latency's figures, by name (``*_ms``: hmd_to_received_ms, render_ms, ...).
    latency_ms: Mapping[str, object] = dataclasses.field(default_factory=dict)

    @classmethod
    def from_json(cls, content: Mapping[str, object]) -> EyeViewReceived:
        return cls(
            received=_int(content.get("received")),
            received_shm=_int(content.get("received_shm")),
            logged_bytes_per_frame=json_number(content.get("logged_bytes_per_frame")),
            latency_ms={k: v for k, v in content.items() if k.endswith("_ms")},
        )


@dataclass(frozen=True)
class RecorderSummary(ServiceSummary):
    """The recorder's (services/recorder.py)."""

    rrd_path: str | None = None
    viewer: str | None = None  # the live viewer's state ("not spawned: ..." if it failed)
    cpu_share: float | None = None
    eye_view: Mapping[str, object] | None = None

    @property
    def eye_view_received(self) -> EyeViewReceived:
        return EyeViewReceived.from_json(self.eye_view or {})


@dataclass(frozen=True)
class EyeViewSummary(ServiceSummary):
    """The eye view's (services/eyeview.py)."""

    frames_published: int | None = None
    render_ms_p50: float | None = None
    cpu_share: float | None = None
    shm_pool: Mapping[str, object] | None = None  # its SHM pool, and why not, if refused


@dataclass(frozen=True)
class HmdSummary(ServiceSummary):
    """The head-mounted display's (services/hmd.py)."""

    samples: int | None = None
    published: int | None = None


# The record of each role's summary (teleop.bus.graph roles); another role's is a
# ServiceSummary.
RECORDS: Mapping[str, type[ServiceSummary]] = {
    "plant": PlantSummary,
    "controller": ControllerSummary,
    "haptic": HapticSummary,
    "operator": OperatorSummary,
    "recorder": RecorderSummary,
    "eyeview": EyeViewSummary,
    "hmd": HmdSummary,
}


def record_of(role: str, content: Mapping[str, object]) -> ServiceSummary:
    """The record of a service of ``role``'s summary JSON."""
    return RECORDS.get(role, ServiceSummary).from_json(content)


def record_problems(role: str, content: Mapping[str, object]) -> list[str]:
    """What in a service of ``role``'s summary JSON its record does not read as its type
    gives it: a field of another JSON type (empty: the record reads it all). The tests
    check every service's summary a run writes with it."""
    record = RECORDS.get(role, ServiceSummary)
    hints = typing.get_type_hints(record)
    problems = []
    for f in dataclasses.fields(record):
        value = content.get(f.name)
        if f.name == "earlier_incarnations":
            for earlier in _sequence(value):
                problems += [f"earlier: {p}" for p in record_problems(role, _mapping(earlier))]
        elif value is not None and not _is_json_of(value, hints[f.name]):
            problems.append(f"{role}.{f.name}: {type(value).__name__}, not {hints[f.name]}")
    return problems


def _is_json_of(value: object, hint: object) -> bool:
    """Whether JSON ``value`` is of the type ``hint`` (``T | None``) gives a field."""
    outer = next(a for a in typing.get_args(hint) if a is not type(None))
    origin = typing.get_origin(outer) or outer
    if origin is tuple:
        return isinstance(value, list)
    if origin is Mapping:
        return isinstance(value, dict)
    if origin is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if origin is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, origin)


def _is_tuple(hint: object) -> bool:
    return any(typing.get_origin(a) is tuple for a in (hint, *typing.get_args(hint)))


def _tuple_item(hint: object) -> object:
    """The item type of a ``tuple[T, ...] | None`` hint."""
    tuples = [a for a in (hint, *typing.get_args(hint)) if typing.get_origin(a) is tuple]
    return typing.get_args(tuples[0])[0]


def _mapping(value: object) -> Mapping[str, object]:
    return value if isinstance(value, Mapping) else {}


def _sequence(value: object) -> list[object]:
    return list(value) if isinstance(value, list | tuple) else []


def _int(value: object) -> int | None:
    return value if isinstance(value, int) else None
