"""Linux input, decoded as pure code: a gamepad's and a SpaceMouse's events into a HandIntent.

Two byte formats come in, both stable kernel ABI, so the standard library's ``struct``
reads them and no input library is needed:

* evdev (``/dev/input/eventN``): a stream of ``struct input_event`` (linux/input.h; on
  64-bit Linux ``struct timeval`` as two longs, ``__u16 type``, ``__u16 code``,
  ``__s32 value``: 24 bytes). A device's state changes are grouped into frames closed
  by ``EV_SYN/SYN_REPORT``; a frame is applied whole, as the kernel means it. After
  ``SYN_DROPPED`` (the kernel's buffer overflowed) everything up to and including the
  next ``SYN_REPORT`` is discarded and the state is read back from the device
  (:class:`EventFramer`).
* hidraw (``/dev/hidrawN``) for a SpaceMouse: one HID input report per read. Report 1:
  translation X, Y, Z as little-endian int16 (7 bytes), or on newer models all six axes
  (13 bytes); report 2: rotation RX, RY, RZ; report 3: the buttons as a bitmask, bit i
  the button the kernel calls BTN_0 + i (:func:`decode_spacemouse_report`).

Absolute axes are normalised by their ``struct input_absinfo`` range (the EVIOCGABS
ioctl on a device; given directly in tests): -1..1 about the middle of the range, or 0..1
from the minimum for an axis at rest there (a trigger). A SpaceMouse's axes are counts
over ``spacemouse.full_scale_counts`` whatever its absinfo says (the kernel passes the
device's logical range through, and models report it differently).

From device axes to a :class:`HandIntent`: an axis map (config ``axes``: ``"x=-Y"``
drives view axis x by minus device axis Y; entries for one view axis add up), a dead zone
per device axis (a fraction of full scale; beyond it the output is rescaled to start at
0), a gain, the velocity's norm clipped to 1, and button roles for the gripper and the
clutch (toggle or hold, :class:`ToggleRole` / :class:`HoldRole`).

A device starts disarmed: it asks for no motion until all its mapped axes have been seen
inside their dead zones, so a stick held, or a trigger mistaken for a stick, at start
does not move the arm (:attr:`IntentMapper.armed`).

Gamepad rumble: ``struct ff_effect`` (linux/input.h) packed by :func:`pack_rumble_effect`
for the EVIOCSFF ioctl, played by writing an ``EV_FF`` event; :class:`RumbleSchedule`
decides when a new strength is uploaded. The ioctl numbers are computed here as the
kernel's ``_IOC`` macro does (asm-generic/ioctl.h).

Device names and codes are linux/input-event-codes.h's.
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

from teleop.bus.messages import Button
from teleop.core.clock import NS_PER_S
from teleop.core.config import ConfigError, GamepadConfig, SpaceMouseConfig
from teleop.devices.person.intent import AXES, HandIntent

# Event types and the codes used here (linux/input-event-codes.h).
EV_SYN, EV_KEY, EV_REL, EV_ABS, EV_FF = 0x00, 0x01, 0x02, 0x03, 0x15
SYN_REPORT, SYN_DROPPED = 0, 3
ABS_X, ABS_Y, ABS_Z, ABS_RX, ABS_RY, ABS_RZ = 0x00, 0x01, 0x02, 0x03, 0x04, 0x05
ABS_HAT0X, ABS_HAT0Y = 0x10, 0x11
REL_X, REL_Y, REL_Z, REL_RX, REL_RY, REL_RZ = 0x00, 0x01, 0x02, 0x03, 0x04, 0x05
BTN_0, BTN_1 = 0x100, 0x101
BTN_TRIGGER = 0x120  # first button of a joystick
BTN_SOUTH, BTN_EAST, BTN_NORTH, BTN_WEST = 0x130, 0x131, 0x133, 0x134
BTN_TL, BTN_TR, BTN_TL2, BTN_TR2 = 0x136, 0x137, 0x138, 0x139
KEY_MAX = 0x2FF
ABS_MAX = 0x3F
FF_RUMBLE = 0x50
FF_MAX = 0x7F

# Absolute axes by name, without the ABS_ prefix (the config's axis names).
ABS_NAMES: Mapping[str, int] = {
    "X": 0x00, "Y": 0x01, "Z": 0x02, "RX": 0x03, "RY": 0x04, "RZ": 0x05,
    "THROTTLE": 0x06, "RUDDER": 0x07, "WHEEL": 0x08, "GAS": 0x09, "BRAKE": 0x0A,
    "HAT0X": 0x10, "HAT0Y": 0x11, "HAT1X": 0x12, "HAT1Y": 0x13,
    "HAT2X": 0x14, "HAT2Y": 0x15, "HAT3X": 0x16, "HAT3Y": 0x17,
}  # fmt: skip
# A SpaceMouse's six axes: the same numbers as REL_X..REL_RZ and ABS_X..ABS_RZ, and the
# order of the values in its HID reports.
SPACEMOUSE_AXIS_NAMES: Mapping[str, int] = {
    "X": 0, "Y": 1, "Z": 2, "RX": 3, "RY": 4, "RZ": 5,
}  # fmt: skip
SPACEMOUSE_AXES = 6
TRANSLATION_AXES, ROTATION_AXES = (0, 1, 2), (3, 4, 5)

# Buttons by their kernel names (aliases as the header has them).
BUTTON_NAMES: Mapping[str, int] = {
    **{f"BTN_{i}": BTN_0 + i for i in range(10)},
    "BTN_LEFT": 0x110, "BTN_RIGHT": 0x111, "BTN_MIDDLE": 0x112, "BTN_SIDE": 0x113,
    "BTN_EXTRA": 0x114, "BTN_FORWARD": 0x115, "BTN_BACK": 0x116, "BTN_TASK": 0x117,
    "BTN_TRIGGER": 0x120, "BTN_THUMB": 0x121, "BTN_THUMB2": 0x122, "BTN_TOP": 0x123,
    "BTN_TOP2": 0x124, "BTN_PINKIE": 0x125, "BTN_BASE": 0x126, "BTN_BASE2": 0x127,
    "BTN_BASE3": 0x128, "BTN_BASE4": 0x129, "BTN_BASE5": 0x12A, "BTN_BASE6": 0x12B,
    "BTN_SOUTH": 0x130, "BTN_A": 0x130, "BTN_EAST": 0x131, "BTN_B": 0x131, "BTN_C": 0x132,
    "BTN_NORTH": 0x133, "BTN_X": 0x133, "BTN_WEST": 0x134, "BTN_Y": 0x134, "BTN_Z": 0x135,
    "BTN_TL": 0x136, "BTN_TR": 0x137, "BTN_TL2": 0x138, "BTN_TR2": 0x139,
    "BTN_SELECT": 0x13A, "BTN_START": 0x13B, "BTN_MODE": 0x13C,
    "BTN_THUMBL": 0x13D, "BTN_THUMBR": 0x13E,
}  # fmt: skip

# struct input_event: struct timeval (two native longs), __u16 type, __u16 code, __s32 value.
INPUT_EVENT = struct.Struct("@llHHi")
# struct input_absinfo: value, minimum, maximum, fuzz, flat, resolution (__s32 each).
INPUT_ABSINFO = struct.Struct("@6i")

# struct ff_effect: type, id, direction, trigger {button, interval}, replay {length, delay},
# then a union aligned as a pointer; its largest member (ff_periodic_effect) is 24 bytes
# and a pointer. The rumble member is its first 4 bytes: strong, weak magnitude.
_POINTER_BYTES = struct.calcsize("P")
_FF_HEADER_BYTES = 14
_FF_UNION_OFFSET = -(-_FF_HEADER_BYTES // _POINTER_BYTES) * _POINTER_BYTES
_FF_UNION_BYTES = 24 + _POINTER_BYTES
FF_EFFECT = struct.Struct(f"=HhHHHHH{_FF_UNION_OFFSET - _FF_HEADER_BYTES}xHH{_FF_UNION_BYTES - 4}x")
FF_ID_NEW = -1  # an ff_effect id of -1 asks EVIOCSFF for a new effect
FF_MAGNITUDE_MAX = 0xFFFF  # a rumble motor's full strength

# ioctl numbers, as asm-generic/ioctl.h's _IOC builds them.
_IOC_WRITE, _IOC_READ = 1, 2
_IOC_NRSHIFT, _IOC_TYPESHIFT, _IOC_SIZESHIFT, _IOC_DIRSHIFT = 0, 8, 16, 30


def _ioc(direction: int, kind: str, number: int, size: int) -> int:
    return (
        (direction << _IOC_DIRSHIFT)
        | (ord(kind) << _IOC_TYPESHIFT)
        | (number << _IOC_NRSHIFT)
        | (size << _IOC_SIZESHIFT)
    )


def eviocgbit(event_type: int, length: int) -> int:
    """EVIOCGBIT(ev, len): the bitmap of the codes of ``event_type`` a device has (0: types)."""
    return _ioc(_IOC_READ, "E", 0x20 + event_type, length)


def eviocgabs(code: int) -> int:
    """EVIOCGABS(abs): an absolute axis's ``struct input_absinfo``."""
    return _ioc(_IOC_READ, "E", 0x40 + code, INPUT_ABSINFO.size)


