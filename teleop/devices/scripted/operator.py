"""The scripted operator: plays a task on the haptic handle, closing the loop on what it sees.

Pure and process-free: :class:`ScriptedLoop` is the whole operator minus the bus
(``services/operator.py`` feeds it and publishes what it sends), so the closed loop and
the service's decisions can be simulated in a test.

What the operator knows is the controller's rate mapping (teleop mode): a handle offset
``d`` (device frame: x forward, away from the operator; y left; z up; metres from the
workspace centre) commands the world tool velocity

    v_world = Rz(yaw) * rate_gain * (|d| - deadband) * d / |d|     (0 inside the deadband),

capped at ``max_tool_speed_m_s``, with ``yaw`` the view yaw of the HMD. The operator
inverts it (:func:`hand_offset_for_velocity`).

The loop, per decision (``operator.decision_rate_hz``, on plant ticks):

1. ``observed`` is what the operator saw ``reaction_delay_s`` ago (tool, objects, view yaw):
   :class:`ObservationBuffer` returns it.
2. Desired tool velocity ``v = k (target - tool)``, capped at ``SPEED_CAP_FRACTION`` of the
   controller's limit (so the controller's own cap never bends the commanded direction).
3. Drift compensation: ``v -= w``, where ``w`` is a slow (``DRIFT_TIME_CONSTANT_S``)
   estimate of the tool velocity seen minus the velocity the operator's own past hand
   commands asked for (:func:`tool_velocity_for_offset`). A constant disturbance, like the
   held cube's weight rendered on the handle (0.2 kg x 9.81 x force_scale 0.5 on a
   200 N/m hand: 5 mm of sag, 3 cm/s of tool drift), would otherwise leave a P loop
   ``drift / k`` = 4 cm short of its target. It acts on the velocity mismatch, not on
   the position error, so a step of the target still converges without overshoot.
4. Inverse mapping to a handle offset, limited to ``max_hand_offset_m`` and to the device
   workspace.
5. A first-order low-pass with ``HAND_TIME_CONSTANT_S`` = 0.15 s: a hand does not jump.
   Deliberate arm/hand movement has a bandwidth of about 1 Hz; 0.15 s puts the corner at
   1 / (2 pi 0.15) = 1.06 Hz. It is also what keeps the hand from twitching by twice the
   deadband when the error changes sign.

Gain ``k``: the loop is an integrator (the robot under rate control) behind a delay ``tau``
(the reaction delay plus the lags the operator does not model: the input lead, the
decision hold and the handle's spring, ``UNMODELLED_LAG_S``) and the hand's first-order
lag ``T``. Its characteristic equation is ``s (1 + T s) + k exp(-s tau) = 0``. A pure delayed
integrator is *stable* for ``k tau < pi / 2``, but it rings long before that: it converges
without overshoot only while a real dominant root exists, ``k tau <= 1/e`` (0.37, four times
below the stability bound). With the hand lag the same condition is ``k <= k_crit(tau, T)``
(:func:`critical_gain_per_s`, closed form below). The operator uses
``k = NO_OVERSHOOT_MARGIN * k_crit``: 0.8 x 0.85 = 0.68 /s with the default 0.2 s reaction
delay (time constant about 1.5 s, slow and careful like a person placing an object).
Overshoot matters here: at the end of the descent the fingertips are 5 mm above the table.

Phases come from a scenario file (``deploy/scenarios/*.toml``, :class:`Scenario`). A target
is an offset from the cube, the bin (positions observed when the phase starts, then held:
a lift target must not follow the cube it lifts) or the tool's position at phase start. A
phase is complete once the observed tool stays within its tolerance for its dwell time; a
phase timeout or the task time limit ends the task with success False, and so does losing
the held object in a ``carrying`` phase.

Like a person, the operator sees what is in the way: at phase start a move whose straight
line would enter a virtual obstacle's influence or cross the bin's walls gets waypoints
over (or around) them (:mod:`teleop.devices.scripted.routing`), passed at cruising speed, the
phase's timeout lengthened by the detour. And it notices when the tool no longer comes
closer though it pushes toward it (``STALL_WINDOW_S``): it gives up at once with an
OUT_OF_REACH event and the reason (out of reach, or blocked by an obstacle) instead of
pushing until the phase times out. A tool the plant held meanwhile (its watchdog braked:
TOOL_POSE's BRAKING flag) was not pushed, and no progress is expected of it.
"""

from __future__ import annotations

import bisect
import dataclasses
import itertools
import logging
import math
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import numpy as np

from teleop.bus.messages import Button, Event
from teleop.core.config import (
    Config,
    ConfigError,
    HapticConfig,
    OperatorConfig,
    RobotConfig,
    TeleopConfig,
    build,
    read_toml,
)
from teleop.core.ticks import hand_schedule, head_schedule, scene_schedule
from teleop.devices.scripted.routing import KeepOut, SceneKnowledge, plan_route, route_length_m
from teleop.sim.proximity import BIN_BODY

logger = logging.getLogger(__name__)

# --- Gains and human limits --------------------------------------------------------------

# Lags the operator does not see in its own model (s): the HAND_INPUT lead (10 ms), half a
# decision period of hold (5 ms) and the handle's hand spring (about 2 / omega_n = 30 ms).
UNMODELLED_LAG_S = 0.05
# Fraction of the no-overshoot gain used, for lags beyond UNMODELLED_LAG_S.
NO_OVERSHOOT_MARGIN = 0.8
# Time constant of the hand's low-pass (s): about 1 Hz of voluntary hand bandwidth.
HAND_TIME_CONSTANT_S = 0.15
# The operator asks for at most this fraction of the controller's speed cap.
SPEED_CAP_FRACTION = 0.8
# Time constant (s) of the operator's estimate of a steady drift (the weight of a held
# object felt on the handle sags the tool; a person learns to hold against it).
DRIFT_TIME_CONSTANT_S = 1.0
# The drift compensation never exceeds this fraction of the operator's speed cap.
DRIFT_LIMIT_FRACTION = 0.5
# Below this tool speed (m/s) the hand eases to the centre instead of hovering at the
# deadband edge, where a sign change of the error would flip it by twice the deadband.
MIN_SPEED_M_S = 5e-4
# A waypoint of a route counts as passed once the tool is this close (m): about the
# distance the tool covers at the operator's cruise speed within the reaction delay.
WAYPOINT_PASS_M = 0.04
# Stopped short: over this long (s) the tool closed less than STALL_PROGRESS_FRACTION of
# the distance the operator's intended speed would have covered, and that distance was at
# least STALL_MIN_EXPECTED_M. A person pushing toward a target that does not come closer
# gives up and says why, instead of pushing until the phase times out.
STALL_WINDOW_S = 3.0
STALL_PROGRESS_FRACTION = 0.1
STALL_MIN_EXPECTED_M = 0.03
# ... and it is still this far (m) from its aim: closer, it is there give or take a sag
# (a held object's weight on the handle), not stopped short.
STALL_MIN_DISTANCE_M = 0.025
# Stopped short within this distance (m) of a keep-out volume: blocked by it.
BLOCKED_NEAR_M = 0.02
# A restarted operator takes the held object for lifted (in the gripper, off the table)
# once its origin is this far (m) above where the scene rests it: more than the object
# settles or rocks on the table or the bin's floor, less than any lift.
LIFTED_M = 0.02

