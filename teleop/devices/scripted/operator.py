"""The scripted operator: plays a task on the haptic handle, closing the loop on what it sees.

Pure and process-free: :class:`ScriptedOperator` decides the hand from what it observed;
:class:`teleop.devices.scripted.loop.ScriptedLoop` runs it on the plant's ticks (the whole
operator minus the bus, which ``services/operator.py`` feeds), so the closed loop and the
service's decisions can be simulated in a test.

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

Phases come from a scenario file (``deploy/scenarios/*.toml``,
:class:`teleop.devices.scripted.scenario.Scenario`). A target is an offset from the cube,
the bin (positions observed when the phase starts, then held: a lift target must not
follow the cube it lifts) or the tool's position at phase start. A phase is complete once
the observed tool stays within its tolerance for its dwell time; a phase timeout or the
task time limit ends the task with success False, and so does losing the held object in
a ``carrying`` phase.

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
import itertools
import logging
import math
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from teleop.bus.messages import Button, Event
from teleop.core.config import (
    HapticConfig,
    OperatorConfig,
    TeleopConfig,
)
from teleop.devices.scripted.routing import KeepOut, SceneKnowledge, plan_route, route_length_m
from teleop.devices.scripted.scenario import TOOL_ANCHOR, Phase, Scenario
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

# --- The controller's rate mapping, and its inverse ----------------------------------


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