def eviocgkey(length: int) -> int:
    """EVIOCGKEY(len): the bitmap of the keys and buttons held now."""
    return _ioc(_IOC_READ, "E", 0x18, length)


def eviocgname(length: int) -> int:
    """EVIOCGNAME(len): the device's name."""
    return _ioc(_IOC_READ, "E", 0x06, length)


EVIOCSFF = _ioc(_IOC_WRITE, "E", 0x80, FF_EFFECT.size)
EVIOCRMFF = _ioc(_IOC_WRITE, "E", 0x81, struct.calcsize("i"))


class InputEvent(NamedTuple):
    """One ``struct input_event``: the kernel's timestamp (s, us) and type, code, value."""

    sec: int
    usec: int
    type: int
    code: int
    value: int


def pack_event(event_type: int, code: int, value: int, sec: int = 0, usec: int = 0) -> bytes:
    """One ``struct input_event`` as the kernel lays it out (and as a write to evdev takes)."""
    return INPUT_EVENT.pack(sec, usec, event_type, code, value)


def decode_events(data: bytes) -> list[InputEvent]:
    """Whole ``struct input_event`` records of ``data`` (its length a multiple of 24)."""
    if len(data) % INPUT_EVENT.size:
        raise ValueError(f"{len(data)} bytes is not a whole number of input events")
    return [InputEvent(*fields) for fields in INPUT_EVENT.iter_unpack(data)]