# --- Scenario vocabulary -----------------------------------------------------------------

TOOL_ANCHOR = "tool"  # target relative to the tool position at phase start
GRIPPER_STATES = {"open": False, "closed": True}  # gripper word -> GRIPPER_CLOSE held
# Keys of a repeat entry in the [[phase]] list (see Scenario.from_table).
REPEAT_KEY = "repeat"
_TOP_LEVEL_KEYS = ("task", "phase")


class ScenarioError(ConfigError):
    """A scenario file is missing, malformed or has a bad value (names file and phase)."""


def rot_z(yaw_rad: float) -> np.ndarray:
    """(3, 3) rotation about the world z axis: device/view frame -> world frame."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def critical_gain_per_s(delay_s: float, lag_s: float) -> float:
    """Largest P gain (1/s) at which ``s (1 + lag s) + k exp(-s delay) = 0`` has a real
    dominant root, i.e. the delayed, lagged integrator loop converges without overshoot.

    On the real axis ``k(s) = -s (1 + lag s) exp(s delay)``; its maximum over
    ``-1/lag < s < 0`` is where two real roots meet (critical damping). Setting
    ``dk/ds = 0`` gives ``delay lag s^2 + (2 lag + delay) s + 1 = 0``.
    """
    if delay_s < 0 or lag_s < 0 or delay_s + lag_s == 0:
        raise ValueError("delay_s and lag_s must be >= 0, not both 0")
    if delay_s == 0:
        return 1.0 / (4.0 * lag_s)  # s = -1 / (2 lag)
    if lag_s == 0:
        return 1.0 / (math.e * delay_s)  # s = -1 / delay
    b = 2.0 * lag_s + delay_s
    s = (-b + math.sqrt(b * b - 4.0 * delay_s * lag_s)) / (2.0 * delay_s * lag_s)
    return -s * (1.0 + lag_s * s) * math.exp(s * delay_s)


def hand_offset_for_velocity(
    world_v_m_s: np.ndarray, yaw_rad: float, teleop: TeleopConfig
) -> np.ndarray:
    """Device-frame handle offset (m, (3,)) that makes the controller move the tool at
    ``world_v_m_s`` (world frame, m/s, below the speed cap): the exact inverse of the
    rate mapping. Rotate world -> view with Rz(-yaw), divide the speed by the gain, add
    the deadband back along the same direction. Below ``MIN_SPEED_M_S`` the offset shrinks
    linearly to zero (the hand relaxes; the controller then sees no motion request).
    """
    device_v = rot_z(-yaw_rad) @ np.asarray(world_v_m_s, dtype=np.float64)
    speed = float(np.linalg.norm(device_v))
    if speed == 0.0:
        return np.zeros(3)
    radius_m = speed / teleop.rate_gain_per_s + teleop.deadband_m
    if speed < MIN_SPEED_M_S:
        radius_m = (MIN_SPEED_M_S / teleop.rate_gain_per_s + teleop.deadband_m) * (
            speed / MIN_SPEED_M_S
        )
    return device_v * (radius_m / speed)


def tool_velocity_for_offset(
    offset_m: np.ndarray, yaw_rad: float, teleop: TeleopConfig
) -> np.ndarray:
    """The operator's model of the controller's rate mapping: device-frame handle offset
    (m) -> world tool velocity (m/s), deadband and speed cap included."""
    offset_m = np.asarray(offset_m, dtype=np.float64)
    radius_m = float(np.linalg.norm(offset_m))
    if radius_m <= teleop.deadband_m:
        return np.zeros(3)
    speed = min(teleop.rate_gain_per_s * (radius_m - teleop.deadband_m), teleop.max_tool_speed_m_s)
    return rot_z(yaw_rad) @ (offset_m * (speed / radius_m))


def limit_offset(offset_m: np.ndarray, max_offset_m: float, workspace_half_m: float) -> np.ndarray:
    """Scale a handle offset (device frame, m) back along its own direction so that its
    norm stays within ``max_offset_m`` and every axis within the device's end stops
    (``workspace_half_m``). Scaling, not clipping per axis, keeps the direction."""
    norm = float(np.linalg.norm(offset_m))
    peak = float(np.abs(offset_m).max(initial=0.0))
    scale = 1.0
    if norm > max_offset_m:
        scale = max_offset_m / norm
    if peak * scale > workspace_half_m:
        scale = workspace_half_m / peak
    return offset_m * scale


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


# --- What the operator sees ----------------------------------------------------------------


@dataclass(frozen=True)
class Observation:
    """One delayed look at the scene (world frame, m; yaw in rad about world z)."""

    tick: int  # plant tick of the tool sample
    tool_p_m: np.ndarray  # (3,)
    objects_p_m: Mapping[str, np.ndarray]  # name -> (3,)
    view_yaw_rad: float
    # The plant's watchdog braked since the tool sample before this one (TOOL_POSE's
    # BRAKING flag): the tool was held still, whatever the hand asked.
    tool_braked: bool = False


class ObservationBuffer:
    """Time-stamped scene samples; :meth:`observe` answers "what did I see ``delay`` ago".

    Keyed by plant tick (``sim_time_ns / timestep``): TOOL_POSE and OBJECT_POSES by their
    sample tick, HEAD_POSE by its ``valid_from_tick`` (the tick its predicted yaw is for).
    Thread-safe: Zenoh callbacks add, the decision thread observes and waits. A stream
    whose tick goes backwards has restarted (a new run): its history is dropped.
    """

    _STREAMS = ("tool", "objects", "head")

    def __init__(
        self,
        object_names: Sequence[str],
        delay_ticks: int,
        default_yaw_rad: float,
        keep_ticks: int | None = None,
    ) -> None:
        self.object_names = tuple(object_names)
        self.delay_ticks = delay_ticks
        self.default_yaw_rad = default_yaw_rad
        # History kept per stream beyond the newest sample (ticks): the delay plus slack.
        self.keep_ticks = keep_ticks if keep_ticks is not None else 2 * delay_ticks + 1000
        self._cond = threading.Condition()
        self._ticks: dict[str, list[int]] = {s: [] for s in self._STREAMS}
        self._values: dict[str, list[Any]] = {s: [] for s in self._STREAMS}

    def _add(self, stream: str, tick: int, value: Any) -> None:
        with self._cond:
            ticks, values = self._ticks[stream], self._values[stream]
            if ticks and tick < ticks[-1]:
                ticks.clear()
                values.clear()
            if ticks and tick == ticks[-1]:
                values[-1] = value  # a re-sent sample replaces its first copy
            else:
                ticks.append(tick)
                values.append(value)
            # Keep the newest sample at or before the horizon, drop everything older.
            cut = bisect.bisect_right(ticks, tick - self.keep_ticks) - 1
            if cut > 0:
                del ticks[:cut]
                del values[:cut]
            self._cond.notify_all()

    def add_tool(self, tick: int, world_p_m: np.ndarray, braked: bool = False) -> None:
        """TOOL_POSE at ``tick``: the tool site position (world, m); ``braked``: the plant
        braked since the previous one (its BRAKING flag)."""
        self._add("tool", tick, (np.array(world_p_m, dtype=np.float64), braked))

    def add_objects(self, tick: int, world_p_m: np.ndarray) -> None:
        """OBJECT_POSES at ``tick``: rows in ``object_names`` order (world, m)."""
        rows = np.array(world_p_m[: len(self.object_names)], dtype=np.float64)
        self._add("objects", tick, dict(zip(self.object_names, rows, strict=True)))

    def add_head(self, valid_from_tick: int, predicted_yaw_rad: float) -> None:
        """HEAD_POSE: the view yaw (rad) that applies from ``valid_from_tick``."""
        self._add("head", valid_from_tick, float(predicted_yaw_rad))

    def _newest_at(self, stream: str, tick: int) -> tuple[int, Any] | None:
        ticks = self._ticks[stream]
        i = bisect.bisect_right(ticks, tick) - 1
        return None if i < 0 else (ticks[i], self._values[stream][i])

    def observe(self, tick: int) -> Observation | None:
        """What the operator saw at ``tick - delay_ticks``: the newest tool, objects and
        head samples at or before it (yaw: ``default_yaw_rad`` before the first HEAD_POSE
        applies). None until a tool and an objects sample exist."""
        seen = tick - self.delay_ticks
        with self._cond:
            tool = self._newest_at("tool", seen)
            objects = self._newest_at("objects", seen)
            head = self._newest_at("head", seen)
        if tool is None or objects is None:
            return None
        yaw = self.default_yaw_rad if head is None else head[1]
        tool_p_m, braked = tool[1]
        return Observation(tool[0], tool_p_m, objects[1], yaw, braked)

    def ready(self, tick: int, head_valid_from: int | None) -> bool:
        """True once :meth:`observe` ``(tick)`` can no longer change: the objects sample of
        the observed tool tick is in, and so is the HEAD_POSE valid from
        ``head_valid_from`` (None: no head pose expected)."""
        seen = tick - self.delay_ticks
        with self._cond:
            return self._ready(seen, head_valid_from)

    def _ready(self, seen: int, head_valid_from: int | None) -> bool:
        tool = self._newest_at("tool", seen)
        objects = self._ticks["objects"]
        if tool is not None and not (objects and objects[-1] >= tool[0]):
            return False
        if head_valid_from is not None:
            heads = self._ticks["head"]
            if heads and head_valid_from < heads[0]:
                # Older than every head pose held: sent before this operator subscribed
                # (a restart), or past the history kept. It will never come.
                return True
            i = bisect.bisect_left(heads, head_valid_from)
            return i < len(heads) and heads[i] == head_valid_from
        return True

    def wait_ready(self, tick: int, head_valid_from: int | None, timeout_s: float) -> bool:
        """Block (event driven) until :meth:`ready`; False on timeout (lockstep)."""
        seen = tick - self.delay_ticks
        with self._cond:
            return self._cond.wait_for(lambda: self._ready(seen, head_valid_from), timeout_s)


# --- Taking a task up where the world is ------------------------------------------------


@dataclass(frozen=True)
class Resumption:
    """Where a restarted operator takes the task up: the phase, the anchors its target
    uses instead of the objects' observed positions (name -> world position, m) and why,
    in a few words (for the log and the summary)."""

    phase: int
    anchors: Mapping[str, np.ndarray]
    why: str


def resume_phase(scenario: Scenario, seen: Observation, scene: SceneKnowledge) -> Resumption:
    """The phase of ``scenario`` an operator that joins a run under way (restarted) takes
    the task up at, from one look at the world (``seen``), instead of its first phase:
    the phases are read through their ``carrying`` and ``gripper`` flags, so any
    pick-and-place scenario of that shape resumes the same way.

    - The held object in the gripper (within ``carry_tolerance_m`` of the tool) and lifted
      (``LIFTED_M`` above its rest height, ``scene.rest_z_m``): the first carrying phase
      not yet reached; a target anchored on the held object itself (a lift, which moves
      with it) is taken from where it rests below its current position and counts as
      reached by its height. All reached: the phase after the last carrying one (release).
    - Else, the object lies in the bin (``scene.in_bin``) and a phase follows the last
      carrying one: that phase (release, then what follows).
    - Else, the tool at the object's grasp point (the target of the phase before the
      first closing one, within the closing phase's tolerance): the closing phase.
    - Else the first phase: the object is where it can be picked up from the start.
    """
    phases = scenario.phases
    carrying = [i for i, p in enumerate(phases) if p.carrying]
    if not carrying:
        return Resumption(0, {}, "no carrying phase: from the start")
    first_c, last_c = carrying[0], carrying[-1]
    held = scenario.held_object
    obj = np.asarray(seen.objects_p_m[held], dtype=np.float64)
    tool = np.asarray(seen.tool_p_m, dtype=np.float64)
    attached = float(np.linalg.norm(obj - tool)) <= scenario.carry_tolerance_m
    rest_z = scene.rest_z_m.get(held)
    lifted = rest_z is not None and float(obj[2]) > rest_z + LIFTED_M

    def anchor_of(index: int, anchors: Mapping[str, np.ndarray]) -> np.ndarray:
        name = phases[index].target.relative_to
        if name == TOOL_ANCHOR:
            return tool
        return anchors.get(name, np.asarray(seen.objects_p_m[name], dtype=np.float64))

    if attached and lifted:
        assert rest_z is not None
        anchors = {held: np.array([obj[0], obj[1], rest_z])}
        for i in carrying:
            phase = phases[i]
            target = anchor_of(i, anchors) + np.array(phase.target.offset_m)
            if phase.target.relative_to == held:
                reached = float(tool[2]) >= float(target[2]) - phase.tolerance_m
            else:
                reached = float(np.linalg.norm(target - tool)) <= phase.tolerance_m
            if not reached:
                return Resumption(i, anchors, f"{held} in the gripper, lifted")
        after = min(last_c + 1, len(phases) - 1)
        return Resumption(after, anchors, f"{held} in the gripper, carried to its place")
    if last_c + 1 < len(phases) and scene.in_bin(obj, seen.objects_p_m.get(BIN_BODY)):
        return Resumption(last_c + 1, {}, f"{held} in the bin")
    closing = next((i for i in range(first_c) if phases[i].gripper_closed), None)
    if closing is not None and closing > 0:
        before = phases[closing - 1]
        grasp_point = anchor_of(closing - 1, {}) + np.array(before.target.offset_m)
        if (
            before.target.relative_to == held
            and float(np.linalg.norm(grasp_point - tool)) <= phases[closing].tolerance_m
        ):
            return Resumption(closing, {}, f"tool at the {held}'s grasp point")
    return Resumption(0, {}, f"{held} not in hand: from the start")


# --- The operator ------------------------------------------------------------------------


@dataclass(frozen=True)
class HandCommand:
    """One decision: where the hand pulls the handle and which buttons it holds."""

    target_p_m: np.ndarray  # (3,) device frame, m from the workspace centre
    buttons: Button
    phase: int  # index into Scenario.phases; -1 before the task starts
    done: bool
    success: bool  # meaningful once done
    world_v_ref_m_s: np.ndarray  # (3,) the tool velocity the operator intends (world)


class ScriptedOperator:
    """The decision logic of a human-like operator, one call per decision tick.

    Deterministic: the output depends only on the ticks and observations passed in.
    """

    def __init__(
        self,
        scenario: Scenario,
        operator_cfg: OperatorConfig,
        teleop_cfg: TeleopConfig,
        haptic_cfg: HapticConfig,
        tick_s: float,
        scene: SceneKnowledge | None = None,
    ) -> None:
        self.scenario = scenario
        # What the operator sees of the scene's fixed geometry (None: nothing to avoid).
        self.scene = scene if scene is not None else SceneKnowledge()
        self.operator_cfg = operator_cfg
        self.teleop = teleop_cfg
        self.haptic = haptic_cfg
        self.tick_s = tick_s
        self.gain_per_s = NO_OVERSHOOT_MARGIN * critical_gain_per_s(
            operator_cfg.reaction_delay_s + UNMODELLED_LAG_S, HAND_TIME_CONSTANT_S
        )
        self.speed_cap_m_s = SPEED_CAP_FRACTION * teleop_cfg.max_tool_speed_m_s
        self.drift_limit_m_s = DRIFT_LIMIT_FRACTION * self.speed_cap_m_s
        # A hand command decided at tick s moves the tool from about s + this (ticks).
        self._apply_lag_ticks = round(UNMODELLED_LAG_S / tick_s)
        # Decisions further apart than this (ticks): the device centred the handle
        # meanwhile (haptic.hand_input_stale_s), the hand starts over from there.
        self._hand_hold_ticks = round(haptic_cfg.hand_input_stale_s / tick_s)
        self.hand_holds = 0  # gaps in the decisions that long (a late operator caught up)
        # The haptic device, the operator's only way to move the tool, is gone (its
        # liveliness token withdrawn: killed, restarting): nothing the hand does reaches
        # the tool, so a still tool says nothing about reach (see device_gone).
        self.device_gone = False
        self.device_gone_decisions = 0
        # Expected-velocity history kept for the drift estimate (ticks).
        self._history_ticks = round(operator_cfg.reaction_delay_s / tick_s) + 2 * (
            self._apply_lag_ticks + 1
        )
        self.reset()

    def reset(self) -> None:
        """Forget the task: a new run starts with the hand at rest, before phase 0."""
        self.phase = -1
        self.done = False
        self.success = False
        self.task_start_tick: int | None = None
        self.done_tick: int | None = None
        self.phase_start_ticks: list[int] = []  # index i: tick phase i began
        self.failure = ""  # why the task was given up ("" while running or on success)
        self._phase_start = 0
        self._dwell_start: int | None = None
        self._target_m = np.zeros(3)
        self.route_m: list[np.ndarray] = []  # waypoints still ahead of the target
        self.routes: list[dict[str, Any]] = []  # every route planned (phase, waypoints)
        self._timeout_s = 0.0  # this phase's timeout, a detour's travel time added
        self._stall: list[tuple[int, float, float]] = []  # (tick, distance, intended speed)
        # Events the operator has to announce (Event, value), taken by ScriptedLoop.
        self.events: list[tuple[Event, float]] = []
        self._hand_m = np.zeros(3)  # low-passed handle target, device frame
        self._last_tick: int | None = None
        self.drift_m_s = np.zeros(3)  # estimated tool drift, world frame
        self._prev_seen: tuple[int, np.ndarray] | None = None  # (tick, tool position)
        self._expected: list[tuple[int, np.ndarray]] = []  # (tick in effect, world v)
        # Joined a run under way (a restarted operator): the first look takes the task up
        # where the world is (resume_phase) instead of at phase 0; what it decided.
        self.joining = False
        self.resumed: dict[str, Any] | None = None

    # -- phase logic -----------------------------------------------------------------------
    def _start_phase(
        self,
        index: int,
        tick: int,
        seen: Observation,
        anchors: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        """Begin phase ``index``: its target from the anchor as seen now (or as given in
        ``anchors``), its route, its timeout."""
        phase = self.scenario.phases[index]
        anchor = phase.target.relative_to
        if anchors and anchor in anchors:
            origin = anchors[anchor]
        elif anchor == TOOL_ANCHOR:
            origin = seen.tool_p_m
        else:
            origin = seen.objects_p_m[anchor]
        self._target_m = np.asarray(origin, dtype=np.float64) + np.array(phase.target.offset_m)
        self.phase = index
        self._phase_start = tick
        self._dwell_start = None
        self.phase_start_ticks.append(tick)
        self._stall = []
        self._timeout_s = phase.timeout_s
        volumes = self.keep_outs(seen, phase)
        self.route_m = plan_route(seen.tool_p_m, self._target_m, volumes)
        if self.route_m:
            # A detour takes longer: its extra length at the operator's cruise speed.
            direct_m = float(np.linalg.norm(self._target_m - seen.tool_p_m))
            extra_m = route_length_m(seen.tool_p_m, self.route_m, self._target_m) - direct_m
            self._timeout_s += extra_m / self.speed_cap_m_s
            self.routes.append(
                {
                    "phase": phase.name,
                    "waypoints_m": [np.round(w, 4).tolist() for w in self.route_m],
                    "extra_m": round(extra_m, 4),
                }
            )

    def keep_outs(self, seen: Observation, phase: Phase) -> list[KeepOut]:
        """The volumes the tool keeps out of in ``phase``, the bin where it was seen."""
        bin_p = seen.objects_p_m.get("bin")
        return self.scene.keep_outs(bin_p, holding=phase.carrying)

    @property
    def aim_m(self) -> np.ndarray:
        """Where the tool heads now: the next waypoint, else the phase's target."""
        return self.route_m[0] if self.route_m else self._target_m

    def _finish(self, tick: int, success: bool, why: str = "") -> None:
        self.done = True
        self.success = success
        self.done_tick = tick
        self.failure = why

    def _elapsed_s(self, tick: int, since: int) -> float:
        return (tick - since) * self.tick_s

    def _resume(self, tick: int, seen: Observation) -> None:
        """Take the task up where the world is (see :func:`resume_phase`). The task began
        when the run's first operator first looked, one reaction delay into the run:
        ``max_task_s`` bounds the whole task, the restart included."""
        resumption = resume_phase(self.scenario, seen, self.scene)
        delay_ticks = round(self.operator_cfg.reaction_delay_s / self.tick_s)
        self.task_start_tick = min(tick, delay_ticks)
        self._start_phase(resumption.phase, tick, seen, resumption.anchors)
        name = self.scenario.phases[resumption.phase].name
        self.resumed = {
            "sim_time_s": tick * self.tick_s,
            "phase": resumption.phase,
            "name": name,
            "why": resumption.why,
        }
        logger.info(
            "joined a run under way at %.2f s: taking the task up at phase %d (%s): %s",
            tick * self.tick_s,
            resumption.phase,
            name,
            resumption.why,
        )

    def _update_phase(self, tick: int, seen: Observation) -> None:
        """Advance, complete or give up, from this observation."""
        if self.phase < 0:
            if self.joining:
                self._resume(tick, seen)
            else:
                self.task_start_tick = tick
                self._start_phase(0, tick, seen)
        assert self.task_start_tick is not None
        if self._elapsed_s(tick, self.task_start_tick) > self.scenario.max_task_s:
            self._finish(tick, False, "task time limit")
            return
        phase = self.scenario.phases[self.phase]
        if phase.carrying:
            held = seen.objects_p_m[self.scenario.held_object]
            if np.linalg.norm(held - seen.tool_p_m) > self.scenario.carry_tolerance_m:
                self._finish(tick, False, f"lost the {self.scenario.held_object} in {phase.name}")
                return
        if self.route_m and np.linalg.norm(self.route_m[0] - seen.tool_p_m) <= WAYPOINT_PASS_M:
            self.route_m.pop(0)
            self._stall = []
        if self._stopped_short(tick, seen, phase):
            return
        if self.route_m:
            self._dwell_start = None
        elif np.linalg.norm(self._target_m - seen.tool_p_m) <= phase.tolerance_m:
            if self._dwell_start is None:
                self._dwell_start = tick
            if self._elapsed_s(tick, self._dwell_start) >= phase.dwell_s - 1e-12:
                if self.phase + 1 == len(self.scenario.phases):
                    self._finish(tick, True)
                else:
                    self._start_phase(self.phase + 1, tick, seen)
                return
        else:
            self._dwell_start = None
        if self._elapsed_s(tick, self._phase_start) > self._timeout_s:
            self._finish(tick, False, f"timeout in {phase.name}")

    def _intended_speed_m_s(self, distance_m: float) -> float:
        """The speed (m/s) the operator means the tool to move at, ``distance_m`` from its
        aim: cruising toward a waypoint, slowing down on the phase's target."""
        if self.route_m:
            return self.speed_cap_m_s
        return min(self.speed_cap_m_s, self.gain_per_s * distance_m)

    def _stopped_short(self, tick: int, seen: Observation, phase: Phase) -> bool:
        """Give up (True) when the tool has stopped short of its aim (see STALL_WINDOW_S):
        blocked by a volume it is up against, else out of reach. Announces OUT_OF_REACH."""
        distance_m = float(np.linalg.norm(self.aim_m - seen.tool_p_m))
        # A tool the plant held (braked: lost real time, a silent peer) was not pushed:
        # no progress is expected of it until the next look.
        intended = 0.0 if seen.tool_braked else self._intended_speed_m_s(distance_m)
        self._stall.append((tick, distance_m, intended))
        first_tick = self._stall[0][0]
        if self._elapsed_s(tick, first_tick) < STALL_WINDOW_S:
            return False
        while self._elapsed_s(tick, self._stall[1][0]) >= STALL_WINDOW_S:
            self._stall.pop(0)
        expected_m = sum(
            a[2] * self._elapsed_s(b[0], a[0]) for a, b in itertools.pairwise(self._stall)
        )
        closed_m = self._stall[0][1] - distance_m
        if (
            distance_m < STALL_MIN_DISTANCE_M
            or expected_m < STALL_MIN_EXPECTED_M
            or closed_m >= STALL_PROGRESS_FRACTION * expected_m
        ):
            return False
        blocking = [
            v.name
            for v in self.keep_outs(seen, phase)
            if v.radius_m > 0
            and float(np.linalg.norm(seen.tool_p_m - v.low_m)) < v.radius_m + BLOCKED_NEAR_M
        ]
        where = "a waypoint" if self.route_m else "the target"
        if blocking:
            why = f"blocked by {blocking[0]} in {phase.name}"
        else:
            why = f"{where} out of reach in {phase.name}"
        self.events.append((Event.OUT_OF_REACH, distance_m))
        self._finish(tick, False, f"{why} (stopped {distance_m * 1e3:.0f} mm short)")
        return True

    # -- the hand --------------------------------------------------------------------------
    def _wanted_velocity(self, seen: Observation) -> np.ndarray:
        """k (target - tool) - drift, capped at the operator's speed (world, m/s); toward
        a waypoint, the operator's cruise speed (a waypoint is passed, not stopped at)."""
        error = self.aim_m - seen.tool_p_m
        if self.route_m:
            distance_m = float(np.linalg.norm(error))
            error = error * (self.speed_cap_m_s / (self.gain_per_s * max(distance_m, 1e-9)))
        v = self.gain_per_s * error - self.drift_m_s
        speed = float(np.linalg.norm(v))
        if speed > self.speed_cap_m_s:
            v *= self.speed_cap_m_s / speed
        return v

    def _expected_velocity_at(self, tick: int) -> np.ndarray:
        """The tool velocity the hand commands in effect at ``tick`` asked for."""
        ticks = [t for t, _ in self._expected]
        i = bisect.bisect_right(ticks, tick) - 1
        return np.zeros(3) if i < 0 else self._expected[i][1]

    def _update_drift(self, seen: Observation) -> None:
        """Low-pass (observed - expected) tool velocity between consecutive looks."""
        prev = self._prev_seen
        self._prev_seen = (seen.tick, seen.tool_p_m)
        if prev is None or seen.tick <= prev[0]:
            return
        dt_s = (seen.tick - prev[0]) * self.tick_s
        observed_v = (seen.tool_p_m - prev[1]) / dt_s
        mismatch = observed_v - self._expected_velocity_at(seen.tick - 1)
        alpha = 1.0 - math.exp(-dt_s / DRIFT_TIME_CONSTANT_S)
        drift = self.drift_m_s + alpha * (mismatch - self.drift_m_s)
        norm = float(np.linalg.norm(drift))
        if norm > self.drift_limit_m_s:
            drift *= self.drift_limit_m_s / norm
        self.drift_m_s = drift

    def _remember(self, tick: int, hand_m: np.ndarray, yaw_rad: float) -> None:
        """Store what this hand command asks of the tool, from when it takes effect."""
        v = tool_velocity_for_offset(hand_m, yaw_rad, self.teleop)
        self._expected.append((tick + self._apply_lag_ticks, v))
        horizon = tick - self._history_ticks
        while len(self._expected) > 1 and self._expected[1][0] <= horizon:
            self._expected.pop(0)

    def _move_hand(self, tick: int, goal_m: np.ndarray) -> np.ndarray:
        """Low-pass the hand toward ``goal_m`` over the sim time since the last decision."""
        if self._last_tick is not None and tick > self._last_tick:
            dt_s = (tick - self._last_tick) * self.tick_s
            alpha = 1.0 - math.exp(-dt_s / HAND_TIME_CONSTANT_S)
            self._hand_m = self._hand_m + alpha * (goal_m - self._hand_m)
        self._last_tick = tick
        return self._hand_m.copy()

    def _after_hold(self, tick: int) -> None:
        """No decision for longer than the device keeps a hand input (a late operator
        catching up by skipping): the handle was centred meanwhile and the tool held
        still. The hand starts from the centre, the drift estimate forgets the held
        stretch (its commands were never applied: no drift to learn from it) and the
        stall window starts over (the tool was not pushed)."""
        self.hand_holds += 1
        self._hand_m = np.zeros(3)
        self._last_tick = tick
        self._forget_unpushed()

    def _forget_unpushed(self) -> None:
        """A stretch in which the hand did not push the tool: no drift to learn from it,
        and the stall window starts over."""
        self._prev_seen = None
        self._expected = []
        self._stall = []

    def decide(self, tick: int, observed: Observation | None) -> HandCommand:
        """The hand command from decision tick ``tick`` on, given what was seen
        ``reaction_delay_s`` earlier (None: nothing seen yet, the hand stays at rest)."""
        if self._last_tick is not None and tick - self._last_tick > self._hand_hold_ticks:
            self._after_hold(tick)
        gone = self.device_gone
        if gone:
            # As after a hold: the tool is not pushed, so no stall window and no drift
            # learnt; the person waits for the device, the hand at rest, the grip held.
            self.device_gone_decisions += 1
            self._forget_unpushed()
        if observed is not None and not self.done and not gone:
            self._update_drift(observed)
            self._update_phase(tick, observed)
        v = np.zeros(3)
        goal = np.zeros(3)
        buttons = Button.NONE
        if observed is not None and not self.done and self.phase >= 0:
            if not gone:
                v = self._wanted_velocity(observed)
                goal = limit_offset(
                    hand_offset_for_velocity(v, observed.view_yaw_rad, self.teleop),
                    self.operator_cfg.max_hand_offset_m,
                    self.haptic.workspace_half_m,
                )
            if self.scenario.phases[self.phase].gripper_closed:
                buttons = Button.GRIPPER_CLOSE
        hand_m = self._move_hand(tick, goal)
        yaw = observed.view_yaw_rad if observed is not None else 0.0
        self._remember(tick, hand_m, yaw)
        return HandCommand(
            target_p_m=hand_m,
            buttons=buttons,
            phase=self.phase,
            done=self.done,
            success=self.success,
            world_v_ref_m_s=v,
        )

    @property
    def target_m(self) -> np.ndarray:
        """The current phase's target point (world frame, m)."""
        return self._target_m.copy()


