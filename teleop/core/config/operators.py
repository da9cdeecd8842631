"""Who drives the haptic handle: the scripted operator (``operator``) or a person through
the keyboard, a gamepad, a SpaceMouse or a web page (``keyboard``, ``gamepad``,
``spacemouse``, ``web``), and the checks the input devices share."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from teleop.core.config.base import DEPLOY_DIR, REPO_ROOT, require


@dataclass(frozen=True)
class OperatorConfig:
    """The scripted operator: what it does, how fast it reacts, how it moves its hand."""

    # Task file: a name in deploy/scenarios/, or a path.
    scenario_file: str = "grasp.toml"
    reaction_delay_s: float = 0.2
    decision_rate_hz: float = 100.0
    # The largest offset the hand gives the handle (m); the operator's gain follows from
    # reaction_delay_s (no overshoot for a delayed P loop, see teleop/devices/scripted/operator.py).
    max_hand_offset_m: float = 0.045

    def __post_init__(self) -> None:
        require(self.reaction_delay_s >= 0, "operator.reaction_delay_s >= 0")
        require(0 < self.decision_rate_hz <= 1000, "operator.decision_rate_hz in (0, 1000]")

    @property
    def scenario_path(self) -> Path:
        candidate = Path(self.scenario_file)
        if candidate.is_absolute():
            return candidate
        if (DEPLOY_DIR / "scenarios" / candidate).exists():
            return DEPLOY_DIR / "scenarios" / candidate
        return REPO_ROOT / candidate


# Who drives the emulated haptic handle (RunConfig.operator): the scripted operator, or a
# person through one of the human input devices (teleop/devices/person/intent.py).
SCRIPTED = "scripted"
OPERATORS = (SCRIPTED, "keyboard", "gamepad", "spacemouse", "web")
# The person's devices read in the launcher's terminal (the launcher runs them in the
# foreground); the others run under supervisord like every service.
TERMINAL_OPERATORS = ("keyboard",)
# The person's devices that show the operator's eye view (the web page): their runs have
# the eye view in lockstep too.
VIEWING_OPERATORS = ("web",)
# The person's devices read from Linux input (evdev, hidraw):
# teleop/devices/person/input_devices.py.
INPUT_DEVICE_OPERATORS = ("gamepad", "spacemouse")


@dataclass(frozen=True)
class KeyboardConfig:
    """A person at the terminal's keyboard (``--operator keyboard``,
    teleop/devices/person/intent.py): how long a key press moves and the speed steps."""

    # A motion key moves its axis this long after its last press (s): longer than the
    # terminal's key-repeat delay, so a held key moves on without a stutter.
    hold_s: float = 0.6
    # Speed steps, fractions of teleop.max_tool_speed_m_s (+ and - step through them).
    speed_steps: tuple[float, ...] = (0.1, 0.2, 0.4, 0.7, 1.0)
    start_speed_step: int = 2
    # The screen is redrawn this often (Hz).
    screen_rate_hz: float = 10.0

    def __post_init__(self) -> None:
        require(self.hold_s > 0, "keyboard.hold_s > 0")
        require(
            len(self.speed_steps) > 0 and all(0 < v <= 1 for v in self.speed_steps),
            "keyboard.speed_steps: fractions in (0, 1]",
        )
        require(
            0 <= self.start_speed_step < len(self.speed_steps),
            "keyboard.start_speed_step: an index into keyboard.speed_steps",
        )
        require(0 < self.screen_rate_hz <= 60, "keyboard.screen_rate_hz in (0, 60]")


# A human device's axis map entry: "<view axis>=<sign><device axis>", the view axis x
# (forward), y (left) or z (up), the device axis by its kernel name without the ABS_/REL_
# prefix (X, Y, Z, RX, RY, RZ, HAT0X, ...). Entries for one view axis add up.
_AXIS_MAP_ENTRY = re.compile(r"[xyz]=[+-]?[A-Z][A-Z0-9]*")
_DEVICE_AXIS_NAME = re.compile(r"[A-Z][A-Z0-9]*")
_BUTTON_NAME = re.compile(r"BTN_[A-Z0-9]+")  # a kernel button name, linux/input-event-codes.h
# How a button role acts: "toggle" flips on each press, "hold" is on while a button is held.
BUTTON_MODES = ("toggle", "hold")


def _check_human_device(section: str, axes: tuple[str, ...], dead_zone_fraction: float,
                        gain: float, gripper_buttons: tuple[str, ...],
                        clutch_buttons: tuple[str, ...], gripper_mode: str,
                        clutch_mode: str, switch_buttons: tuple[str, ...]) -> None:  # fmt: skip
    """The checks a gamepad's and a SpaceMouse's sections share (names checked against the
    kernel's tables when the device opens, teleop/devices/person/input_events.py)."""
    require(
        len(axes) > 0 and all(_AXIS_MAP_ENTRY.fullmatch(a) for a in axes),
        f'{section}.axes: entries like "x=-Y" (view axis x/y/z = sign, device axis name)',
    )
    require(0 <= dead_zone_fraction < 1, f"{section}.dead_zone_fraction in [0, 1)")
    require(gain > 0, f"{section}.gain > 0")
    require(len(gripper_buttons) > 0, f"{section}.gripper_buttons: at least one button")
    roles = {"gripper_buttons": gripper_buttons, "clutch_buttons": clutch_buttons,
             "switch_buttons": switch_buttons}  # fmt: skip
    for name, buttons in roles.items():
        require(
            all(_BUTTON_NAME.fullmatch(b) for b in buttons),
            f"{section}.{name}: kernel button names like BTN_SOUTH, BTN_0",
        )
    for name, buttons in roles.items():  # one role per button
        for other, others in roles.items():
            shared = sorted(set(buttons) & set(others)) if name < other else []
            require(not shared, f"{section}.{name} and {section}.{other} share {shared}")
    for name, mode in (("gripper_mode", gripper_mode), ("clutch_mode", clutch_mode)):
        require(mode in BUTTON_MODES, f"{section}.{name}: one of {', '.join(BUTTON_MODES)}")


@dataclass(frozen=True)
class GamepadConfig:
    """A person with a gamepad (``--operator gamepad``, teleop/devices/person/input_devices.py):
    which stick drives which view axis, the dead zone, the buttons and the rumble.

    Defaults fit the kernel's gamepad layout (xpad, hid-playstation, hid-nintendo): left
    stick forward/back and left/right (a stick pushed up or left reads negative), right
    stick up/down; the triggers are the alternative for z: ``axes = ["x=-Y", "y=-X",
    "z=+RZ", "z=-Z"]`` (right trigger up, left trigger down)."""

    # "auto": the first /dev/input/by-id/*-event-joystick, else the first event device with
    # a gamepad's sticks and buttons; or the path of its event device (/dev/input/eventN).
    device: str = "auto"
    axes: tuple[str, ...] = ("x=-Y", "y=-X", "z=-RY")
    # Axes at rest at their minimum (analogue triggers): read 0..1 from the minimum up;
    # every other axis reads -1..1 about the middle of its range.
    trigger_axes: tuple[str, ...] = ("Z", "RZ")
    # Per axis: deflections below this fraction of full scale read 0, and the rest is
    # rescaled so the output starts at 0 at its edge (the kernel's "flat", if larger, wins).
    dead_zone_fraction: float = 0.15
    # Velocity fraction per unit of deflection beyond the dead zone (1: full deflection is
    # the top speed, teleop.max_tool_speed_m_s).
    gain: float = 1.0
    # Any of these closes / opens the gripper (gripper_mode) and clutches (clutch_mode):
    # toggle, so a held object needs no held button; a clutch held only while pressed.
    gripper_buttons: tuple[str, ...] = ("BTN_SOUTH",)
    gripper_mode: str = "toggle"
    clutch_buttons: tuple[str, ...] = ("BTN_TL", "BTN_TR")
    clutch_mode: str = "hold"
    # A press of any of these drives the next robot (a run of several robots).
    switch_buttons: tuple[str, ...] = ("BTN_NORTH",)
    # Rumble (where the pad has it, FF_RUMBLE): the feedback force's magnitude as strength,
    # 0 below rumble_min_force_n, full at rumble_full_force_n (N).
    rumble: bool = True
    rumble_min_force_n: float = 0.5
    rumble_full_force_n: float = 8.0
    # Each strength plays this long (s), renewed at most every rumble_period_s while the
    # force lasts, so a stopped service stops the rumble within rumble_length_s.
    rumble_length_s: float = 0.2
    rumble_period_s: float = 0.05

    def __post_init__(self) -> None:
        _check_human_device("gamepad", self.axes, self.dead_zone_fraction, self.gain,
                            self.gripper_buttons, self.clutch_buttons, self.gripper_mode,
                            self.clutch_mode, self.switch_buttons)  # fmt: skip
        require(
            all(_DEVICE_AXIS_NAME.fullmatch(a) for a in self.trigger_axes),
            "gamepad.trigger_axes: axis names like Z, RZ",
        )
        require(self.device != "", 'gamepad.device: "auto" or a path')
        require(
            0 <= self.rumble_min_force_n < self.rumble_full_force_n,
            "gamepad: 0 <= rumble_min_force_n < rumble_full_force_n",
        )
        require(
            0 < self.rumble_period_s <= self.rumble_length_s <= 1,
            "gamepad: 0 < rumble_period_s <= rumble_length_s <= 1",
        )


@dataclass(frozen=True)
class SpaceMouseConfig:
    """A person with a 3Dconnexion SpaceMouse (``--operator spacemouse``,
    teleop/devices/person/input_devices.py): which of its six axes drive the view axes, its
    full scale, the dead zone and the buttons. Rotation is not mapped by default.

    The device's own axes (HID reports and the kernel's events alike): X right, Y towards
    the user, Z down, each positive; so pushing the cap forward, left and up reads -Y,
    -X and -Z, and the defaults map those to x, y and z."""

    # "auto": the first 3Dconnexion hidraw device, else its event device; or a path
    # (/dev/hidrawN or /dev/input/eventN).
    device: str = "auto"
    # Counts of a full deflection (the devices report about +-350).
    full_scale_counts: float = 350.0
    axes: tuple[str, ...] = ("x=-Y", "y=-X", "z=-Z")
    dead_zone_fraction: float = 0.1
    gain: float = 1.0
    # BTN_0 is the left (or menu) button, BTN_1 the right (or fit) button.
    gripper_buttons: tuple[str, ...] = ("BTN_0",)
    gripper_mode: str = "toggle"
    clutch_buttons: tuple[str, ...] = ("BTN_1",)
    clutch_mode: str = "hold"
    # A press of any of these drives the next robot (a run of several robots). None by
    # default: the two buttons of most SpaceMice are the gripper's and the clutch's.
    switch_buttons: tuple[str, ...] = ()
    # Through the kernel's relative axes (REL_X..REL_RZ) a return to 0 is never reported
    # (the kernel drops zero relative events): an axis not reported for this long (s)
    # reads 0. The devices report about every 8-16 ms while deflected.
    rel_hold_s: float = 0.1

    def __post_init__(self) -> None:
        _check_human_device("spacemouse", self.axes, self.dead_zone_fraction, self.gain,
                            self.gripper_buttons, self.clutch_buttons, self.gripper_mode,
                            self.clutch_mode, self.switch_buttons)  # fmt: skip
        require(self.device != "", 'spacemouse.device: "auto" or a path')
        require(self.full_scale_counts > 0, "spacemouse.full_scale_counts > 0")
        require(0 < self.rel_hold_s <= 1, "spacemouse.rel_hold_s in (0, 1]")


@dataclass(frozen=True)
class WebConfig:
    """A person at a web page (``--operator web``, services/web.py): the page's port on
    127.0.0.1, the run's token, and how often the page and the service talk.

    The launcher takes a free loopback port and writes a fresh token to a 0600 file
    under ``<run_dir>/auth`` (teleop/run/web_operator.py); only the file's path is on a
    command line, since other users can read every process's command line."""

    # HTTP port on 127.0.0.1 (the launcher takes a free one); 0: any free port (logged).
    port: int = 0
    # The file holding the run's token: every request must carry it (empty: refused).
    token_file: str = ""
    # The page's state stream (tick, tool, phase, force, ...) is sent this often (Hz).
    state_rate_hz: float = 20.0
    # While it asks for motion, the page repeats its input this often (Hz), and sends a
    # change at once.
    input_rate_hz: float = 20.0
    # This long (s) after the page's newest input, its motion falls back to none (the
    # buttons stay as they were: a held object is not dropped): a closed tab, a lost
    # link or a frozen browser stops the arm.
    input_expiry_s: float = 0.5
    # JPEG quality (1-100) of the eye-view frames the page shows.
    jpeg_quality: int = 80

    def __post_init__(self) -> None:
        require(0 <= self.port <= 65535, "web.port in [0, 65535]")
        require(0 < self.state_rate_hz <= 60, "web.state_rate_hz in (0, 60]")
        require(0 < self.input_rate_hz <= 100, "web.input_rate_hz in (0, 100]")
        require(
            2 / self.input_rate_hz <= self.input_expiry_s <= 5,
            "web.input_expiry_s in [2 / web.input_rate_hz, 5]: two of the page's inputs fit in it",
        )
        require(1 <= self.jpeg_quality <= 100, "web.jpeg_quality in [1, 100]")