class EventFramer:
    """An evdev byte stream into frames: the events of one device report, closed by
    SYN_REPORT, in order. Bytes of an event split across reads wait for the rest.

    After SYN_DROPPED the events up to and including the next SYN_REPORT are discarded
    (they describe a state with changes missing) and :attr:`resync_needed` is set: the
    reader reads the device's state back (EVIOCGABS, EVIOCGKEY) and clears it."""

    def __init__(self) -> None:
        self._partial = b""
        self._pending: list[InputEvent] = []
        self._discarding = False
        self.resync_needed = False
        self.dropped = 0  # SYN_DROPPED seen

    def feed(self, data: bytes) -> list[list[InputEvent]]:
        """The frames completed by ``data``."""
        data = self._partial + data
        whole = len(data) - len(data) % INPUT_EVENT.size
        self._partial = data[whole:]
        frames: list[list[InputEvent]] = []
        for event in decode_events(data[:whole]):
            if event.type == EV_SYN and event.code == SYN_DROPPED:
                self._pending = []
                self._discarding = True
                self.dropped += 1
            elif event.type == EV_SYN and event.code == SYN_REPORT:
                if self._discarding:
                    self._discarding = False
                    self.resync_needed = True
                elif self._pending:
                    frames.append(self._pending)
                self._pending = []
            elif not self._discarding:
                self._pending.append(event)
        return frames


