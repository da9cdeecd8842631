"""What a latency report reads of the services' summaries: counters of a stack's run.

From the run's :class:`~teleop.core.summary.RunSummary`: through the services' records
(:mod:`teleop.core.service_summaries`) where those have the field, else from the
service's summary JSON (:func:`_service_json`): samples shed, records lost or
reordered, the services' rates and CPU, deadlines missed.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields

from teleop.core.service_summaries import (
    ControllerSummary,
    HmdSummary,
    PlantSummary,
    record_of,
)
from teleop.core.summary import RunSummary, json_number

# -- what the report reads of the services' summaries -------------------------------------


def _service_json(summary: RunSummary, role: str, *section: str) -> Mapping[str, object]:
    """A service's summary JSON (or a section of it: ``arrival``, ``loop``), for the
    counters its record in teleop.core.service_summaries does not have; empty if absent."""
    content: object = (summary.services or {}).get(role, {})
    for key in section:
        content = content.get(key, {}) if isinstance(content, Mapping) else {}
    return content if isinstance(content, Mapping) else {}


def _count(content: Mapping[str, object], key: str) -> int:
    """A counter of a summary's JSON, 0 if not written."""
    value = content.get(key, 0)
    return int(value) if isinstance(value, int | float) else 0


def _figure(content: Mapping[str, object], key: str) -> float | None:
    """A number of a summary's JSON as written, None if not written."""
    return json_number(content.get(key))


@dataclass(frozen=True)
class ShedCounts:
    """Inputs dropped on purpose because a service was behind (:func:`shed_counters`)."""

    haptic: int
    state: int
    feedback: int
    command: int
    command_late: int
    command_stale: int

    @property
    def total(self) -> int:
        return sum(asdict(self).values())

    def to_json(self) -> dict[str, int]:
        return asdict(self)


@dataclass(frozen=True)
class LostCounts:
    """Messages per stream the bus never delivered (gaps in ``seq``)."""

    haptic: int
    command: int
    state: int
    feedback: int

    def to_json(self) -> dict[str, int]:
        return asdict(self)


@dataclass(frozen=True)
class ReorderedCounts:
    """Messages per stream that came after a newer one."""

    haptic: int
    command: int
    feedback: int

    @property
    def total(self) -> int:
        return sum(asdict(self).values())

    def to_json(self) -> dict[str, int]:
        return asdict(self)


def shed_counters(summary: RunSummary) -> ShedCounts:
    """Inputs dropped on purpose because a service was behind (a CPU stall): the
    controller's too-old haptic samples and states, the haptic device's too-old
    feedback, the plant's too-old commands, those that came after their device period
    was stepped (merged into the next step) and those too stale to apply. Each is a
    handle sample that never comes back (a state or feedback without one is counted
    too)."""
    arrival = _service_json(summary, "plant", "arrival")
    controller = _service_json(summary, "controller")
    return ShedCounts(
        haptic=_count(controller, "haptic_shed"),
        state=_count(controller, "states_shed"),
        feedback=_count(_service_json(summary, "haptic"), "feedback_shed"),
        command=_count(arrival, "commands_shed"),
        command_late=_count(arrival, "commands_late"),
        command_stale=_count(arrival, "commands_stale"),
    )


def stream_counters(summary: RunSummary) -> tuple[LostCounts, ReorderedCounts]:
    """(lost, reordered) per stream, from the services' own sequence checks: a gap in a
    stream's ``seq`` is a message the bus never delivered."""
    arrival = _service_json(summary, "plant", "arrival")
    controller = _service_json(summary, "controller")
    haptic = _service_json(summary, "haptic")
    skipped_states = ControllerSummary.from_json(controller).skipped_states
    lost = LostCounts(
        haptic=_count(controller, "haptic_lost"),
        command=_count(arrival, "commands_lost"),
        state=int(skipped_states or 0),
        feedback=_count(haptic, "feedback_lost"),
    )
    reordered = ReorderedCounts(
        haptic=_count(controller, "haptic_reordered"),
        command=_count(arrival, "commands_reordered"),
        feedback=_count(haptic, "feedback_reordered"),
    )
    return lost, reordered


