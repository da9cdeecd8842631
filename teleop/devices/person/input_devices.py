"""Gamepads and SpaceMice on Linux: finding one, opening it, reading intents, rumble.

The adapter around teleop/devices/person/input_events.py's pure decoding: discovery through
sysfs, the device node opened non-blocking, reads driven by ``poll`` with a timeout (no
busy loop), and a gamepad's rumble through EVIOCSFF. Only the standard library: the
kernel's ``input_event``, ``input_absinfo``, ``ff_effect`` and hidraw report formats are
stable ABI and the four ioctls needed (EVIOCGBIT, EVIOCGABS, EVIOCGKEY, EVIOCSFF) are
plain ``fcntl.ioctl`` calls.

Discovery reads sysfs, which any user may read, so a device that is there but not
readable is told apart from one that is not there:

* gamepad, ``gamepad.device = "auto"``: the first ``/dev/input/by-id/*-event-joystick``
  (udev's name for a joystick or gamepad), else the first ``/dev/input/eventN`` whose
  capabilities (``/sys/class/input/eventN/device/capabilities``, the bitmaps EVIOCGBIT
  returns) have ABS_X, ABS_Y and a gamepad's or joystick's first button.
* SpaceMouse, ``spacemouse.device = "auto"``: the hidraw nodes whose
  ``/sys/class/hidraw/hidrawN/device/uevent`` names a 3Dconnexion device (``HID_ID``:
  vendor 256f, or 046d with a SpaceMouse product id), then the event devices of those
  ids; the first readable one wins (hidraw first: its reports carry an axis's return to 0,
  which the kernel's relative events drop).

A device that is absent or that this user may not open raises :class:`DeviceUnavailable`,
whose message is one line: the device, the reason and the fix (the ``input`` group, the
udev rule). The launcher turns it into exit code 2.

The roots (``/dev``, ``/sys``) and the readability test are parameters, so tests build
a fake tree in a temporary directory and run as root, where file modes stop nothing.
"""

from __future__ import annotations

import errno
import fcntl
import grp
import os
import re
import select
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from teleop.bus.messages import Button
from teleop.core.clock import Clock, MonotonicClock
from teleop.core.config import Config, GamepadConfig, SpaceMouseConfig
from teleop.devices.person.input_events import (
    ABS_MAX,
    ABS_NAMES,
    ABS_X,
    ABS_Y,
    BTN_SOUTH,
    BTN_TRIGGER,
    EV_ABS,
    EV_FF,
    EVIOCSFF,
    FF_MAX,
    FF_RUMBLE,
    INPUT_ABSINFO,
    INPUT_EVENT,
    KEY_MAX,
    AbsInfo,
    EventFramer,
    GamepadState,
    RumbleSchedule,
    SpaceMouseState,
    bitmap_bits,
    bitmap_has,
    effect_id_of,
    eviocgabs,
    eviocgbit,
    eviocgkey,
    pack_event,
    pack_rumble_effect,
)
from teleop.devices.person.intent import HandIntent

DEV_ROOT = Path("/dev")
SYS_ROOT = Path("/sys")
EVDEV, HIDRAW = "evdev", "hidraw"  # how a device node is read

VENDOR_3DCONNEXION = 0x256F
VENDOR_LOGITECH = 0x046D
# 3Dconnexion devices sold under Logitech's vendor id (spacenavd's list): SpaceMouse Plus
# XT, CADman, SpaceMouse Classic, SpaceBall 5000, SpaceTraveler, SpacePilot,
# SpaceNavigator, SpaceExplorer, SpaceNavigator for Notebooks, SpacePilot Pro,
# SpaceMouse Pro.
LOGITECH_SPACEMOUSE_PRODUCTS = frozenset(
    {0xC603, 0xC605, 0xC606, 0xC621, 0xC623, 0xC625, 0xC626, 0xC627, 0xC628, 0xC629, 0xC62B}
)
# 3Dconnexion's own ids that are plain mice (the CadMouse family), not six-axis devices.
CADMOUSE_PRODUCTS = frozenset({0xC650, 0xC651, 0xC654, 0xC655, 0xC656, 0xC657})