@dataclass(frozen=True)
class AbsInfo:
    """An absolute axis's ``struct input_absinfo``: its value and range, in device counts."""

    value: int
    minimum: int
    maximum: int
    fuzz: int = 0
    flat: int = 0
    resolution: int = 0

    @classmethod
    def unpack(cls, data: bytes) -> AbsInfo:
        return cls(*INPUT_ABSINFO.unpack(data))

    def pack(self) -> bytes:
        return INPUT_ABSINFO.pack(self.value, self.minimum, self.maximum, self.fuzz, self.flat,
                                  self.resolution)  # fmt: skip


def abs_fraction(value: int, info: AbsInfo, one_sided: bool) -> float:
    """``value`` (counts) as a fraction of the axis's range: -1..1 about its middle, or
    0..1 from its minimum for a ``one_sided`` axis (a trigger); clipped (the kernel does
    not clip to the range)."""
    span = info.maximum - info.minimum
    if span <= 0:
        return 0.0
    if one_sided:
        return min(max((value - info.minimum) / span, 0.0), 1.0)
    centre = (info.maximum + info.minimum) / 2.0
    return min(max((value - centre) / (span / 2.0), -1.0), 1.0)


def flat_fraction(info: AbsInfo, one_sided: bool) -> float:
    """The kernel's ``flat`` (the deflection its joystick interface reports as 0) as a
    fraction of the same full scale :func:`abs_fraction` uses."""
    span = info.maximum - info.minimum
    if span <= 0:
        return 0.0
    return min(max(info.flat, 0) / (span if one_sided else span / 2.0), 1.0)


def apply_dead_zone(fraction: float, dead_zone_fraction: float) -> float:
    """``fraction`` (-1..1) with ``|fraction| <= dead_zone_fraction`` read as 0 and the rest
    rescaled so the output starts at 0 at the dead zone's edge and reaches 1 at full scale."""
    magnitude = abs(fraction)
    if magnitude <= dead_zone_fraction:
        return 0.0
    scaled = min((magnitude - dead_zone_fraction) / (1.0 - dead_zone_fraction), 1.0)
    return math.copysign(scaled, fraction)


class AxisSource(NamedTuple):
    """One axis map entry: device axis ``code`` drives view axis ``view_axis`` (0 x forward,
    1 y left, 2 z up) with ``sign``."""

    view_axis: int
    code: int
    sign: float


_ENTRY = re.compile(r"([xyz])=([+-]?)([A-Z][A-Z0-9]*)")


def parse_axis_map(
    entries: Sequence[str], names: Mapping[str, int], key: str
) -> tuple[AxisSource, ...]:
    """Config axis map entries (``"x=-Y"``) as :class:`AxisSource`; an unknown axis name is
    a ConfigError naming ``key`` and the names there are."""
    sources = []
    for entry in entries:
        match = _ENTRY.fullmatch(entry)
        if match is None or match.group(3) not in names:
            raise ConfigError(
                f"{key}: {entry!r} is not <x|y|z>=<+|->axis with axis one of {', '.join(names)}"
            )
        view, sign, name = match.groups()
        sources.append(AxisSource(AXES.index(view), names[name], -1.0 if sign == "-" else 1.0))
    return tuple(sources)


def button_codes(names: Iterable[str], key: str) -> frozenset[int]:
    """Kernel button names as codes; an unknown name is a ConfigError naming ``key``."""
    codes = set()
    for name in names:
        if name not in BUTTON_NAMES:
            raise ConfigError(f"{key}: unknown button {name!r} (kernel names: BTN_SOUTH, ...)")
        codes.add(BUTTON_NAMES[name])
    return frozenset(codes)


