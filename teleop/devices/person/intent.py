"""A person at the controls, as pure code: what any human input device asks of the hand.

Every device a person drives the arm with (the terminal keyboard, a gamepad, a
SpaceMouse, the browser page) is read into one device-independent :class:`HandIntent`:
the tool speed asked for along the view frame's axes, as fractions of the top speed, and
the gripper and clutch held or not. :func:`hand_command` turns an intent into what the
scripted operator sends too (HAND_INPUT: where the hand pulls the emulated handle, and
the buttons), so the haptic device, the controller and the plant never know who drives.

Frames: the view frame is the device frame (teleop/control/teleop.py): x forward (away
from the operator, where the HMD looks), y left, z up.

Rate control maps the handle's offset from its centre to a tool velocity
(``teleop.rate_gain_per_s`` beyond ``teleop.deadband_m``): a fraction ``f`` of the top
speed is an offset of ``deadband + f (top - deadband)`` along the intent's direction,
``top`` the offset of ``teleop.max_tool_speed_m_s``, kept within the handle's free
workspace (``teleop.workspace_free_m``: beyond it the workspace spring pushes back).

:class:`KeyboardIntent` reads key presses (a terminal gives presses and their repeats,
never releases): a motion key moves along its axis for ``keyboard.hold_s`` after its last
press, so a held key (its repeats) moves on and a tap moves a step. Clock-injected: each
call takes the time.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from teleop.bus.messages import Button
from teleop.core.clock import NS_PER_S
from teleop.core.config import KeyboardConfig, TeleopConfig

AXES = ("x", "y", "z")  # view frame: forward, left, up


@dataclass(frozen=True)
class HandIntent:
    """What a person asks of the hand, whatever the device: the tool speed along the view
    frame's axes as fractions of the top speed (each in [-1, 1]; the vector's norm is
    clipped to 1), and the gripper and clutch held or not."""

    velocity_fraction: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gripper_closed: bool = False
    clutch: bool = False

    def __post_init__(self) -> None:
        if len(self.velocity_fraction) != 3 or not all(
            math.isfinite(v) and -1.0 <= v <= 1.0 for v in self.velocity_fraction
        ):
            raise ValueError(f"velocity_fraction: 3 finite values in [-1, 1], got "
                             f"{self.velocity_fraction!r}")  # fmt: skip

    @property
    def buttons(self) -> Button:
        """The HAND_INPUT button bits of this intent."""
        bits = Button.NONE
        if self.gripper_closed:
            bits |= Button.GRIPPER_CLOSE
        if self.clutch:
            bits |= Button.CLUTCH
        return bits

    @classmethod
    def at_rest(cls, buttons: Button) -> HandIntent:
        """No motion, the gripper and clutch as the HAND_INPUT bits ``buttons`` hold them
        (the inverse of :attr:`buttons`)."""
        return cls(
            gripper_closed=bool(buttons & Button.GRIPPER_CLOSE),
            clutch=bool(buttons & Button.CLUTCH),
        )

    @property
    def moving(self) -> bool:
        return any(v != 0.0 for v in self.velocity_fraction)


def top_offset_m(teleop: TeleopConfig) -> float:
    """The handle offset (m) that asks for the top tool speed, within the free workspace."""
    full_speed_m = teleop.deadband_m + teleop.max_tool_speed_m_s / teleop.rate_gain_per_s
    return min(full_speed_m, teleop.workspace_free_m)


def hand_command(intent: HandIntent, teleop: TeleopConfig) -> tuple[np.ndarray, Button]:
    """Where the hand pulls the handle (device frame, m from the workspace centre) and the
    buttons it holds, for ``intent``."""
    fraction = np.array(intent.velocity_fraction, dtype=np.float64)
    norm = float(np.linalg.norm(fraction))
    if norm == 0.0:
        return np.zeros(3), intent.buttons
    magnitude = min(norm, 1.0)
    top = top_offset_m(teleop)
    offset_m = teleop.deadband_m + magnitude * (top - teleop.deadband_m)
    return fraction / norm * offset_m, intent.buttons


# What a key does: move along an axis (+1 / -1), a speed step, a toggle, stop, quit, or
# switch robots.
@dataclass(frozen=True)
class KeyAction:
    kind: str  # "move", "faster", "slower", "gripper", "clutch", "stop", "quit", "help", "switch"
    axis: int = -1  # move: 0 x forward, 1 y left, 2 z up
    sign: float = 0.0  # move: +1 or -1


MOVE, FASTER, SLOWER, GRIPPER, CLUTCH, STOP, QUIT, HELP, SWITCH = (
    "move", "faster", "slower", "gripper", "clutch", "stop", "quit", "help", "switch"
)  # fmt: skip

# Key names: a printable character as itself; the terminal's special keys by these names
# (teleop.devices.terminal reads them from their escape sequences).
UP, DOWN, LEFT, RIGHT, PAGE_UP, PAGE_DOWN = "up", "down", "left", "right", "pgup", "pgdn"
TAB = "tab"

DEFAULT_KEYS: Mapping[str, KeyAction] = {
    "w": KeyAction(MOVE, 0, 1.0), UP: KeyAction(MOVE, 0, 1.0),
    "s": KeyAction(MOVE, 0, -1.0), DOWN: KeyAction(MOVE, 0, -1.0),
    "a": KeyAction(MOVE, 1, 1.0), LEFT: KeyAction(MOVE, 1, 1.0),
    "d": KeyAction(MOVE, 1, -1.0), RIGHT: KeyAction(MOVE, 1, -1.0),
    "r": KeyAction(MOVE, 2, 1.0), PAGE_UP: KeyAction(MOVE, 2, 1.0),
    "f": KeyAction(MOVE, 2, -1.0), PAGE_DOWN: KeyAction(MOVE, 2, -1.0),
    "+": KeyAction(FASTER), "=": KeyAction(FASTER), "-": KeyAction(SLOWER),
    "g": KeyAction(GRIPPER), "c": KeyAction(CLUTCH), " ": KeyAction(STOP),
    "q": KeyAction(QUIT), "?": KeyAction(HELP), "h": KeyAction(HELP),
    TAB: KeyAction(SWITCH),
}  # fmt: skip

# The help the terminal shows, one line per group of keys.
KEY_HELP = (
    "w/s or up/down: forward/back    a/d or left/right: left/right    r/f or PgUp/PgDn: up/down",
    "+/-: speed step    g: gripper close/open    c: clutch (move the handle, not the arm)",
    "space: stop    ?: this help    q: end the run",
)
# The robot switch's help, in a run of several robots.
SWITCH_HELP = "tab: drive the next robot (its gripper as you left it)"


@dataclass
class KeyboardIntent:
    """Key presses into a :class:`HandIntent` (clock-injected: every call takes ``now_ns``).

    A motion key sets its axis to its sign at the current speed step for ``hold_s`` after
    its press; a repeat of the key extends it, the opposite key takes the axis over, space
    stops every axis. ``speed_steps`` are fractions of the top speed. The hold runs on the
    person's clock, as a hand does: a lockstep run that lags takes the keys as they are
    when it catches up (a tap it lagged past is gone, as in any live view)."""

    config: KeyboardConfig
    keys: Mapping[str, KeyAction] = field(default_factory=lambda: dict(DEFAULT_KEYS))
    speed_index: int = -1  # into config.speed_steps; -1: the configured start step
    gripper_closed: bool = False
    clutch: bool = False
    quit_requested: bool = False
    show_help: bool = True
    presses: int = 0
    unknown_keys: int = 0

    def __post_init__(self) -> None:
        if self.speed_index < 0:
            self.speed_index = self.config.start_speed_step
        # Per axis: (sign, until_ns) of the newest motion key; sign 0: still.
        self._axes: list[tuple[float, int]] = [(0.0, 0)] * 3

    @property
    def speed_fraction(self) -> float:
        return self.config.speed_steps[self.speed_index]

    def press(self, key: str, now_ns: int) -> KeyAction | None:
        """One key press (or a repeat); the action it took (None: not a key of the map)."""
        action = self.keys.get(key)
        if action is None:
            self.unknown_keys += 1
            return None
        self.presses += 1
        if action.kind == MOVE:
            until_ns = now_ns + round(self.config.hold_s * NS_PER_S)
            self._axes[action.axis] = (action.sign, until_ns)
        elif action.kind == FASTER:
            self.speed_index = min(self.speed_index + 1, len(self.config.speed_steps) - 1)
        elif action.kind == SLOWER:
            self.speed_index = max(self.speed_index - 1, 0)
        elif action.kind == GRIPPER:
            self.gripper_closed = not self.gripper_closed
        elif action.kind == CLUTCH:
            self.clutch = not self.clutch
        elif action.kind == STOP:
            self._axes = [(0.0, 0)] * 3
        elif action.kind == QUIT:
            self.quit_requested = True
        elif action.kind == HELP:
            self.show_help = not self.show_help
        return action

    def take_robot(self, buttons: Button) -> None:
        """The hand moved to another robot (the robot switch): every axis stops (the
        handle comes to rest, which the haptic device waits for to switch), and the
        gripper and clutch are as the hand last left that robot (``buttons``)."""
        self._axes = [(0.0, 0)] * 3
        held = HandIntent.at_rest(buttons)
        self.gripper_closed, self.clutch = held.gripper_closed, held.clutch

    def intent(self, now_ns: int) -> HandIntent:
        """What the keys ask of the hand at ``now_ns``."""
        speed = self.speed_fraction
        fraction = tuple(sign * speed if now_ns < until else 0.0 for sign, until in self._axes)
        norm = math.sqrt(sum(v * v for v in fraction))
        if norm > 1.0:
            fraction = tuple(v / norm for v in fraction)
        return HandIntent(fraction, self.gripper_closed, self.clutch)  # type: ignore[arg-type]