UDEV_RULES_FILE = "/etc/udev/rules.d/99-spacemouse.rules"
INPUT_GROUP_FIX = "join the input group: sudo usermod -aG input $USER, then log out and in again"

_EVENT_BYTES_PER_READ = 64 * INPUT_EVENT.size  # up to 64 events per read
_HID_REPORT_BYTES_MAX = 256  # a hidraw read returns one report, at most this long here
_READS_PER_CALL_MAX = 64  # a read() drains at most this many chunks, then returns
_NAME_BYTES = 256
_KEY_BITMAP_BYTES = KEY_MAX // 8 + 1
_ABS_BITMAP_BYTES = ABS_MAX // 8 + 1
_FF_BITMAP_BYTES = FF_MAX // 8 + 1
_MS_PER_S = 1000


class DeviceUnavailable(Exception):
    """A human input device that is absent or cannot be opened or read: ``str()`` is one
    line naming the device, the reason and the fix."""

    def __init__(self, device: str, reason: str, fix: str) -> None:
        super().__init__(device, reason, fix)
        self.device = device
        self.reason = reason
        self.fix = fix

    def __str__(self) -> str:
        return " ".join(f"{self.device}: {self.reason}; fix: {self.fix}".split())


@dataclass(frozen=True)
class FoundDevice:
    """A device node found for a role: its path, how it is read (EVDEV or HIDRAW), its
    name and USB ids (0 when unknown)."""

    path: Path
    interface: str
    name: str
    vendor_id: int = 0
    product_id: int = 0

    @property
    def label(self) -> str:
        return f"{self.name} ({self.path})" if self.name != str(self.path) else self.name


def readable(path: Path) -> bool:
    """Whether this user may open ``path`` for reading."""
    return os.access(path, os.R_OK)


def is_spacemouse(vendor_id: int, product_id: int) -> bool:
    """Whether USB ids are a 3Dconnexion six-axis device."""
    if vendor_id == VENDOR_3DCONNEXION:
        return product_id not in CADMOUSE_PRODUCTS
    return vendor_id == VENDOR_LOGITECH and product_id in LOGITECH_SPACEMOUSE_PRODUCTS


def parse_capability_bitmap(text: str) -> int:
    """A sysfs capabilities file (hex words of a native long, most significant first, as
    the kernel prints the EVIOCGBIT bitmap) as one integer, bit n = code n."""
    word_bits = 8 * struct.calcsize("L")
    value = 0
    for word in text.split():
        value = (value << word_bits) | int(word, 16)
    return value