class HoldRole:
    """A button role on while any of its buttons is held (the clutch by default)."""

    def __init__(self, codes: frozenset[int]) -> None:
        self.codes = codes
        self.on = False

    def update(self, held_before: frozenset[int], held_now: frozenset[int]) -> None:
        self.on = bool(self.codes & held_now)


class ToggleRole:
    """A button role that flips at each press of one of its buttons (the gripper by
    default: a held object needs no held button)."""

    def __init__(self, codes: frozenset[int]) -> None:
        self.codes = codes
        self.on = False

    def update(self, held_before: frozenset[int], held_now: frozenset[int]) -> None:
        if self.codes & (held_now - held_before):
            self.on = not self.on


ButtonRole = HoldRole | ToggleRole
_ROLES = {"hold": HoldRole, "toggle": ToggleRole}


def button_role(mode: str, codes: frozenset[int]) -> ButtonRole:
    """The role object for a config mode ("toggle" or "hold")."""
    return _ROLES[mode](codes)


class IntentMapper:
    """Device axis fractions and held buttons into a :class:`HandIntent`.

    Each source's fraction (-1..1, or 0..1) goes through its dead zone, times its sign and
    the gain, added per view axis, each clipped to [-1, 1] and the vector's norm to 1.
    Disarmed until every mapped axis has read 0 after its dead zone."""

    def __init__(
        self,
        sources: Sequence[AxisSource],
        gain: float,
        gripper: ButtonRole,
        clutch: ButtonRole,
        switch_codes: frozenset[int] = frozenset(),
    ) -> None:
        self.sources = tuple(sources)
        self.gain = gain
        self.gripper = gripper
        self.clutch = clutch
        self.switch_codes = switch_codes
        self.switch_presses = 0  # presses of a robot-switch button so far
        self.armed = False
        self._held: frozenset[int] = frozenset()

    @property
    def held(self) -> frozenset[int]:
        return self._held

    def buttons(self, held_now: frozenset[int]) -> None:
        """The buttons held after a frame; press edges against the previous frame's."""
        for role in (self.gripper, self.clutch):
            role.update(self._held, held_now)
        if self.switch_codes & (held_now - self._held):
            self.switch_presses += 1
        self._held = held_now

    def take_robot(self, buttons: Button) -> None:
        """The hand moved to another robot: the gripper (and a toggled clutch) as the
        hand last left that robot; a held clutch follows the buttons held."""
        held = HandIntent.at_rest(buttons)
        self.gripper.on = held.gripper_closed
        if isinstance(self.clutch, ToggleRole):
            self.clutch.on = held.clutch

    def intent(self, fractions: Mapping[int, float], dead_zones: Mapping[int, float]) -> HandIntent:
        """What the device asks for, ``fractions`` per device axis code (absent: 0) after
        ``dead_zones`` per code (fractions of full scale)."""
        velocity = [0.0, 0.0, 0.0]
        at_rest = True
        for view_axis, code, sign in self.sources:
            deflection = apply_dead_zone(fractions.get(code, 0.0), dead_zones.get(code, 0.0))
            velocity[view_axis] += sign * self.gain * deflection
            at_rest = at_rest and deflection == 0.0
        self.armed = self.armed or at_rest
        if not self.armed:
            velocity = [0.0, 0.0, 0.0]
        velocity = [min(max(v, -1.0), 1.0) for v in velocity]
        norm = math.sqrt(sum(v * v for v in velocity))
        if norm > 1.0:
            velocity = [v / norm for v in velocity]
        return HandIntent((velocity[0], velocity[1], velocity[2]), self.gripper.on, self.clutch.on)


def _mapper(config: GamepadConfig | SpaceMouseConfig, section: str,
            axis_names: Mapping[str, int]) -> IntentMapper:  # fmt: skip
    return IntentMapper(
        parse_axis_map(config.axes, axis_names, f"{section}.axes"),
        config.gain,
        button_role(config.gripper_mode,
                    button_codes(config.gripper_buttons, f"{section}.gripper_buttons")),
        button_role(config.clutch_mode,
                    button_codes(config.clutch_buttons, f"{section}.clutch_buttons")),
        button_codes(config.switch_buttons, f"{section}.switch_buttons"),
    )  # fmt: skip