# --- The decision loop, on sim time --------------------------------------------------------

# TASK_DONE names a tick this far ahead of the arrival that ends the task: the plant
# (in lockstep, waiting at that arrival's tick at most) finishes the run there exactly.
TASK_DONE_AHEAD_TICKS = 100
# Lockstep: longest wait for an observation's samples before deciding with what is there (s).
LOCKSTEP_INPUT_WAIT_S = 1.0


class ScriptedOutputs(Protocol):
    """Where :class:`ScriptedLoop` sends what it decides (the service: its publishers)."""

    def hand(self, valid_from_tick: int, command: HandCommand) -> None:
        """A HAND_INPUT that applies from ``valid_from_tick``."""

    def event(self, event: Event, tick: int, step: int, value: float) -> None:
        """A RUN_EVENT decided at ``tick``; ``step`` is the tick it names (see Event)."""


class ScriptedLoop:
    """The scripted operator on plant ticks: which decisions a TOOL_POSE arrival triggers,
    what they publish, and the run boundaries. No bus and no thread of its own.

    The arrival of the TOOL_POSE of tick ``m`` (:meth:`on_arrival`, in arrival order)
    triggers one decision for every sample tick ``s`` of the operator's clock
    (:func:`teleop.core.ticks.is_sample_tick` at ``decision_rate_hz``) in ``(previous
    arrival, m]``, sent with ``valid_from_tick = s + lead_ticks`` (``lead_ticks = 1 /
    (rate timestep)``): exactly the records the haptic device waits for. A decision rate
    above the scene rate would need a record before the TOOL_POSE that triggers it exists,
    which deadlocks lockstep, so it is a config error.

    Lockstep determinism: a decision uses only tick-stamped samples, the newest at or before
    ``s - reaction_delay`` (:class:`ObservationBuffer`, filled by the caller). Before
    deciding it waits (event driven, at most ``LOCKSTEP_INPUT_WAIT_S``) until that
    observation is complete: the OBJECT_POSES of the observed tool tick and, once an HMD is
    known to be in the run (:meth:`hmd_seen`), the HEAD_POSE whose ``valid_from_tick``
    applies at the observed tick. Without an HMD the view yaw is ``hmd.head_yaw_rad``.

    A new run (a TOOL_POSE at tick 0, or :meth:`on_started` for the plant's STARTED
    event) resets the operator; a tick not newer than the last one is a plant re-send and
    is ignored.

    An operator whose first TOOL_POSE is past tick 0 joined a run under way (it was
    restarted): its first look takes the task up where the world is
    (:func:`resume_phase`), and until it has seen anything (one reaction delay) it sends
    no hand input: the haptic device holds the handle still with its predecessor's
    buttons meanwhile (``haptic.hand_input_stale_s``), where a guess would open the
    gripper. Lockstep decisions do not wait for observations older than its first pose.

    ``scene``: what the operator knows of the scene's fixed geometry (default: read from
    the config's scene file and ``scene.*`` placements, as the plant places them).
    """

    def __init__(
        self,
        config: Config,
        scenario: Scenario,
        outputs: ScriptedOutputs,
        *,
        lockstep: bool,
        scene: SceneKnowledge | None = None,
    ) -> None:
        # Across an emulated link (site.emulated_round_trip_ms) the robot's site's scene
        # comes its way back later: the operator sees it that much later, and its hand
        # takes the gain of the longer delay, as a person slows down to a late picture.
        _, back_ticks = config.link_delay_ticks()
        if back_ticks:
            seen_s = config.operator.reaction_delay_s + back_ticks * config.tick_s
            config = dataclasses.replace(
                config, operator=dataclasses.replace(config.operator, reaction_delay_s=seen_s)
            )
        self.tick_s = config.tick_s
        self.hand_schedule = hand_schedule(config)
        rate_hz = self.hand_schedule.rate_hz
        if rate_hz > config.plant.scene_rate_hz:
            raise ConfigError(
                f"operator.decision_rate_hz ({rate_hz:g}) above plant.scene_rate_hz "
                f"({config.plant.scene_rate_hz:g}): decisions are driven by TOOL_POSE arrivals"
            )
        self.lockstep = lockstep
        # Lockstep: how far the newest TOOL_POSE can be ahead of the last one decided while
        # the haptic device waits for this operator's hand inputs (a hand input applies
        # for a decision period from a decision period ahead, and poses come every scene
        # period), with a scene period to spare. A pose further ahead means the run went
        # on without this operator (a restart, or the device gave up waiting for it).
        scene_ticks = scene_schedule(config).gap_ticks
        self.lockstep_lag_ticks = 3 * self.hand_schedule.lead_ticks + 2 * scene_ticks
        # Realtime: poses that stopped coming for longer than the device keeps a hand
        # input (a link cut, a stalled plant) froze the view; see on_arrival.
        self.frozen_view_ticks = round(config.haptic.hand_input_stale_s / self.tick_s)
        self.delay_ticks = round(config.operator.reaction_delay_s / self.tick_s)
        self.head_schedule = head_schedule(config)
        self.scenario = scenario
        self.outputs = outputs
        self.operator = ScriptedOperator(
            scenario,
            config.operator,
            config.teleop,
            config.haptic,
            self.tick_s,
            scene=scene if scene is not None else SceneKnowledge.from_config(config),
        )
        self.buffer = ObservationBuffer(
            config.robot.object_bodies, self.delay_ticks, config.hmd.head_yaw_rad
        )
        self._hmd_present = threading.Event()  # set from any thread, read by the loop's
        self._last_tick: int | None = None  # newest TOOL_POSE tick handled in this run
        self._phase_reported = -1
        self._done_reported = False
        self.runs = 0
        self.decisions = 0
        self.late_observations = 0  # lockstep waits that timed out
        self.duplicate_poses = 0  # TOOL_POSE re-sends (same tick) ignored
        self._joined_tick: int | None = None  # first TOOL_POSE tick of a run joined late
        self.withheld_inputs = 0  # joined: decisions made before anything was seen
        self.skipped_decisions = 0  # realtime: sample ticks a late operator skipped
        self.frozen_views = 0  # realtime: poses that came after a frozen view
        self.phase_times: list[dict[str, Any]] = []

    def hmd_seen(self) -> None:
        """An HMD is in the run (its liveliness token or a HEAD_POSE): lockstep decisions
        wait for its head pose from now on."""
        self._hmd_present.set()

    def on_started(self) -> None:
        """The plant's STARTED event: a new run, unless this run's first pose came first."""
        if self._last_tick not in (None, 0):
            self._new_run()

    def _new_run(self) -> None:
        self.operator.reset()
        self._joined_tick = None
        self._last_tick = None
        self._phase_reported = -1
        self._done_reported = False
        self.phase_times = []
        self.runs += 1
        logger.info("new run: operator reset")

    @property
    def done_reported(self) -> bool:
        """Whether this run's TASK_DONE has gone out."""
        return self._done_reported

    def take_over(self, tick: int) -> None:
        """Take the hand over after tick ``tick`` (another robot's last decided pose, in
        a run of several robots driven in turn): the next arrival decides from the
        sample tick after ``tick`` on, this task starting at phase 0 then. What this
        operator decides on was observed meanwhile (its buffer is filled all along)."""
        self._last_tick = tick

    def left_behind(self, m: int) -> bool:
        """Whether the TOOL_POSE of tick ``m`` shows the run going on without this
        operator: realtime, always decide on the newest pose; lockstep, only once a pose
        is further ahead of the last one decided than a device waiting for this
        operator lets the plant go (``lockstep_lag_ticks``: never in a run the device
        waited through, so lockstep stays deterministic)."""
        if not self.lockstep:
            return True
        return self._last_tick is not None and m - self._last_tick > self.lockstep_lag_ticks

    def on_arrival(self, m: int, catch_up: bool = False) -> None:
        """The TOOL_POSE of tick ``m`` is in the buffer: decide every sample tick up to it.

        ``catch_up`` (a late operator whose caller skipped the poses queued before this
        one, see :meth:`left_behind`): decide only the newest sample tick, never a burst
        of decisions whose hand inputs would all be late (see
        ScriptedOperator._after_hold). The same in realtime after a frozen view (no pose
        for longer than ``frozen_view_ticks``: the link was cut, the plant stalled): a
        person who saw nothing new decided nothing meanwhile, and a burst over the frozen
        stretch would judge the tool's progress on a picture that did not move."""
        if m == 0 and self._last_tick != 0:
            self._new_run()
        elif self._last_tick is not None and m <= self._last_tick:
            self.duplicate_poses += 1  # a plant re-send of a state nobody answered yet
            return
        if self._last_tick is None:
            first = self.hand_schedule.last_sample(m)
            if m > 0 and self.operator.phase < 0 and not self.operator.done:
                self._joined_tick = m
                self.operator.joining = True
                logger.info("joined a run under way at tick %d (a restart)", m)
        elif catch_up or (not self.lockstep and m - self._last_tick > self.frozen_view_ticks):
            if not catch_up:
                self.frozen_views += 1
            first = max(self._last_tick + 1, self.hand_schedule.last_sample(m))
            self.skipped_decisions += sum(
                self.hand_schedule.is_sample(s) for s in range(self._last_tick + 1, first)
            )
        else:
            first = self._last_tick + 1
        self._last_tick = m
        for s in range(first, m + 1):
            if self.hand_schedule.is_sample(s):
                self._decide(s, m)

    def _decide(self, s: int, m: int) -> None:
        """One decision at sample tick ``s`` (triggered by the TOOL_POSE of tick ``m``)."""
        seen = s - self.delay_ticks
        unseen = self._joined_tick is not None and seen < self._joined_tick
        if self.lockstep and not unseen:
            head_from = None
            if self._hmd_present.is_set() and seen >= 0:
                head_from = self.head_schedule.valid_from_for(seen)
            if not self.buffer.wait_ready(s, head_from, LOCKSTEP_INPUT_WAIT_S):
                self.late_observations += 1
        command = self.operator.decide(s, self.buffer.observe(s))
        self.decisions += 1
        if unseen and command.phase < 0:
            self.withheld_inputs += 1  # nothing of this run seen yet: no hand to give
            return
        self.outputs.hand(s + self.hand_schedule.lead_ticks, command)
        if command.phase != self._phase_reported and command.phase >= 0:
            self._phase_reported = command.phase
            self.phase_times.append(
                {
                    "phase": command.phase,
                    "name": self.scenario.phases[command.phase].name,
                    "sim_time_s": s * self.tick_s,
                }
            )
            self.outputs.event(Event.PHASE, s, s, float(command.phase))
        for event, value in self.operator.events:
            self.outputs.event(event, s, s, value)
        self.operator.events.clear()
        if command.done and not self._done_reported:
            self._done_reported = True
            finish_tick = m + TASK_DONE_AHEAD_TICKS
            self.outputs.event(Event.TASK_DONE, s, finish_tick, float(command.success))
            logger.info(
                "task done at %.2f s: %s %s",
                s * self.tick_s,
                "success" if command.success else "gave up",
                self.operator.failure,
            )

    def summary(self) -> dict[str, Any]:
        """The task's outcome, phase times and decision counters (JSON-ready)."""
        op = self.operator
        duration_s = None
        if op.task_start_tick is not None and op.done_tick is not None:
            duration_s = (op.done_tick - op.task_start_tick) * self.tick_s
        return {
            "scenario": self.scenario.source,
            "phases": self.phase_times,
            "task_done": op.done,
            "success": op.success if op.done else None,
            "failure": op.failure,
            "routes": op.routes,
            "task_duration_s": duration_s,
            "gain_per_s": op.gain_per_s,
            "decisions": self.decisions,
            "late_observations": self.late_observations,
            "duplicate_poses": self.duplicate_poses,
            "runs": self.runs,
            "resumed": op.resumed,  # a restarted operator: where it took the task up
            "withheld_inputs": self.withheld_inputs,
            "skipped_decisions": self.skipped_decisions,
            "frozen_views": self.frozen_views,
            "hand_holds": op.hand_holds,
            "device_gone_decisions": op.device_gone_decisions,
        }