def _read_text(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except (OSError, UnicodeDecodeError):
        return None


def _node_number(path: Path) -> int:
    digits = re.search(r"(\d+)$", path.name)
    return int(digits.group(1)) if digits else -1


def _hex_id(path: Path) -> int:
    text = _read_text(path)
    try:
        return int(text, 16) if text else 0
    except ValueError:
        return 0


@dataclass(frozen=True)
class _EventNode:
    """An input event device as sysfs describes it."""

    node: str  # eventN
    name: str
    vendor_id: int
    product_id: int
    key_bits: int
    abs_bits: int


def _event_nodes(sys_root: Path) -> list[_EventNode]:
    nodes = []
    for entry in sorted((sys_root / "class/input").glob("event*"), key=_node_number):
        device = entry / "device"
        nodes.append(
            _EventNode(
                entry.name,
                _read_text(device / "name") or entry.name,
                _hex_id(device / "id/vendor"),
                _hex_id(device / "id/product"),
                parse_capability_bitmap(_read_text(device / "capabilities/key") or ""),
                parse_capability_bitmap(_read_text(device / "capabilities/abs") or ""),
            )
        )
    return nodes


def _looks_like_gamepad(node: _EventNode) -> bool:
    sticks = node.abs_bits >> ABS_X & 1 and node.abs_bits >> ABS_Y & 1
    buttons = node.key_bits >> BTN_SOUTH & 1 or node.key_bits >> BTN_TRIGGER & 1
    return bool(sticks and buttons) and not is_spacemouse(node.vendor_id, node.product_id)


def find_gamepads(dev_root: Path = DEV_ROOT, sys_root: Path = SYS_ROOT) -> list[FoundDevice]:
    """Gamepads and joysticks, best first: udev's ``by-id/*-event-joystick`` links, then
    event devices with a gamepad's capabilities."""
    names = {node.node: node for node in _event_nodes(sys_root)}
    found: list[FoundDevice] = []
    for link in sorted((dev_root / "input/by-id").glob("*-event-joystick")):
        target = link.resolve()
        if target.exists():
            node = names.get(target.name)
            found.append(FoundDevice(target, EVDEV, node.name if node else link.name,
                                     node.vendor_id if node else 0,
                                     node.product_id if node else 0))  # fmt: skip
    for node in names.values():
        path = dev_root / "input" / node.node
        if _looks_like_gamepad(node) and all(f.path.name != node.node for f in found):
            found.append(FoundDevice(path, EVDEV, node.name, node.vendor_id, node.product_id))
    return found


_HID_ID = re.compile(r"HID_ID=([0-9A-Fa-f]+):([0-9A-Fa-f]+):([0-9A-Fa-f]+)")
_HID_NAME = re.compile(r"HID_NAME=(.*)")


def find_spacemice(dev_root: Path = DEV_ROOT, sys_root: Path = SYS_ROOT) -> list[FoundDevice]:
    """3Dconnexion six-axis devices: their hidraw nodes, then their event devices."""
    found: list[FoundDevice] = []
    for entry in sorted((sys_root / "class/hidraw").glob("hidraw*"), key=_node_number):
        uevent = _read_text(entry / "device/uevent") or ""
        ids = _HID_ID.search(uevent)
        if ids is None:
            continue
        vendor_id, product_id = int(ids.group(2), 16), int(ids.group(3), 16)
        if is_spacemouse(vendor_id, product_id):
            name = _HID_NAME.search(uevent)
            found.append(FoundDevice(dev_root / entry.name, HIDRAW,
                                     name.group(1).strip() if name else entry.name,
                                     vendor_id, product_id))  # fmt: skip
    for node in _event_nodes(sys_root):
        if is_spacemouse(node.vendor_id, node.product_id):
            found.append(FoundDevice(dev_root / "input" / node.node, EVDEV, node.name,
                                     node.vendor_id, node.product_id))  # fmt: skip
    return found


def udev_rule(vendor_id: int, product_id: int) -> str:
    """The udev rule line that lets the input group read a SpaceMouse's hidraw node (a
    Logitech-id device by its product too: not every Logitech device)."""
    product = "" if vendor_id == VENDOR_3DCONNEXION else f', ATTRS{{idProduct}}=="{product_id:04x}"'
    return (f'KERNEL=="hidraw*", ATTRS{{idVendor}}=="{vendor_id:04x}"{product}, '
            'MODE="0660", GROUP="input"')  # fmt: skip


def access_fix(device: FoundDevice) -> str:
    """How to let this user read ``device``: the input group for an event device, a udev
    rule (and the group) for a hidraw node, which is root's alone by default."""
    if device.interface == HIDRAW:
        vendor_id = device.vendor_id or VENDOR_3DCONNEXION
        return (
            f"write the line '{udev_rule(vendor_id, device.product_id)}' to {UDEV_RULES_FILE}, "
            "run 'sudo udevadm control --reload && sudo udevadm trigger', and "
            f"{INPUT_GROUP_FIX}"
        )
    return INPUT_GROUP_FIX


def _node_owner(path: Path) -> str:
    try:
        status = path.stat()
    except OSError:
        return "cannot stat it"
    try:
        group = grp.getgrgid(status.st_gid).gr_name
    except KeyError:
        group = str(status.st_gid)
    return f"group {group}, mode {status.st_mode & 0o777:03o}"


def _first_readable(candidates: list[FoundDevice],
                    can_read: Callable[[Path], bool]) -> FoundDevice:  # fmt: skip
    for candidate in candidates:
        if can_read(candidate.path):
            return candidate
    first = candidates[0]
    raise DeviceUnavailable(
        first.label, f"not readable by this user ({_node_owner(first.path)})", access_fix(first)
    )


def _configured(path: Path, section: str, sys_root: Path) -> FoundDevice:
    """The device ``<section>.device`` names, described from sysfs where it can be."""
    if not path.exists():
        raise DeviceUnavailable(
            str(path), "no such device",
            f'plug it in, or set {section}.device to its node (or "auto")',
        )  # fmt: skip
    target = path.resolve()
    interface = HIDRAW if target.name.startswith("hidraw") else EVDEV
    if interface == HIDRAW:
        uevent = _read_text(sys_root / "class/hidraw" / target.name / "device/uevent") or ""
        ids = _HID_ID.search(uevent)
        vendor_id, product_id = (int(ids.group(2), 16), int(ids.group(3), 16)) if ids else (0, 0)
        return FoundDevice(path, HIDRAW, str(path), vendor_id, product_id)
    device = sys_root / "class/input" / target.name / "device"
    return FoundDevice(path, EVDEV, _read_text(device / "name") or str(path),
                       _hex_id(device / "id/vendor"), _hex_id(device / "id/product"))  # fmt: skip


def find_gamepad(
    config: GamepadConfig,
    dev_root: Path = DEV_ROOT,
    sys_root: Path = SYS_ROOT,
    can_read: Callable[[Path], bool] = readable,
) -> FoundDevice:
    """The gamepad ``config.device`` names or auto-discovery finds, readable by this user;
    else :class:`DeviceUnavailable`."""
    if config.device != "auto":
        found = _configured(Path(config.device), "gamepad", sys_root)
        if found.interface != EVDEV:
            raise DeviceUnavailable(
                str(found.path),
                "a hidraw node; a gamepad is read as an event device",
                "set gamepad.device=/dev/input/eventN",
            )
        candidates = [found]
    else:
        candidates = find_gamepads(dev_root, sys_root)
        if not candidates:
            raise DeviceUnavailable(
                "gamepad",
                f"none found (no {dev_root}/input/by-id/*-event-joystick, no event device with "
                "a gamepad's sticks and buttons)",
                "plug it in (or pair it), or set gamepad.device=/dev/input/eventN",
            )
    return _first_readable(candidates, can_read)


def find_spacemouse(
    config: SpaceMouseConfig,
    dev_root: Path = DEV_ROOT,
    sys_root: Path = SYS_ROOT,
    can_read: Callable[[Path], bool] = readable,
) -> FoundDevice:
    """The SpaceMouse ``config.device`` names or auto-discovery finds, readable by this
    user; else :class:`DeviceUnavailable`."""
    if config.device != "auto":
        candidates = [_configured(Path(config.device), "spacemouse", sys_root)]
    else:
        candidates = find_spacemice(dev_root, sys_root)
        if not candidates:
            raise DeviceUnavailable(
                "spacemouse",
                "none found (no hidraw or event device of 3Dconnexion: USB vendor 256f, or "
                "046d with a SpaceMouse product id)",
                "plug it in (or its receiver), or set spacemouse.device=/dev/hidrawN",
            )
    return _first_readable(candidates, can_read)


class PersonInputDevice(Protocol):
    """What the operator service needs of a gamepad or SpaceMouse reader."""

    name: str

    @property
    def armed(self) -> bool: ...

    def fileno(self) -> int: ...

    @property
    def switch_presses(self) -> int: ...

    def read(self, timeout_s: float) -> HandIntent: ...

    def take_robot(self, buttons: Button) -> HandIntent: ...

    def rumble(self, force_n: float) -> None: ...

    def close(self) -> None: ...


class _Reader:
    """A non-blocking device node read when ``poll`` says it has data: ``read`` waits at
    most its timeout, takes what is there (whole events or reports) and returns the
    intent. Closed once, safely twice; a context manager."""

    _read_bytes = _EVENT_BYTES_PER_READ
    state: GamepadState | SpaceMouseState

    def __init__(self, fd: int, name: str, clock: Clock | None) -> None:
        self._fd = fd
        self.name = name
        self.clock: Clock = clock if clock is not None else MonotonicClock()
        self._poll = select.poll()
        self._poll.register(fd, select.POLLIN)
        self.closed = False

    def fileno(self) -> int:
        return self._fd

    @property
    def armed(self) -> bool:
        """Whether the device's axes have been seen at rest since it was opened (until then
        it asks for no motion: a user interface says "centre the stick")."""
        return self.state.mapper.armed

    @property
    def switch_presses(self) -> int:
        """Presses of a robot-switch button (``switch_buttons``) since it was opened."""
        return self.state.mapper.switch_presses

    def take_robot(self, buttons: Button) -> HandIntent:
        """The hand moved to another robot: the gripper as the hand left it
        (:meth:`IntentMapper.take_robot`); the intent now."""
        self.state.mapper.take_robot(buttons)
        return self.intent()

    def read(self, timeout_s: float) -> HandIntent:
        """Wait up to ``timeout_s`` for input, apply all there is, return the intent now."""
        if self.closed:
            raise ValueError(f"{self.name}: read after close")
        if self._poll.poll(max(0, round(timeout_s * _MS_PER_S))):
            self._drain()
        return self.intent()

    def _drain(self) -> None:
        for _ in range(_READS_PER_CALL_MAX):
            try:
                data = os.read(self._fd, self._read_bytes)
            except BlockingIOError:
                return
            except OSError as exc:
                raise DeviceUnavailable(
                    self.name, f"read failed ({exc.strerror or exc})",
                    "plug it back in and start again",
                ) from exc  # fmt: skip
            if not data:
                raise DeviceUnavailable(self.name, "disconnected (its stream ended)",
                                        "plug it back in and start again")  # fmt: skip
            self._consume(data)

    def _consume(self, data: bytes) -> None:
        raise NotImplementedError

    def intent(self) -> HandIntent:
        raise NotImplementedError

    def rumble(self, force_n: float) -> None:
        """Render a feedback force's magnitude (N) where the device can; here it cannot."""

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._poll.unregister(self._fd)
        os.close(self._fd)

    def __enter__(self) -> _Reader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _NoRumble:
    """A gamepad without rumble (or with it switched off)."""

    available = False

    def set_force(self, force_n: float, now_ns: int) -> None:
        return


class EvdevRumble:
    """One FF_RUMBLE effect of an evdev device: uploaded (EVIOCSFF) with each new strength
    the :class:`RumbleSchedule` asks for and played by writing an EV_FF event. Best effort:
    a failing upload switches rumble off (:attr:`errors` counts) and never stops control."""

    available = True

    def __init__(self, fd: int, config: GamepadConfig) -> None:
        self._fd = fd
        self.schedule = RumbleSchedule(config)
        self.effect_id = -1
        self.errors = 0

    def set_force(self, force_n: float, now_ns: int) -> None:
        magnitude = self.schedule.step(force_n, now_ns)
        if magnitude is None or self.errors:
            return
        try:
            if magnitude == 0:
                if self.effect_id >= 0:
                    os.write(self._fd, pack_event(EV_FF, self.effect_id, 0))
                return
            effect = bytearray(pack_rumble_effect(self.effect_id, magnitude, magnitude,
                                                  self.schedule.length_ms))  # fmt: skip
            fcntl.ioctl(self._fd, EVIOCSFF, effect, True)
            self.effect_id = effect_id_of(bytes(effect))
            os.write(self._fd, pack_event(EV_FF, self.effect_id, 1))
        except OSError:
            self.errors += 1


class GamepadReader(_Reader):
    """A gamepad's event device, read into intents; rumble where it has it.

    ``resync``: reads the device's axis values and held buttons back after SYN_DROPPED
    (``query_gamepad_state``; None where the fd is not a device, as in tests)."""

    def __init__(
        self,
        fd: int,
        config: GamepadConfig,
        absinfo: dict[int, AbsInfo],
        *,
        name: str = "gamepad",
        rumble: EvdevRumble | None = None,
        resync: Callable[[], tuple[dict[int, int], frozenset[int]]] | None = None,
        clock: Clock | None = None,
    ) -> None:
        super().__init__(fd, name, clock)
        self.state = GamepadState(config, absinfo)
        self.framer = EventFramer()
        self._rumble: EvdevRumble | _NoRumble = rumble if rumble is not None else _NoRumble()
        self._resync = resync

    @property
    def has_rumble(self) -> bool:
        return self._rumble.available

    def _consume(self, data: bytes) -> None:
        for frame in self.framer.feed(data):
            self.state.apply(frame)
        if self.framer.resync_needed:
            self.framer.resync_needed = False
            if self._resync is not None:
                self.state.resync(*self._resync())

    def intent(self) -> HandIntent:
        return self.state.intent()

    def rumble(self, force_n: float) -> None:
        """Rumble with the strength of a feedback force's magnitude (N)."""
        self._rumble.set_force(force_n, self.clock.now_ns())


class _EvdevSpaceMouse:
    """A SpaceMouse's event device: frames of events into its state."""

    read_bytes = _EVENT_BYTES_PER_READ

    def __init__(self, state: SpaceMouseState) -> None:
        self.state = state
        self.framer = EventFramer()

    def consume(self, data: bytes, now_ns: int) -> None:
        for frame in self.framer.feed(data):
            self.state.apply_frame(frame, now_ns)
        if self.framer.resync_needed:
            self.framer.resync_needed = False
            self.state.release_axes()


class _HidrawSpaceMouse:
    """A SpaceMouse's hidraw node: one HID report per read into its state."""

    read_bytes = _HID_REPORT_BYTES_MAX

    def __init__(self, state: SpaceMouseState) -> None:
        self.state = state

    def consume(self, data: bytes, now_ns: int) -> None:
        self.state.apply_report(data, now_ns)


class SpaceMouseReader(_Reader):
    """A SpaceMouse read into intents, through its hidraw node or its event device
    (``interface``: HIDRAW or EVDEV, chosen once). It has no actuator: ``rumble`` does
    nothing."""

    def __init__(
        self,
        fd: int,
        config: SpaceMouseConfig,
        interface: str,
        *,
        name: str = "spacemouse",
        clock: Clock | None = None,
    ) -> None:
        super().__init__(fd, name, clock)
        self.state = SpaceMouseState(config)
        self.interface = interface
        self._source = (_HidrawSpaceMouse if interface == HIDRAW else _EvdevSpaceMouse)(self.state)
        self._read_bytes = self._source.read_bytes

    def _consume(self, data: bytes) -> None:
        self._source.consume(data, self.clock.now_ns())

    def intent(self) -> HandIntent:
        return self.state.intent(self.clock.now_ns())


def _open_node(device: FoundDevice, write: bool) -> tuple[int, bool]:
    """``device`` opened non-blocking (read-write if ``write`` and allowed, for rumble);
    the fd and whether it is writable."""
    flags = os.O_NONBLOCK | os.O_CLOEXEC
    modes = [os.O_RDWR, os.O_RDONLY] if write else [os.O_RDONLY]
    for mode in modes:
        try:
            return os.open(device.path, flags | mode), mode == os.O_RDWR
        except PermissionError as exc:
            if mode == modes[-1]:
                raise DeviceUnavailable(
                    device.label, f"not readable by this user ({_node_owner(device.path)})",
                    access_fix(device),
                ) from exc  # fmt: skip
        except OSError as exc:
            if exc.errno in (errno.ENOENT, errno.ENODEV, errno.ENXIO):
                raise DeviceUnavailable(device.label, "gone while opening it",
                                        "plug it in and start again") from exc  # fmt: skip
            raise DeviceUnavailable(device.label, f"cannot open it ({exc.strerror or exc})",
                                    "close what holds it and start again") from exc  # fmt: skip
    raise AssertionError("unreachable: the last mode raises")


def read_absinfo(fd: int) -> dict[int, AbsInfo]:
    """Every absolute axis of an event device (EVIOCGBIT(EV_ABS), then EVIOCGABS each)."""
    bits = fcntl.ioctl(fd, eviocgbit(EV_ABS, _ABS_BITMAP_BYTES), bytes(_ABS_BITMAP_BYTES))
    return {
        code: AbsInfo.unpack(fcntl.ioctl(fd, eviocgabs(code), bytes(INPUT_ABSINFO.size)))
        for code in bitmap_bits(bits)
    }


def has_rumble(fd: int) -> bool:
    """Whether an event device plays FF_RUMBLE effects (EVIOCGBIT(EV_FF))."""
    try:
        bits = fcntl.ioctl(fd, eviocgbit(EV_FF, _FF_BITMAP_BYTES), bytes(_FF_BITMAP_BYTES))
    except OSError:
        return False
    return bitmap_has(bits, FF_RUMBLE)


def query_gamepad_state(fd: int) -> tuple[dict[int, int], frozenset[int]]:
    """An event device's axis values (EVIOCGABS) and held buttons (EVIOCGKEY) now."""
    counts = {code: info.value for code, info in read_absinfo(fd).items()}
    held = bitmap_bits(fcntl.ioctl(fd, eviocgkey(_KEY_BITMAP_BYTES), bytes(_KEY_BITMAP_BYTES)))
    return counts, held


def open_gamepad(
    config: GamepadConfig,
    *,
    dev_root: Path = DEV_ROOT,
    sys_root: Path = SYS_ROOT,
    can_read: Callable[[Path], bool] = readable,
    clock: Clock | None = None,
) -> GamepadReader:
    """The configured (or first found) gamepad, open; :class:`DeviceUnavailable` if none
    can be read, or if it lacks an axis ``gamepad.axes`` maps."""
    device = find_gamepad(config, dev_root, sys_root, can_read)
    fd, writable = _open_node(device, write=config.rumble)
    try:
        absinfo = read_absinfo(fd)
        rumble = EvdevRumble(fd, config) if config.rumble and writable and has_rumble(fd) else None
        reader = GamepadReader(fd, config, absinfo, name=device.label, rumble=rumble,
                               resync=lambda: query_gamepad_state(fd), clock=clock)  # fmt: skip
    except OSError as exc:
        os.close(fd)
        raise DeviceUnavailable(device.label, f"not an input event device ({exc.strerror})",
                                "set gamepad.device=/dev/input/eventN") from exc  # fmt: skip
    missing = reader.state.missing_axes
    if missing:
        reader.close()
        names = {code: name for name, code in ABS_NAMES.items()}
        has = ", ".join(names.get(code, hex(code)) for code in sorted(absinfo)) or "none"
        raise DeviceUnavailable(
            device.label,
            f"has no axis {', '.join(names[c] for c in missing)} that gamepad.axes maps",
            f"set gamepad.axes to axes it has ({has})",
        )
    return reader


def open_spacemouse(
    config: SpaceMouseConfig,
    *,
    dev_root: Path = DEV_ROOT,
    sys_root: Path = SYS_ROOT,
    can_read: Callable[[Path], bool] = readable,
    clock: Clock | None = None,
) -> SpaceMouseReader:
    """The configured (or first found) SpaceMouse, open; :class:`DeviceUnavailable` if none
    can be read."""
    device = find_spacemouse(config, dev_root, sys_root, can_read)
    fd, _ = _open_node(device, write=False)
    return SpaceMouseReader(fd, config, device.interface, name=device.label, clock=clock)


def open_input_device(
    operator: str,
    config: Config,
    *,
    dev_root: Path = DEV_ROOT,
    sys_root: Path = SYS_ROOT,
    can_read: Callable[[Path], bool] = readable,
    clock: Clock | None = None,
) -> GamepadReader | SpaceMouseReader:
    """The reader for ``run.operator`` "gamepad" or "spacemouse", from its config section."""
    if operator == "gamepad":
        return open_gamepad(config.gamepad, dev_root=dev_root, sys_root=sys_root,
                            can_read=can_read, clock=clock)  # fmt: skip
    if operator == "spacemouse":
        return open_spacemouse(config.spacemouse, dev_root=dev_root, sys_root=sys_root,
                               can_read=can_read, clock=clock)  # fmt: skip
    raise ValueError(f"operator {operator!r} is not an input device (gamepad, spacemouse)")