class GamepadState:
    """A gamepad's evdev state, frame by frame, and the intent it asks for.

    ``absinfo``: per absolute axis code the device's range (EVIOCGABS at open); its value
    is the axis's position at open. Axes named in ``gamepad.trigger_axes`` read 0..1."""

    def __init__(self, config: GamepadConfig, absinfo: Mapping[int, AbsInfo]) -> None:
        self.mapper = _mapper(config, "gamepad", ABS_NAMES)
        triggers = parse_axis_map([f"x={name}" for name in config.trigger_axes], ABS_NAMES,
                                  "gamepad.trigger_axes")  # fmt: skip
        self._one_sided = frozenset(source.code for source in triggers)
        self.absinfo = dict(absinfo)
        self._counts = {code: info.value for code, info in self.absinfo.items()}
        self._dead_zones = {
            code: max(config.dead_zone_fraction, flat_fraction(info, code in self._one_sided))
            for code, info in self.absinfo.items()
        }
        self.frames = 0

    @property
    def missing_axes(self) -> tuple[int, ...]:
        """Mapped axis codes the device does not have (they read 0)."""
        return tuple(s.code for s in self.mapper.sources if s.code not in self.absinfo)

    def apply(self, frame: Sequence[InputEvent]) -> None:
        """One frame of events (between SYN_REPORTs)."""
        held = set(self.mapper.held)
        for event in frame:
            if event.type == EV_ABS and event.code in self._counts:
                self._counts[event.code] = event.value
            elif event.type == EV_KEY:
                if event.value:  # 1 press, 2 autorepeat
                    held.add(event.code)
                else:
                    held.discard(event.code)
        self.mapper.buttons(frozenset(held))
        self.frames += 1

    def resync(self, abs_counts: Mapping[int, int], held: frozenset[int]) -> None:
        """The device's state read back after SYN_DROPPED (EVIOCGABS values, EVIOCGKEY)."""
        for code, value in abs_counts.items():
            if code in self._counts:
                self._counts[code] = value
        self.mapper.buttons(held)

    def fractions(self) -> dict[int, float]:
        return {
            code: abs_fraction(value, self.absinfo[code], code in self._one_sided)
            for code, value in self._counts.items()
        }

    def intent(self) -> HandIntent:
        return self.mapper.intent(self.fractions(), self._dead_zones)


@dataclass(frozen=True)
class SpaceMouseReport:
    """One decoded SpaceMouse HID report: what it carries (None: not in this report).
    Axes in counts, the device's frame (X right, Y towards the user, Z down)."""

    translation: tuple[int, int, int] | None = None
    rotation: tuple[int, int, int] | None = None
    buttons: int | None = None  # bit i: button BTN_0 + i held


REPORT_TRANSLATION, REPORT_ROTATION, REPORT_BUTTONS = 1, 2, 3
_AXIS_TRIPLE = struct.Struct("<3h")
_REPORT_ID_BYTES = 1
TRANSLATION_REPORT_BYTES = _REPORT_ID_BYTES + _AXIS_TRIPLE.size  # 7
SIX_AXIS_REPORT_BYTES = _REPORT_ID_BYTES + 2 * _AXIS_TRIPLE.size  # 13