@dataclass(frozen=True)
class ServiceRates:
    """Loop or message rate of each service over the run (Hz); None: not known."""

    plant_hz: float | None
    haptic_hz: float | None
    controller_hz: float | None
    hmd_hz: float | None

    def to_json(self) -> dict[str, float | None]:
        return {f.name.removesuffix("_hz"): getattr(self, f.name) for f in fields(self)}


def service_rates(summary: RunSummary) -> ServiceRates:
    """Loop or message rate of each service over the run (Hz)."""
    wall_s = summary.wall_s or 0.0

    def per_s(count: float | None) -> float | None:
        return float(count) / wall_s if count is not None and wall_s > 0 else None

    hmd = HmdSummary.from_json(_service_json(summary, "hmd"))
    return ServiceRates(
        plant_hz=_figure(_service_json(summary, "plant"), "rate_hz"),
        haptic_hz=_figure(_service_json(summary, "haptic"), "rate_hz"),
        controller_hz=per_s(_figure(_service_json(summary, "controller"), "cycles")),
        hmd_hz=per_s(hmd.published),
    )


def cpu_share(summary: RunSummary) -> dict[str, float | None]:
    """Each service's CPU time over the run's wall time (1.0 = one core all the time;
    start-up included, so a short run overstates it), by service name."""
    wall_s = summary.stack_wall_s or 0.0
    shares = {}
    for name in summary.services or {}:
        cpu_s = record_of(name, _service_json(summary, name)).cpu_s
        shares[name] = cpu_s / wall_s if wall_s > 0 and cpu_s is not None else None
    return shares


@dataclass(frozen=True)
class PlantMisses:
    """The plant's device periods without a command, its stalls, overruns and skipped
    ticks, as its summary gives them (None: not written)."""

    steps: int | None
    periods_without_command: int | None
    stalls: int | None
    overrun_fraction: float | None
    skipped_ticks: int | None


@dataclass(frozen=True)
class HapticMisses:
    """The haptic device loop's overruns, skipped ticks and lateness (None: not written)."""

    steps: int | None
    overruns: int | None
    skipped_ticks: int | None
    lateness_p99_us: float | None


@dataclass(frozen=True)
class DeadlineMisses:
    """Each periodic loop's misses (:func:`deadline_misses`)."""

    plant: PlantMisses
    haptic: HapticMisses

    def to_json(self) -> dict[str, dict[str, float | None]]:
        return {"plant": asdict(self.plant), "haptic": asdict(self.haptic)}


def deadline_misses(summary: RunSummary) -> DeadlineMisses:
    """Each periodic loop's misses: the plant's device periods without a command and stalls,
    the haptic device loop's overruns and skipped ticks."""
    plant = PlantSummary.from_json(_service_json(summary, "plant"))
    arrival = _service_json(summary, "plant", "arrival")
    haptic = _service_json(summary, "haptic")
    haptic_loop = _service_json(summary, "haptic", "loop")
    return DeadlineMisses(
        plant=PlantMisses(
            steps=plant.steps,
            periods_without_command=_figure(arrival, "steps_without_command"),
            stalls=_figure(arrival, "stalls"),
            overrun_fraction=plant.overrun_fraction,
            skipped_ticks=_figure(_service_json(summary, "plant"), "skipped_ticks"),
        ),
        haptic=HapticMisses(
            steps=_figure(haptic, "steps"),
            overruns=_figure(haptic_loop, "overruns"),
            skipped_ticks=_figure(haptic_loop, "skipped"),
            lateness_p99_us=_figure(haptic_loop, "lateness_p99_us"),
        ),
    )