# --- Several robots, one hand ---------------------------------------------------------------


class PoseArrival(NamedTuple):
    """A TOOL_POSE of ``robot`` at plant tick ``tick``, sampled at ``sampled_ns``."""

    robot: int
    tick: int
    sampled_ns: int


class RunStarted(NamedTuple):
    """``robot``'s plant started a run (its STARTED event)."""

    robot: int


Arrival = PoseArrival | RunStarted


class ScriptedStation:
    """One scripted operator's hand over the robots of a run (``run.robots``), one task
    per robot, in turn: :class:`ScriptedLoop` ``loops[i]`` plays robot i's task (its
    outputs go out on robot i's keys). The hand drives robot 0 until its TASK_DONE is
    out, then the next robot's task starts where the last decision left off
    (:meth:`ScriptedLoop.take_over`). Every robot's scene is observed all along (the
    caller fills each loop's buffer); only the driven robot's poses trigger decisions.
    With one robot it is that robot's loop, as the service always was.
    """

    def __init__(self, loops: Sequence[ScriptedLoop]) -> None:
        self.loops = list(loops)
        self.active = 0  # the robot the hand drives

    @property
    def loop(self) -> ScriptedLoop:
        """The driven robot's loop."""
        return self.loops[self.active]

    def take(self, items: Sequence[Arrival], decided: Callable[[int], None] | None = None) -> None:
        """One batch of arrivals, in order: the driven robot's poses decided (``decided``
        gets each one's sample stamp), a new run started over on robot 0, the hand passed
        on once the driven robot's task is done.

        A late operator (realtime: poses queued behind a newer one; lockstep: a run that
        went on without it, :meth:`ScriptedLoop.left_behind`) decides on the newest pose
        only and skips the rest: it catches up by skipping, never by a burst of late hand
        inputs. Lockstep otherwise decides every one (the haptic device waits for each)."""
        loop = self.loop
        poses = [item for item in items if isinstance(item, PoseArrival)]
        driven = [pose for pose in poses if pose.robot == self.active]
        behind = bool(driven) and loop.left_behind(driven[-1].tick)
        catch_up = behind and (len(driven) > 1 or loop.lockstep)
        for i, item in enumerate(items):
            if isinstance(item, RunStarted):
                self.loops[item.robot].on_started()
                if item.robot == 0 and self.active:
                    self.active = 0  # a new run: robot 0's task first again
                    self.take(items[i + 1 :], decided)
                    return
                continue
            if item.robot != self.active:
                continue  # observed (buffered), not driven
            later = items[i + 1 :]
            if behind and any(isinstance(x, PoseArrival) and x.robot == item.robot for x in later):
                continue  # a newer pose is queued behind it
            if decided is not None:
                decided(item.sampled_ns)
            loop.on_arrival(item.tick, catch_up=catch_up)
            if loop.done_reported and self.active + 1 < len(self.loops):
                self.active += 1
                self.loop.take_over(item.tick)
                logger.info("tick %d: the hand moves on to robot %d", item.tick, self.active)
                self.take(later, decided)  # what came after, for the robot driven now
                return

    def summary(self, robot_ids: Sequence[str]) -> dict[str, Any]:
        """The task's outcome (:meth:`ScriptedLoop.summary`): with one robot its loop's;
        with several, one section per robot id under ``robots``."""
        if len(self.loops) == 1:
            return self.loops[0].summary()
        return {
            "robots": {rid: loop.summary() for rid, loop in zip(robot_ids, self.loops, strict=True)}
        }