def decode_spacemouse_report(report: bytes) -> SpaceMouseReport | None:
    """A hidraw read (report id first) as a :class:`SpaceMouseReport`; None for a report
    of another kind (battery, LEDs) or too short to hold what its id says."""
    if not report:
        return None
    report_id = report[0]
    if report_id == REPORT_TRANSLATION and len(report) >= TRANSLATION_REPORT_BYTES:
        translation = _AXIS_TRIPLE.unpack_from(report, _REPORT_ID_BYTES)
        rotation = None
        if len(report) >= SIX_AXIS_REPORT_BYTES:
            rotation = _AXIS_TRIPLE.unpack_from(report, TRANSLATION_REPORT_BYTES)
        return SpaceMouseReport(translation=translation, rotation=rotation)
    if report_id == REPORT_ROTATION and len(report) >= TRANSLATION_REPORT_BYTES:
        return SpaceMouseReport(rotation=_AXIS_TRIPLE.unpack_from(report, _REPORT_ID_BYTES))
    if report_id == REPORT_BUTTONS and len(report) > _REPORT_ID_BYTES:
        return SpaceMouseReport(buttons=int.from_bytes(report[_REPORT_ID_BYTES:], "little"))
    return None


def buttons_from_mask(mask: int) -> frozenset[int]:
    """A report-3 bitmask as the kernel's button codes (bit i: BTN_0 + i)."""
    return frozenset(BTN_0 + bit for bit in range(mask.bit_length()) if mask >> bit & 1)


# An axis reported through an absolute event or a HID report never goes stale.
_NEVER_NS = -1


class SpaceMouseState:
    """A SpaceMouse's six axes and buttons, from evdev frames or hidraw reports, and the
    intent they ask for (clock-injected: each call takes ``now_ns``, monotonic).

    Relative axes (REL_X..REL_RZ): the kernel drops zero relative events, so a frame with
    some of X/Y/Z (or RX/RY/RZ) sets the others of the group to 0 (one HID report holds
    the group), and an axis not reported for ``spacemouse.rel_hold_s`` reads 0 (a return
    to rest can leave nothing to report). Absolute axes and hidraw reports carry zeros."""

    def __init__(self, config: SpaceMouseConfig) -> None:
        self.config = config
        self.mapper = _mapper(config, "spacemouse", SPACEMOUSE_AXIS_NAMES)
        self._counts = [0] * SPACEMOUSE_AXES
        self._stale_ns = [_NEVER_NS] * SPACEMOUSE_AXES  # relative axes: when they read 0
        self._hold_ns = round(config.rel_hold_s * NS_PER_S)
        self._dead_zones = dict.fromkeys(range(SPACEMOUSE_AXES), config.dead_zone_fraction)
        self.reports = 0
        self.ignored_reports = 0

    def apply_frame(self, frame: Sequence[InputEvent], now_ns: int) -> None:
        """One evdev frame (between SYN_REPORTs), applied at ``now_ns``."""
        held = set(self.mapper.held)
        relative: dict[int, int] = {}
        for event in frame:
            if event.type == EV_REL and event.code < SPACEMOUSE_AXES:
                relative[event.code] = event.value
            elif event.type == EV_ABS and event.code < SPACEMOUSE_AXES:
                self._counts[event.code] = event.value
                self._stale_ns[event.code] = _NEVER_NS
            elif event.type == EV_KEY:
                if event.value:
                    held.add(event.code)
                else:
                    held.discard(event.code)
        for group in (TRANSLATION_AXES, ROTATION_AXES):
            if any(axis in relative for axis in group):
                for axis in group:
                    self._counts[axis] = relative.get(axis, 0)
                    self._stale_ns[axis] = now_ns + self._hold_ns
        self.mapper.buttons(frozenset(held))
        self.reports += 1

    def apply_report(self, report: bytes, now_ns: int) -> None:
        """One hidraw report (report id first)."""
        decoded = decode_spacemouse_report(report)
        if decoded is None:
            self.ignored_reports += 1
            return
        for values, group in ((decoded.translation, TRANSLATION_AXES),
                              (decoded.rotation, ROTATION_AXES)):  # fmt: skip
            if values is not None:
                for axis, value in zip(group, values, strict=True):
                    self._counts[axis] = value
                    self._stale_ns[axis] = _NEVER_NS
        if decoded.buttons is not None:
            self.mapper.buttons(buttons_from_mask(decoded.buttons))
        self.reports += 1

    def release_axes(self) -> None:
        """Every axis to 0 (after SYN_DROPPED: the missed frames' values are unknown)."""
        self._counts = [0] * SPACEMOUSE_AXES

    def fractions(self, now_ns: int) -> dict[int, float]:
        full = self.config.full_scale_counts
        return {
            axis: 0.0
            if _NEVER_NS < self._stale_ns[axis] <= now_ns
            else min(max(self._counts[axis] / full, -1.0), 1.0)
            for axis in range(SPACEMOUSE_AXES)
        }

    def intent(self, now_ns: int) -> HandIntent:
        return self.mapper.intent(self.fractions(now_ns), self._dead_zones)


