"""A task's success criteria: one verdict for ``teleop run``, ``teleop sweep`` and the
report.

Pure functions of typed records (a run's :class:`~teleop.core.summary.RunSummary`, the
:class:`TaskFigures` it is judged by), so a unit test judges one without running anything:

- path following: path error RMS <= 1 mm and max <= 3 mm after settling,
  ``path_progress`` >= 0.95, no unintended contact (``arm_contacts`` == 0);
- grasp: the cube in the bin, no unintended contact, device force below the device's
  8 N peak (it saturates there: a run that reached it asked for more);
- both: the plant applied commands of its controller (``commands_applied`` > 0): a run
  whose arm was never driven (a controller that sent nothing the plant could take) is
  no success, whatever else it measured.

A criterion whose figure the run does not report is *unavailable*: a short run (before
``run.settle_s``), or one whose controller ran outside the stack, has no path error. A
run succeeds when no criterion fails and the run itself reported no problem (a stall, a
contact, an operator that gave up, a plant that aborted); the sweep asks more of its
tasks: every criterion measured as well (:attr:`TaskVerdict.complete`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from teleop.core.config import scenario_spec
from teleop.core.summary import Criterion, RunSummary

# Path following.
MAX_PATH_ERROR_RMS_M = 1e-3
MAX_PATH_ERROR_M = 3e-3
MIN_PATH_PROGRESS = 0.95
# Grasp: the largest force rendered on the handle (N), the device's peak. The device
# saturates there, so a run that reached it (within SATURATED_N) asked for more: it fails.
MAX_DEVICE_FORCE_N = 8.0
SATURATED_N = 0.01

PASS, FAIL, UNAVAILABLE = "pass", "fail", "unavailable"


@dataclass(frozen=True)
class TaskVerdict:
    """A run judged: its criteria, and the problems the run itself reported."""

    criteria: tuple[Criterion, ...]
    problems: tuple[str, ...] = ()

    @property
    def failed(self) -> list[str]:
        """The details of the criteria that failed."""
        return [c.detail for c in self.criteria if c.status == FAIL]

    @property
    def unmeasured(self) -> list[str]:
        """The names of the criteria the run gave no figure for."""
        return [c.name for c in self.criteria if c.status == UNAVAILABLE]

    @property
    def success(self) -> bool:
        """No criterion failed and the run reported no problem."""
        return not self.failed and not self.problems

    @property
    def reasons(self) -> list[str]:
        """Why the run failed, one line each: the failed criteria, then the problems."""
        return [*self.failed, *self.problems]

    @property
    def complete(self) -> bool:
        """Every criterion was measured."""
        return not self.unmeasured

    def to_json(self) -> dict[str, object]:
        """The summary's ``success``, ``criteria``, ``problems`` and ``reasons`` (JSON):
        with the figures, all :func:`judge_summary` needs to judge the run again, the same
        way."""
        return {
            "success": self.success,
            "criteria": [c.to_json() for c in self.criteria],
            "problems": list(self.problems),
            "reasons": self.reasons,
        }


def _number(value: object) -> float | None:
    return None if value is None else float(value)


def _count(value: object) -> int | None:
    return None if value is None else int(value)


@dataclass(frozen=True)
class TaskFigures:
    """The figures a task is judged by, as a run's summary gives them (None: the run did
    not report it, and its criterion is unavailable, never passed): :meth:`of` a run's
    record, or :meth:`from_json` the figures a run is assembling; the criteria read this
    record."""

    path_error_rms_m: float | None = None
    path_error_max_m: float | None = None
    path_progress: float | None = None
    arm_contacts: int | None = None
    commands_applied: int | None = None
    commands_received: int | None = None
    object_in_box: bool | None = None
    object_bin_distance_m: float | None = None
    max_device_force_n: float | None = None

    @classmethod
    def of(cls, summary: RunSummary) -> TaskFigures:
        """The figures of a run's summary (or of a robot's section of one)."""
        in_box = summary.object_in_box
        return cls(
            path_error_rms_m=_number(summary.path_error_rms_m),
            path_error_max_m=_number(summary.path_error_max_m),
            path_progress=_number(summary.path_progress),
            arm_contacts=_count(summary.arm_contacts),
            commands_applied=_count(summary.commands_applied),
            commands_received=_count(summary.commands_received),
            object_in_box=None if in_box is None else bool(in_box),
            object_bin_distance_m=_number(summary.object_bin_distance_m),
            max_device_force_n=_number(summary.max_device_force_n),
        )

    @classmethod
    def from_json(cls, figures: Mapping[str, object]) -> TaskFigures:
        """The figures of a summary's JSON (the figures a run assembles, before it writes
        them); SummaryError if one has another type than the summary gives it."""
        return cls.of(RunSummary.from_json(figures))


def _at_most(value: float | None, key: str, bound: float, unit: str, scale: float,
             name: str) -> Criterion:  # fmt: skip
    if value is None:
        return Criterion(name, UNAVAILABLE, f"{key} not reported")
    shown = f"{value * scale:.3g} {unit}"
    if value <= bound:
        return Criterion(name, PASS, shown)
    return Criterion(name, FAIL, f"{name}: {shown} > {bound * scale:g} {unit}")


def _no_contact(figures: TaskFigures) -> Criterion:
    contacts = figures.arm_contacts
    if contacts is None:
        return Criterion("no unintended contact", UNAVAILABLE, "arm_contacts not reported")
    if contacts == 0:
        return Criterion("no unintended contact", PASS, "0 steps")
    return Criterion(
        "no unintended contact", FAIL, f"unintended contact: {contacts} steps in contact"
    )


def _commands_applied(figures: TaskFigures) -> Criterion:
    name = "commands applied"
    applied, received = figures.commands_applied, figures.commands_received
    if applied is None:
        return Criterion(name, UNAVAILABLE, "commands_applied not reported")
    if applied > 0:
        return Criterion(name, PASS, f"{applied}")
    if received is None:
        got = ""
    elif received == 0:
        got = ": none it could read reached it (see the records dropped)"
    else:
        got = f": {received} reached it, none admitted"
    return Criterion(name, FAIL, f"the plant applied no command of its controller{got}")


def judge_path(figures: TaskFigures) -> list[Criterion]:
    """The path-following criteria."""
    progress = figures.path_progress
    if progress is None:
        progress_c = Criterion("path progress", UNAVAILABLE, "path_progress not reported")
    elif progress >= MIN_PATH_PROGRESS:
        progress_c = Criterion("path progress", PASS, f"{progress:.3f}")
    else:
        progress_c = Criterion(
            "path progress", FAIL, f"path progress {progress:.3f} < {MIN_PATH_PROGRESS:g}"
        )
    rms, peak = figures.path_error_rms_m, figures.path_error_max_m
    return [
        _at_most(rms, "path_error_rms_m", MAX_PATH_ERROR_RMS_M, "mm", 1e3, "path error RMS"),
        _at_most(peak, "path_error_max_m", MAX_PATH_ERROR_M, "mm", 1e3, "path error max"),
        progress_c,
        _no_contact(figures),
        _commands_applied(figures),
    ]


def judge_grasp(figures: TaskFigures) -> list[Criterion]:
    """The grasp criteria."""
    in_bin = figures.object_in_box
    if in_bin is None:
        bin_c = Criterion("cube in the bin", UNAVAILABLE, "object_in_box not reported")
    elif in_bin:
        bin_c = Criterion("cube in the bin", PASS, "yes")
    else:
        away = figures.object_bin_distance_m
        where = "" if away is None else f": {away * 100:.1f} cm from its inside (bound 0)"
        bin_c = Criterion("cube in the bin", FAIL, f"the cube is not in the bin{where}")
    force = figures.max_device_force_n
    if force is None:
        force_c = Criterion("device force", UNAVAILABLE, "max_device_force_n not reported")
    elif force < MAX_DEVICE_FORCE_N - SATURATED_N:
        force_c = Criterion("device force", PASS, f"{force:.3g} N")
    else:
        force_c = Criterion(
            "device force", FAIL, f"device force at its {MAX_DEVICE_FORCE_N:g} N peak (saturated)"
        )
    return [bin_c, _no_contact(figures), force_c, _commands_applied(figures)]


def judge_task(scenario: str, figures: TaskFigures, problems: Sequence[str] = ()) -> TaskVerdict:
    """The ``figures`` of a ``scenario`` run judged by its criteria; ``problems``: what
    the run itself said went wrong."""
    teleoperated = scenario_spec(scenario).teleoperated
    criteria = judge_grasp(figures) if teleoperated else judge_path(figures)
    return TaskVerdict(tuple(criteria), tuple(problems))


def judge_summary(summary: RunSummary) -> TaskVerdict:
    """A run's summary (as ``teleop run`` writes it: its ``scenario``, figures and
    ``problems``) judged again: the one verdict ``teleop run`` gave it, and the one the
    sweep and the report give it. KeyError if it names no scenario."""
    if summary.scenario is None:
        raise KeyError("scenario")
    return judge_task(summary.scenario, TaskFigures.of(summary), summary.problems or ())


def event_reasons(summary: RunSummary) -> list[str]:
    """What the run itself said went wrong: the operator's failure reason and the run's
    events (stall, unintended contact, singularity, out of reach), when it reports them."""
    reasons = []
    if summary.failure:  # the plant ended the run (teleop.sim.stepping.Abort)
        reasons.append(f"plant: {summary.failure}")
    operator = (summary.services or {}).get("operator")
    failure = summary.operator_failure or (
        operator.get("failure") if isinstance(operator, Mapping) else None
    )
    if failure:
        reasons.append(f"operator: {failure}")
    for event in summary.events or ():
        if isinstance(event, Mapping):
            name = event.get("event") or event.get("kind") or event.get("name")
            at = event.get("sim_time_s")
            reasons.append(f"event {name}" + (f" at {float(at):.1f} s" if at is not None else ""))
        else:
            reasons.append(f"event {event}")
    return reasons
