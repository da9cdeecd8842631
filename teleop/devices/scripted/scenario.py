"""The scripted operator's scenario: the task's phases, read from a scenario file
(``deploy/scenarios/*.toml``), validated at load.

A phase names a target (an offset from the cube, the bin or the tool's position at phase
start), the gripper's state, its tolerance, dwell and timeout; a ``repeat`` block
unrolls into phases. :class:`teleop.devices.scripted.operator.ScriptedOperator` plays
them; the launcher and the task generator read them (what a task is, its phases' names).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from teleop.core.config import (
    ConfigError,
    RobotConfig,
    build,
    read_toml,
)

# --- Scenario vocabulary -----------------------------------------------------------------

TOOL_ANCHOR = "tool"  # target relative to the tool position at phase start
GRIPPER_STATES = {"open": False, "closed": True}  # gripper word -> GRIPPER_CLOSE held
# Keys of a repeat entry in the [[phase]] list (see Scenario.from_table).
REPEAT_KEY = "repeat"
_TOP_LEVEL_KEYS = ("task", "phase")


class ScenarioError(ConfigError):
    """A scenario file is missing, malformed or has a bad value (names file and phase)."""


# --- The scenario --------------------------------------------------------------------------


@dataclass(frozen=True)
class Target:
    """A target point: ``offset_m`` (world frame, m) from an anchor.

    ``relative_to`` is an object name (its observed position at phase start) or
    ``"tool"`` (the observed tool position at phase start).
    """

    relative_to: str
    offset_m: tuple[float, float, float]


@dataclass(frozen=True)
class Phase:
    """One step of the task: where the tool goes, what the gripper does, when it is done.

    Built from a ``[[phase]]`` table by :func:`teleop.core.config.build` (the keys are the
    field names); the values are checked here, the anchor against the scene's objects by
    :meth:`Scenario.from_table`.
    """

    name: str
    target: Target
    gripper: str  # "open" or "closed": GRIPPER_CLOSE held during the phase when closed
    tolerance_m: float  # done once |target - tool| <= this ...
    timeout_s: float  # give up (task fails) after this long in the phase
    dwell_s: float = 0.0  # ... continuously for this long (sim time)
    carrying: bool = False  # the held object must stay with the tool (else: lost, fail)

    def __post_init__(self) -> None:
        _check(bool(self.name), "name: expected a non-empty string")
        _check(
            self.gripper in GRIPPER_STATES,
            f"gripper {self.gripper!r}: one of {', '.join(GRIPPER_STATES)}",
        )
        _check(self.tolerance_m > 0, f"tolerance_m: must be > 0, got {self.tolerance_m!r}")
        _check(self.timeout_s > 0, f"timeout_s: must be > 0, got {self.timeout_s!r}")
        _check(self.dwell_s >= 0, f"dwell_s: must be >= 0, got {self.dwell_s!r}")
        _check(
            self.dwell_s < self.timeout_s,
            f"dwell_s ({self.dwell_s:g}) must be below timeout_s ({self.timeout_s:g})",
        )

    @property
    def gripper_closed(self) -> bool:
        """True when the phase holds GRIPPER_CLOSE."""
        return GRIPPER_STATES[self.gripper]


@dataclass(frozen=True)
class Task:
    """The ``[task]`` table: limits of the whole task and the object it carries."""

    max_task_s: float
    held_object: str  # the object a ``carrying`` phase checks
    carry_tolerance_m: float  # the held object's centre stays this close to the tool

    def __post_init__(self) -> None:
        _check(self.max_task_s > 0, f"max_task_s: must be > 0, got {self.max_task_s!r}")
        _check(
            self.carry_tolerance_m > 0,
            f"carry_tolerance_m: must be > 0, got {self.carry_tolerance_m!r}",
        )


@dataclass(frozen=True)
class Repeat:
    """A repeat entry of the ``[[phase]]`` list: its ``block`` phases in turn, ``repeat``
    phases in all (a last partial round is allowed); each copy's name gets ``_<k>``,
    ``k`` counting the phases this entry expands to from 0."""

    repeat: int
    block: tuple[dict[str, Any], ...]

    def __post_init__(self) -> None:
        _check(self.repeat >= 1, f"repeat: must be >= 1, got {self.repeat!r}")
        _check(bool(self.block), "block: expected at least one [[phase.block]] table")


def _check(ok: bool, message: str) -> None:
    if not ok:
        raise ConfigError(message)


@dataclass(frozen=True)
class Scenario:
    """An ordered task, loaded from TOML (see ``deploy/scenarios/grasp.toml``)."""

    phases: tuple[Phase, ...]
    max_task_s: float
    held_object: str  # the object a ``carrying`` phase checks
    carry_tolerance_m: float  # the held object's centre stays this close to the tool
    source: str = field(default="<memory>", compare=False)

    @classmethod
    def load(
        cls, path: str | Path, object_names: Sequence[str] = RobotConfig().object_bodies
    ) -> Scenario:
        """Read and validate a scenario file; ScenarioError names the file and the phase."""
        path = Path(path)
        table = read_toml(path, ScenarioError)
        return cls.from_table(table, object_names, source=str(path))

    @classmethod
    def from_table(
        cls,
        table: Mapping[str, Any],
        object_names: Sequence[str] = RobotConfig().object_bodies,
        source: str = "<memory>",
    ) -> Scenario:
        """Validate a parsed scenario (the TOML document as a dict), repeats expanded.

        The ``[task]`` table and every phase are built by the config's typed loader
        (:func:`teleop.core.config.build`); an error names ``source``, the phase (index in
        the file and name) and the key.
        """
        try:
            return cls._from_table(table, object_names, source)
        except ScenarioError:
            raise
        except ConfigError as exc:
            raise ScenarioError(f"{source}: {exc}") from exc

    @classmethod
    def _from_table(
        cls, table: Mapping[str, Any], object_names: Sequence[str], source: str
    ) -> Scenario:
        unknown = ", ".join(sorted(set(table) - set(_TOP_LEVEL_KEYS)))
        expected = ", ".join(_TOP_LEVEL_KEYS)
        _check(not unknown, f"top level: unknown key(s) {unknown} (expected {expected})")
        raw_task = table.get("task")
        _check(isinstance(raw_task, Mapping), "top level: missing [task] table")
        task = build(Task, raw_task, "[task]")
        _check(
            task.held_object in object_names,
            f"[task]: held_object {task.held_object!r} is not one of {list(object_names)}",
        )
        raw_phases = table.get("phase")
        _check(isinstance(raw_phases, list) and bool(raw_phases), "top level: no [[phase]] tables")
        anchors = {TOOL_ANCHOR, *object_names}
        phases = []
        for where, raw in expand_phases(raw_phases):
            phase = build(Phase, raw, where)
            _check(
                phase.target.relative_to in anchors,
                f"{where}: target.relative_to {phase.target.relative_to!r}: "
                f"one of {sorted(anchors)}",
            )
            phases.append(phase)
        names = [p.name for p in phases]
        _check(len(set(names)) == len(names), "phases: phase names must be unique")
        return cls(tuple(phases), task.max_task_s, task.held_object, task.carry_tolerance_m, source)

    @property
    def anchors(self) -> frozenset[str]:
        """Every object name a target refers to (``"tool"`` excluded)."""
        names = {p.target.relative_to for p in self.phases} | {self.held_object}
        return frozenset(names - {TOOL_ANCHOR})


def _phase_where(index: int, raw: Any) -> str:
    """How an error names a phase table: its index in the file and its name."""
    name = raw.get("name", "?") if isinstance(raw, Mapping) else "?"
    return f"phase {index} ({name!r})"


def expand_phases(raw_phases: Sequence[Any]) -> list[tuple[str, dict[str, Any]]]:
    """The ``[[phase]]`` list with every repeat entry expanded: (where, phase table) pairs.

    A table with a ``repeat`` key is a :class:`Repeat` (``repeat = N`` and a ``block`` of
    phase tables, ``[[phase.block]]``); the others are phases, kept as they are. ``where``
    names the table in the file for error messages.
    """
    out: list[tuple[str, dict[str, Any]]] = []
    for i, raw in enumerate(raw_phases):
        _check(isinstance(raw, Mapping), f"phase {i}: expected a table")
        if REPEAT_KEY not in raw:
            out.append((_phase_where(i, raw), dict(raw)))
            continue
        entry = build(Repeat, raw, f"phase {i} (repeat)")
        for j, member in enumerate(entry.block):
            _check(isinstance(member, Mapping), f"phase {i} (repeat) block {j}: expected a table")
        block = len(entry.block)
        for k in range(entry.repeat):
            j = k % block
            member = dict(entry.block[j])
            where = f"phase {i} (repeat) block {j} ({member.get('name', '?')!r})"
            if isinstance(member.get("name"), str):
                member["name"] = f"{member['name']}_{k}"
            out.append((where, member))
    return out