def pack_rumble_effect(
    effect_id: int, strong_magnitude: int, weak_magnitude: int, length_ms: int
) -> bytes:
    """A ``struct ff_effect`` of type FF_RUMBLE for EVIOCSFF: ``effect_id`` -1 uploads a new
    effect (the kernel writes its id back), an id of an uploaded one updates it; the two
    motors' magnitudes 0..0xFFFF; played for ``length_ms`` once started, no delay."""
    for name, value in (("strong_magnitude", strong_magnitude), ("weak_magnitude", weak_magnitude)):
        if not 0 <= value <= FF_MAGNITUDE_MAX:
            raise ValueError(f"{name}: 0..{FF_MAGNITUDE_MAX}, got {value}")
    return FF_EFFECT.pack(FF_RUMBLE, effect_id, 0, 0, 0, length_ms, 0, strong_magnitude,
                          weak_magnitude)  # fmt: skip


def effect_id_of(effect: bytes) -> int:
    """The id field of a packed ``struct ff_effect`` (what EVIOCSFF wrote back)."""
    return FF_EFFECT.unpack(effect)[1]


def rumble_magnitude(force_n: float, min_force_n: float, full_force_n: float) -> int:
    """A feedback force's magnitude (N) as a rumble strength 0..0xFFFF: 0 below
    ``min_force_n``, rising linearly to full at ``full_force_n``."""
    if not math.isfinite(force_n) or force_n < min_force_n or force_n <= 0:
        return 0
    fraction = min(force_n / full_force_n, 1.0)
    return max(1, round(fraction * FF_MAGNITUDE_MAX))


class RumbleSchedule:
    """When to upload a new rumble strength (clock-injected, pure).

    A strength is played for ``rumble_length_s``; while the force lasts it is renewed at
    most every ``rumble_period_s`` (an EVIOCSFF per renewal, not one per haptic tick), and
    the moment the force falls to 0 the rumble stops. :meth:`step` says what to do."""

    def __init__(self, config: GamepadConfig) -> None:
        self.config = config
        self._period_ns = round(config.rumble_period_s * NS_PER_S)
        self._last_ns: int | None = None
        self.playing = False

    @property
    def length_ms(self) -> int:
        return round(self.config.rumble_length_s * 1000)

    def step(self, force_n: float, now_ns: int) -> int | None:
        """The magnitude to upload and play now (0: stop the rumble), or None: nothing."""
        magnitude = rumble_magnitude(force_n, self.config.rumble_min_force_n,
                                     self.config.rumble_full_force_n)  # fmt: skip
        if magnitude == 0:
            if not self.playing:
                return None
            self.playing = False
            self._last_ns = None
            return 0
        if self._last_ns is not None and now_ns - self._last_ns < self._period_ns:
            return None
        self._last_ns = now_ns
        self.playing = True
        return magnitude


def bitmap_has(bitmap: bytes, bit: int) -> bool:
    """Whether ``bit`` is set in an EVIOCGBIT / EVIOCGKEY bitmap (bytes, bit 0 first)."""
    return bit // 8 < len(bitmap) and bool(bitmap[bit // 8] >> (bit % 8) & 1)


def bitmap_bits(bitmap: bytes) -> frozenset[int]:
    """Every bit set in an EVIOCGKEY bitmap: the codes held."""
    return frozenset(i for i in range(len(bitmap) * 8) if bitmap_has(bitmap, i))
