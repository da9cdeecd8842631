"""Gamepad and SpaceMouse input: the kernel's byte formats decoded into HandIntents, their
discovery on a fake /dev and /sys, the one-line errors, and readers over real pipes."""

from __future__ import annotations

import os
import socket
import struct

import pytest

from teleop.bus.messages import Button
from teleop.core.clock import NS_PER_S, FakeClock
from teleop.core.config import Config, ConfigError, GamepadConfig, SpaceMouseConfig, load_config
from teleop.devices.person.input_devices import (
    EVDEV,
    HIDRAW,
    UDEV_RULES_FILE,
    DeviceUnavailable,
    EvdevRumble,
    GamepadReader,
    SpaceMouseReader,
    find_gamepad,
    find_gamepads,
    find_spacemice,
    find_spacemouse,
    open_gamepad,
    open_spacemouse,
    parse_capability_bitmap,
)
from teleop.devices.person.input_events import (
    EVIOCSFF,
    FF_EFFECT,
    INPUT_EVENT,
    AbsInfo,
    EventFramer,
    GamepadState,
    RumbleSchedule,
    SpaceMouseState,
    abs_fraction,
    apply_dead_zone,
    decode_events,
    decode_spacemouse_report,
    effect_id_of,
    eviocgabs,
    eviocgbit,
    eviocgkey,
    eviocgname,
    flat_fraction,
    pack_rumble_effect,
    rumble_magnitude,
)

# The kernel's numbers, spelt out here from linux/input-event-codes.h (not imported), so a
# wrong constant in the module cannot agree with itself.
EV_SYN, EV_KEY, EV_REL, EV_ABS, EV_FF = 0, 1, 2, 3, 0x15
SYN_REPORT, SYN_DROPPED = 0, 3
ABS_X, ABS_Y, ABS_Z, ABS_RX, ABS_RY, ABS_RZ = 0, 1, 2, 3, 4, 5
ABS_HAT0X = 0x10
REL_X, REL_Y, REL_Z, REL_RX = 0, 1, 2, 3
BTN_0, BTN_1 = 0x100, 0x101
BTN_SOUTH, BTN_EAST, BTN_TL, BTN_TR = 0x130, 0x131, 0x136, 0x137
FF_RUMBLE = 0x50

LP64 = struct.calcsize("P") == 8
needs_lp64 = pytest.mark.skipif(not LP64, reason="layouts checked are 64-bit Linux's")


def event(event_type: int, code: int, value: int, sec: int = 1700000000, usec: int = 5) -> bytes:
    """A struct input_event as 64-bit Linux lays it out: timeval (two 8-byte longs), then
    __u16 type, __u16 code, __s32 value, native byte order, 24 bytes."""
    return struct.pack("=qqHHi", sec, usec, event_type, code, value)


def syn() -> bytes:
    return event(EV_SYN, SYN_REPORT, 0)


def frame(*events: tuple[int, int, int]) -> bytes:
    return b"".join(event(*e) for e in events) + syn()


# An Xbox pad through xpad: sticks -32768..32767 (flat 128), triggers 0..1023, d-pad -1..1.
XPAD_STICK = AbsInfo(0, -32768, 32767, 16, 128, 0)
XPAD_TRIGGER = AbsInfo(0, 0, 1023, 0, 0, 0)
XPAD_ABSINFO = {
    ABS_X: XPAD_STICK, ABS_Y: XPAD_STICK, ABS_RX: XPAD_STICK, ABS_RY: XPAD_STICK,
    ABS_Z: XPAD_TRIGGER, ABS_RZ: XPAD_TRIGGER, ABS_HAT0X: AbsInfo(0, -1, 1),
}  # fmt: skip


def hid_report(report_id: int, *values: int) -> bytes:
    """A SpaceMouse HID input report: the id byte, then little-endian int16 values."""
    return bytes([report_id]) + struct.pack(f"<{len(values)}h", *values)


# -- the kernel's layouts -------------------------------------------------------------------


@needs_lp64
def test_input_event_is_the_kernels_24_byte_layout():
    assert INPUT_EVENT.size == 24
    raw = event(EV_ABS, ABS_Y, -32768, sec=12, usec=34)
    assert raw[:16] == struct.pack("=qq", 12, 34)  # struct timeval: tv_sec, tv_usec
    assert struct.unpack_from("=HHi", raw, 16) == (EV_ABS, ABS_Y, -32768)
    assert decode_events(raw) == [(12, 34, EV_ABS, ABS_Y, -32768)]
    with pytest.raises(ValueError, match="whole number"):
        decode_events(raw[:-1])


@needs_lp64
def test_ioctl_numbers_match_the_kernel_headers():
    # Values printed by a C program including linux/input.h on x86_64.
    assert EVIOCSFF == 0x40304580
    assert eviocgabs(ABS_X) == 0x80184540 and eviocgabs(ABS_Y) == 0x80184541
    assert eviocgbit(EV_FF, 16) == 0x80104535
    assert eviocgbit(0, 8) == 0x80084520
    assert eviocgkey(96) == 0x80604518
    assert eviocgname(256) == 0x81004506


@needs_lp64
def test_ff_effect_is_packed_as_the_kernel_lays_it_out():
    """struct ff_effect on x86_64 (48 bytes): type, id, direction, trigger {button,
    interval}, replay {length, delay} (u16/s16 each, 14 bytes), 2 bytes padding (the union
    is pointer-aligned), then the union whose rumble member is strong, weak magnitude."""
    packed = pack_rumble_effect(-1, 0x8000, 0x4000, 200)
    assert FF_EFFECT.size == len(packed) == 48
    # The bytes gcc's struct ff_effect holds for the same fields (printed by a C program).
    reference = bytes.fromhex(
        "5000ffff000000000000c800000000000080004000000000"
        "000000000000000000000000000000000000000000000000"
    )
    assert packed == reference
    (kind, effect_id, direction, button, interval, length, delay) = struct.unpack_from(
        "=HhHHHHH", packed
    )
    assert (kind, effect_id, direction, length, delay) == (FF_RUMBLE, -1, 0, 200, 0)
    assert (button, interval) == (0, 0)
    assert struct.unpack_from("=HH", packed, 16) == (0x8000, 0x4000)
    assert packed[20:] == bytes(28)
    assert effect_id_of(pack_rumble_effect(7, 1, 1, 50)) == 7
    with pytest.raises(ValueError, match="strong_magnitude"):
        pack_rumble_effect(-1, 0x10000, 0, 10)


def test_absinfo_round_trips_its_struct():
    raw = struct.pack("=6i", 5, -32768, 32767, 16, 128, 0)
    assert AbsInfo.unpack(raw) == AbsInfo(5, -32768, 32767, 16, 128, 0)
    assert AbsInfo.unpack(raw).pack() == raw


# -- frames: SYN_REPORT and SYN_DROPPED -----------------------------------------------------


def test_events_are_applied_in_frames_closed_by_syn_report():
    framer = EventFramer()
    data = event(EV_ABS, ABS_X, 100) + event(EV_ABS, ABS_Y, -200)
    assert framer.feed(data) == []  # no SYN_REPORT yet: nothing applies
    frames = framer.feed(syn() + event(EV_KEY, BTN_SOUTH, 1) + syn())
    assert [[(e.type, e.code, e.value) for e in f] for f in frames] == [
        [(EV_ABS, ABS_X, 100), (EV_ABS, ABS_Y, -200)],
        [(EV_KEY, BTN_SOUTH, 1)],
    ]


def test_an_event_split_across_reads_waits_for_its_rest():
    framer = EventFramer()
    data = frame((EV_ABS, ABS_X, 7))
    assert framer.feed(data[:10]) == []
    assert framer.feed(data[10:30]) == []
    (only,) = framer.feed(data[30:])
    assert [(e.code, e.value) for e in only] == [(ABS_X, 7)]


def test_syn_dropped_discards_up_to_the_next_report_and_asks_for_a_resync():
    framer = EventFramer()
    data = (
        event(EV_ABS, ABS_X, 1)  # pending when the drop comes: discarded
        + event(EV_SYN, SYN_DROPPED, 0)
        + event(EV_ABS, ABS_X, 2)  # after the drop, before the next report: discarded
        + syn()
        + frame((EV_ABS, ABS_X, 3))
    )
    frames = framer.feed(data)
    assert [[e.value for e in f] for f in frames] == [[3]]
    assert framer.dropped == 1 and framer.resync_needed


# -- normalisation and dead zone ------------------------------------------------------------


def test_absinfo_normalisation_centred_and_one_sided():
    assert abs_fraction(-32768, XPAD_STICK, False) == -1.0
    assert abs_fraction(32767, XPAD_STICK, False) == 1.0
    assert abs_fraction(-1, XPAD_STICK, False) == pytest.approx(0.0, abs=1e-4)
    ds4 = AbsInfo(128, 0, 255, 0, 0, 0)  # hid-playstation stick: 0..255, centre 127.5
    assert abs_fraction(0, ds4, False) == -1.0 and abs_fraction(255, ds4, False) == 1.0
    assert abs_fraction(0, XPAD_TRIGGER, True) == 0.0
    assert abs_fraction(1023, XPAD_TRIGGER, True) == 1.0
    assert abs_fraction(40000, XPAD_STICK, False) == 1.0  # the kernel does not clip
    assert flat_fraction(XPAD_STICK, False) == pytest.approx(128 / 32767.5)


def test_dead_zone_reads_zero_inside_and_rescales_outside():
    assert apply_dead_zone(0.15, 0.15) == 0.0
    assert apply_dead_zone(-0.1, 0.15) == 0.0
    assert apply_dead_zone(0.575, 0.15) == pytest.approx(0.5)
    assert apply_dead_zone(-0.575, 0.15) == pytest.approx(-0.5)
    assert apply_dead_zone(1.0, 0.15) == 1.0
    assert apply_dead_zone(0.151, 0.15) == pytest.approx(0.001 / 0.85)  # starts at 0


# -- gamepad to HandIntent ------------------------------------------------------------------


def gamepad(config: GamepadConfig | None = None, absinfo=None) -> GamepadState:
    state = GamepadState(config or GamepadConfig(), absinfo or XPAD_ABSINFO)
    state.intent()  # sticks at rest: armed
    return state


def apply(state: GamepadState, data: bytes) -> None:
    framer = EventFramer()
    for f in framer.feed(data):
        state.apply(f)


def test_left_stick_up_and_left_are_forward_and_left_right_stick_up_is_up():
    state = gamepad()
    apply(state, frame((EV_ABS, ABS_Y, -32768)))  # stick pushed up reads negative
    assert state.intent().velocity_fraction == (1.0, 0.0, 0.0)
    apply(state, frame((EV_ABS, ABS_Y, 0), (EV_ABS, ABS_X, -32768)))  # pushed left
    assert state.intent().velocity_fraction == pytest.approx((0.0, 1.0, 0.0), abs=1e-4)
    apply(state, frame((EV_ABS, ABS_X, 0), (EV_ABS, ABS_RY, -32768)))
    assert state.intent().velocity_fraction == pytest.approx((0.0, 0.0, 1.0), abs=1e-4)
    apply(state, frame((EV_ABS, ABS_RY, 32767)))
    assert state.intent().velocity_fraction == pytest.approx((0.0, 0.0, -1.0), abs=1e-4)


def test_a_stick_inside_its_dead_zone_asks_for_nothing_and_a_diagonal_is_clipped_to_1():
    state = gamepad()
    apply(state, frame((EV_ABS, ABS_X, 3000), (EV_ABS, ABS_Y, -4000)))  # < 15 %
    assert not state.intent().moving
    apply(state, frame((EV_ABS, ABS_X, -32768), (EV_ABS, ABS_Y, -32768)))
    x, y, z = state.intent().velocity_fraction
    assert x == pytest.approx(y) and x == pytest.approx(2**-0.5) and z == 0.0


def test_a_half_deflection_beyond_the_dead_zone_is_rescaled():
    state = gamepad(GamepadConfig(dead_zone_fraction=0.2))
    apply(state, frame((EV_ABS, ABS_Y, round(-0.6 * 32767.5))))
    assert state.intent().velocity_fraction[0] == pytest.approx(0.5, abs=1e-3)


def test_a_stick_held_at_start_moves_nothing_until_it_has_been_centred():
    held = dict(XPAD_ABSINFO)
    held[ABS_Y] = AbsInfo(-32768, -32768, 32767, 16, 128, 0)  # pushed while opening
    state = GamepadState(GamepadConfig(), held)
    assert not state.intent().moving and not state.mapper.armed
    apply(state, frame((EV_ABS, ABS_Y, 0)))
    assert not state.intent().moving and state.mapper.armed
    apply(state, frame((EV_ABS, ABS_Y, -32768)))
    assert state.intent().velocity_fraction[0] == 1.0


def test_triggers_as_z_read_from_their_minimum():
    config = GamepadConfig(axes=("x=-Y", "y=-X", "z=+RZ", "z=-Z"))
    state = gamepad(config)
    assert not state.intent().moving  # triggers at rest (0) are not half-pressed
    apply(state, frame((EV_ABS, ABS_RZ, 1023)))
    assert state.intent().velocity_fraction[2] == 1.0
    apply(state, frame((EV_ABS, ABS_RZ, 0), (EV_ABS, ABS_Z, 1023)))
    assert state.intent().velocity_fraction[2] == -1.0


def test_gripper_toggles_on_each_press_and_clutch_is_held():
    state = gamepad()
    apply(state, frame((EV_KEY, BTN_SOUTH, 1)))
    assert state.intent().gripper_closed
    apply(state, frame((EV_KEY, BTN_SOUTH, 2)))  # autorepeat is no new press
    apply(state, frame((EV_KEY, BTN_SOUTH, 0)))
    assert state.intent().gripper_closed  # toggle: still closed after the release
    apply(state, frame((EV_KEY, BTN_SOUTH, 1)) + frame((EV_KEY, BTN_SOUTH, 0)))
    assert not state.intent().gripper_closed
    apply(state, frame((EV_KEY, BTN_TR, 1)))
    assert state.intent().clutch
    apply(state, frame((EV_KEY, BTN_TL, 1)) + frame((EV_KEY, BTN_TR, 0)))
    assert state.intent().clutch  # either shoulder button holds it
    apply(state, frame((EV_KEY, BTN_TL, 0)))
    assert not state.intent().clutch
    apply(state, frame((EV_KEY, BTN_EAST, 1)))
    assert not state.intent().gripper_closed and not state.intent().clutch


def test_hold_and_toggle_modes_are_configurable():
    state = gamepad(GamepadConfig(gripper_mode="hold", clutch_mode="toggle"))
    apply(state, frame((EV_KEY, BTN_SOUTH, 1), (EV_KEY, BTN_TL, 1)))
    assert state.intent().gripper_closed and state.intent().clutch
    apply(state, frame((EV_KEY, BTN_SOUTH, 0), (EV_KEY, BTN_TL, 0)))
    assert not state.intent().gripper_closed and state.intent().clutch


def test_resync_after_a_drop_takes_the_devices_state():
    state = gamepad()
    state.resync({ABS_Y: -32768}, frozenset({BTN_TL}))
    intent = state.intent()
    assert intent.velocity_fraction[0] == 1.0 and intent.clutch


def test_a_mapped_axis_the_device_lacks_is_reported():
    absinfo = {ABS_X: XPAD_STICK, ABS_Y: XPAD_STICK}
    assert GamepadState(GamepadConfig(), absinfo).missing_axes == (ABS_RY,)


# -- config ---------------------------------------------------------------------------------


def test_config_has_the_device_sections_with_valid_defaults():
    config = Config()
    assert config.gamepad == GamepadConfig() and config.spacemouse == SpaceMouseConfig()
    assert config.gamepad.device == "auto" and config.spacemouse.device == "auto"
    loaded = load_config(None, ["gamepad.axes=['x=-Y', 'y=-X', 'z=+RZ', 'z=-Z']",
                                "spacemouse.full_scale_counts=500"])  # fmt: skip
    assert loaded.gamepad.axes[2:] == ("z=+RZ", "z=-Z")
    assert loaded.spacemouse.full_scale_counts == 500.0


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("gamepad.axes=['forward=Y']", "gamepad.axes"),
        ("gamepad.dead_zone_fraction=1", "gamepad.dead_zone_fraction"),
        ("gamepad.gripper_mode=latch", "gamepad.gripper_mode"),
        ("gamepad.clutch_buttons=['A']", "gamepad.clutch_buttons"),
        ("gamepad.rumble_period_s=0.5", "rumble_period_s <= rumble_length_s"),
        ("spacemouse.full_scale_counts=0", "spacemouse.full_scale_counts"),
        ("spacemouse.gripper_buttons=[]", "spacemouse.gripper_buttons"),
    ],
)
def test_bad_device_config_is_refused_with_the_key_named(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [override])


def test_names_the_kernel_does_not_have_are_refused_naming_the_key():
    with pytest.raises(ConfigError, match=r"gamepad\.axes: 'x=-STICK'"):
        GamepadState(GamepadConfig(axes=("x=-STICK",)), XPAD_ABSINFO)
    with pytest.raises(ConfigError, match=r"gamepad\.gripper_buttons: unknown button"):
        GamepadState(GamepadConfig(gripper_buttons=("BTN_NOPE",)), XPAD_ABSINFO)
    with pytest.raises(ConfigError, match=r"spacemouse\.axes"):
        SpaceMouseState(SpaceMouseConfig(axes=("x=-HAT0X",)))


# -- SpaceMouse -----------------------------------------------------------------------------


def test_hid_reports_decode_both_forms_and_buttons():
    old = decode_spacemouse_report(hid_report(1, 10, -350, 20))  # 7 bytes: translation
    assert old.translation == (10, -350, 20) and old.rotation is None
    new = decode_spacemouse_report(hid_report(1, 1, 2, 3, 4, 5, 6))  # 13 bytes: all six
    assert len(hid_report(1, 1, 2, 3, 4, 5, 6)) == 13
    assert new.translation == (1, 2, 3) and new.rotation == (4, 5, 6)
    assert decode_spacemouse_report(hid_report(2, -7, 8, -9)).rotation == (-7, 8, -9)
    assert decode_spacemouse_report(bytes([3, 0b10, 0])).buttons == 2
    assert decode_spacemouse_report(bytes([0x17, 80])) is None  # battery: not ours
    assert decode_spacemouse_report(bytes([1, 0, 0])) is None  # too short
    assert decode_spacemouse_report(b"") is None


def test_spacemouse_push_forward_left_up_is_x_y_z_and_rotation_is_ignored():
    """The device's axes: X right, Y towards the user, Z down (as the HID reports and
    the kernel give them); pushing the cap forward / left / up reads -Y / -X / -Z."""
    state = spacemouse()
    state.apply_report(hid_report(1, 0, -350, 0), 0)
    assert state.intent(0).velocity_fraction == (1.0, 0.0, 0.0)
    state.apply_report(hid_report(1, -350, 0, 0), 0)
    assert state.intent(0).velocity_fraction == (0.0, 1.0, 0.0)
    state.apply_report(hid_report(1, 0, 0, -350), 0)
    assert state.intent(0).velocity_fraction == (0.0, 0.0, 1.0)
    state.apply_report(hid_report(1, 0, 0, 0), 0)
    state.apply_report(hid_report(2, 350, 350, 350), 0)  # twisting the cap: no motion
    assert not state.intent(0).moving
    state.apply_report(hid_report(1, 0, 175, 0, 300, 0, 0), 0)  # six-axis form, pulled back
    x = state.intent(0).velocity_fraction[0]
    assert x == pytest.approx(-(0.5 - 0.1) / 0.9)  # dead zone 0.1 of 350 counts


def test_spacemouse_buttons_left_toggles_gripper_right_holds_clutch():
    state = spacemouse()
    state.apply_report(bytes([3, 0b01, 0]), 0)
    assert state.intent(0).gripper_closed
    state.apply_report(bytes([3, 0b10, 0]), 0)
    assert state.intent(0).gripper_closed and state.intent(0).clutch
    state.apply_report(bytes([3, 0, 0]), 0)
    assert state.intent(0).gripper_closed and not state.intent(0).clutch
    state.apply_report(bytes([3, 0b01, 0]), 0)
    assert not state.intent(0).gripper_closed


def test_a_switch_button_counts_presses_and_the_keys_take_up_the_next_robots_gripper():
    state = spacemouse(SpaceMouseConfig(switch_buttons=("BTN_1",), clutch_buttons=()))
    state.apply_report(bytes([3, 0b01, 0]), 0)  # the gripper closed on robot 0
    for mask in (0b10, 0b10, 0, 0b10, 0):  # pressed, held (one press), released, again
        state.apply_report(bytes([3, mask, 0]), 0)
    assert state.mapper.switch_presses == 2
    assert state.intent(0).gripper_closed and not state.intent(0).clutch
    state.mapper.take_robot(Button.NONE)  # the next robot's gripper was left open
    assert not state.intent(0).gripper_closed
    state.mapper.take_robot(Button.GRIPPER_CLOSE | Button.CLUTCH)
    assert state.intent(0).gripper_closed and not state.intent(0).clutch  # no clutch role


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        (['gamepad.switch_buttons=["BTN_SOUTH"]'], "gripper_buttons and gamepad.switch"),
        (['spacemouse.switch_buttons=["BTN_1"]'], "clutch_buttons and spacemouse.switch"),
        (['gamepad.switch_buttons=["north"]'], "kernel button names"),
    ],
)
def test_a_button_has_one_role(settings, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, settings)


def test_spacemouse_through_relative_events_returns_to_zero():
    """The kernel drops zero REL events: a frame's missing translation axes are 0, and an
    axis left unreported for rel_hold_s reads 0."""
    config = SpaceMouseConfig()
    state = spacemouse(config)
    apply_frames(state, frame((EV_REL, REL_Y, -350), (EV_REL, REL_X, -350)), 0)
    x, y, _ = state.intent(0).velocity_fraction
    assert x > 0.7 and y > 0.7
    apply_frames(state, frame((EV_REL, REL_X, -350)), 1)  # Y was 0 in this report
    assert state.intent(1).velocity_fraction == (0.0, 1.0, 0.0)
    apply_frames(state, frame((EV_REL, REL_RX, 200)), 2)  # rotation leaves translation
    assert state.intent(2).velocity_fraction == (0.0, 1.0, 0.0)
    hold_ns = round(config.rel_hold_s * NS_PER_S)
    assert state.intent(1 + hold_ns - 1).moving
    assert not state.intent(1 + hold_ns).moving
    apply_frames(state, frame((EV_KEY, BTN_0, 1)), 3)
    assert state.intent(3).gripper_closed


def test_spacemouse_through_absolute_events_keeps_values_until_changed():
    state = spacemouse()
    apply_frames(state, frame((EV_ABS, ABS_Z, -350)), 0)
    assert state.intent(10 * NS_PER_S).velocity_fraction == (0.0, 0.0, 1.0)
    apply_frames(state, frame((EV_ABS, ABS_Z, 0)), 0)
    assert not state.intent(0).moving


def spacemouse(config: SpaceMouseConfig | None = None) -> SpaceMouseState:
    state = SpaceMouseState(config or SpaceMouseConfig())
    state.intent(0)  # at rest: armed
    return state


def apply_frames(state: SpaceMouseState, data: bytes, now_ns: int) -> None:
    for f in EventFramer().feed(data):
        state.apply_frame(f, now_ns)


# -- rumble ---------------------------------------------------------------------------------


def test_rumble_strength_follows_the_force():
    assert rumble_magnitude(0.2, 0.5, 8.0) == 0
    assert rumble_magnitude(4.0, 0.5, 8.0) == round(0.5 * 0xFFFF)
    assert rumble_magnitude(20.0, 0.5, 8.0) == 0xFFFF
    assert rumble_magnitude(float("nan"), 0.5, 8.0) == 0


def test_rumble_is_renewed_at_most_every_period_and_stops_at_once():
    config = GamepadConfig()
    schedule = RumbleSchedule(config)
    period_ns = round(config.rumble_period_s * NS_PER_S)
    assert schedule.step(0.0, 0) is None  # nothing playing, nothing to stop
    assert schedule.step(8.0, 0) == 0xFFFF
    assert schedule.step(4.0, period_ns - 1) is None
    assert schedule.step(4.0, period_ns) == round(0.5 * 0xFFFF)
    assert schedule.step(0.0, period_ns + 1) == 0  # stop now, not at the next period
    assert schedule.step(0.0, period_ns + 2) is None
    assert schedule.length_ms == 200


# -- discovery and the one-line errors ------------------------------------------------------

# Capability bitmaps as an Xbox pad (xpad) shows them in sysfs: the buttons SOUTH..THUMBR,
# the axes X..RZ and HAT0X/Y, and FF_RUMBLE among its effects.
XPAD_KEY_CAPS = "7cdb000000000000 0 0 0 0"
XPAD_ABS_CAPS = "3003f"


def fake_event_device(sys_root, dev_root, node, name, vendor, product, key="0", abs_caps="0"):
    device = sys_root / "class/input" / node / "device"
    (device / "id").mkdir(parents=True)
    (device / "capabilities").mkdir()
    (device / "name").write_text(name + "\n")
    (device / "id/vendor").write_text(f"{vendor:04x}\n")
    (device / "id/product").write_text(f"{product:04x}\n")
    (device / "capabilities/key").write_text(key + "\n")
    (device / "capabilities/abs").write_text(abs_caps + "\n")
    (dev_root / "input").mkdir(parents=True, exist_ok=True)
    (dev_root / "input" / node).write_bytes(b"")
    return dev_root / "input" / node


def fake_hidraw(sys_root, dev_root, node, name, vendor, product):
    device = sys_root / "class/hidraw" / node / "device"
    device.mkdir(parents=True)
    device.joinpath("uevent").write_text(
        f"DRIVER=hid-generic\nHID_ID=0003:{vendor:08X}:{product:08X}\nHID_NAME={name}\n"
        f"HID_PHYS=usb-0000:00:14.0-2/input0\nMODALIAS=hid:b0003g0001v{vendor:08X}p{product:08X}\n"
    )
    dev_root.mkdir(exist_ok=True)
    (dev_root / node).write_bytes(b"")
    return dev_root / node


@pytest.fixture
def roots(tmp_path):
    return tmp_path / "dev", tmp_path / "sys"


def test_capability_bitmaps_read_as_the_kernel_prints_them():
    keys = parse_capability_bitmap(XPAD_KEY_CAPS)
    assert keys >> BTN_SOUTH & 1 and keys >> BTN_TR & 1 and not keys >> BTN_0 & 1
    axes = parse_capability_bitmap(XPAD_ABS_CAPS)
    assert [a for a in range(64) if axes >> a & 1] == [0, 1, 2, 3, 4, 5, 0x10, 0x11]


def test_gamepad_found_by_its_joystick_link_first(roots):
    dev_root, sys_root = roots
    fake_event_device(sys_root, dev_root, "event2", "Keyboard", 0x046D, 0xC31C,
                      key="ffffffffffffffff", abs_caps="0")  # fmt: skip
    node = fake_event_device(sys_root, dev_root, "event11", "Microsoft X-Box 360 pad",
                             0x045E, 0x028E, XPAD_KEY_CAPS, XPAD_ABS_CAPS)  # fmt: skip
    other = fake_event_device(sys_root, dev_root, "event9", "Generic pad", 0x0079, 0x0006,
                              XPAD_KEY_CAPS, XPAD_ABS_CAPS)  # fmt: skip
    (dev_root / "input/by-id").mkdir()
    (dev_root / "input/by-id/usb-Microsoft_Controller-event-joystick").symlink_to("../event11")
    found = find_gamepads(dev_root, sys_root)
    assert [f.path for f in found] == [node, other]  # the link, then the scan (no keyboard)
    assert found[0].name == "Microsoft X-Box 360 pad" and found[0].interface == EVDEV
    assert find_gamepad(GamepadConfig(), dev_root, sys_root, lambda p: True).path == node


def test_gamepad_found_by_capabilities_without_a_link(roots):
    dev_root, sys_root = roots
    node = fake_event_device(sys_root, dev_root, "event4", "Sony Controller", 0x054C, 0x09CC,
                             XPAD_KEY_CAPS, XPAD_ABS_CAPS)  # fmt: skip
    spacemouse = fake_event_device(sys_root, dev_root, "event3", "3Dconnexion SpaceMouse",
                                   0x256F, 0xC635, "3ff0000000000000000000000000000000000000",
                                   "3f")  # fmt: skip
    assert spacemouse.exists()
    assert [f.path for f in find_gamepads(dev_root, sys_root)] == [node]


def test_no_gamepad_is_one_line_naming_it_the_reason_and_the_fix(roots):
    dev_root, sys_root = roots
    with pytest.raises(DeviceUnavailable) as caught:
        find_gamepad(GamepadConfig(), dev_root, sys_root, lambda p: True)
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith("gamepad: none found")
    assert "fix: plug it in" in message and "gamepad.device" in message


def test_a_configured_path_that_is_not_there_says_so(roots):
    dev_root, sys_root = roots
    missing = dev_root / "input/event99"
    with pytest.raises(DeviceUnavailable, match=r"event99: no such device; fix: plug it in"):
        find_gamepad(GamepadConfig(device=str(missing)), dev_root, sys_root)


def test_an_unreadable_gamepad_names_the_input_group(roots):
    dev_root, sys_root = roots
    fake_event_device(sys_root, dev_root, "event5", "Xbox Wireless Controller", 0x045E,
                      0x0B13, XPAD_KEY_CAPS, XPAD_ABS_CAPS)  # fmt: skip
    with pytest.raises(DeviceUnavailable) as caught:
        find_gamepad(GamepadConfig(), dev_root, sys_root, can_read=lambda p: False)
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith("Xbox Wireless Controller (")
    assert "not readable by this user" in message
    assert "sudo usermod -aG input $USER" in message and "log out and in again" in message


def test_spacemouse_found_through_hidraw_first_then_evdev(roots):
    dev_root, sys_root = roots
    fake_hidraw(sys_root, dev_root, "hidraw0", "Logitech USB Receiver", 0x046D, 0xC52B)
    fake_hidraw(sys_root, dev_root, "hidraw1", "3Dconnexion CadMouse", 0x256F, 0xC650)
    hidraw = fake_hidraw(sys_root, dev_root, "hidraw3", "3Dconnexion SpaceMouse Compact",
                         0x256F, 0xC635)  # fmt: skip
    navigator = fake_hidraw(sys_root, dev_root, "hidraw10", "3Dconnexion SpaceNavigator",
                            0x046D, 0xC626)  # fmt: skip
    evdev = fake_event_device(sys_root, dev_root, "event7", "3Dconnexion SpaceMouse Compact",
                              0x256F, 0xC635)  # fmt: skip
    found = find_spacemice(dev_root, sys_root)
    assert [(f.path, f.interface) for f in found] == [
        (hidraw, HIDRAW), (navigator, HIDRAW), (evdev, EVDEV)
    ]  # fmt: skip
    assert found[0].name == "3Dconnexion SpaceMouse Compact"
    readable_evdev = find_spacemouse(SpaceMouseConfig(), dev_root, sys_root,
                                     can_read=lambda p: p == evdev)  # fmt: skip
    assert readable_evdev.path == evdev


def test_an_unreadable_spacemouse_gives_the_udev_rule(roots):
    dev_root, sys_root = roots
    fake_hidraw(sys_root, dev_root, "hidraw2", "3Dconnexion SpaceMouse Pro Wireless",
                0x256F, 0xC632)  # fmt: skip
    with pytest.raises(DeviceUnavailable) as caught:
        find_spacemouse(SpaceMouseConfig(), dev_root, sys_root, can_read=lambda p: False)
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith("3Dconnexion SpaceMouse Pro Wireless (")
    assert "not readable by this user" in message
    assert UDEV_RULES_FILE == "/etc/udev/rules.d/99-spacemouse.rules" and UDEV_RULES_FILE in message
    assert 'KERNEL=="hidraw*", ATTRS{idVendor}=="256f", MODE="0660", GROUP="input"' in message
    assert "udevadm control --reload" in message and "usermod -aG input" in message


def test_a_logitech_id_spacemouse_rule_names_its_product(roots):
    dev_root, sys_root = roots
    fake_hidraw(sys_root, dev_root, "hidraw0", "3Dconnexion SpaceNavigator", 0x046D, 0xC626)
    with pytest.raises(DeviceUnavailable, match=r'idVendor}=="046d", ATTRS{idProduct}=="c626"'):
        find_spacemouse(SpaceMouseConfig(), dev_root, sys_root, can_read=lambda p: False)


def test_no_spacemouse_is_one_line(roots):
    dev_root, sys_root = roots
    fake_hidraw(sys_root, dev_root, "hidraw0", "Some keyboard", 0x046D, 0xC31C)
    with pytest.raises(DeviceUnavailable) as caught:
        find_spacemouse(SpaceMouseConfig(), dev_root, sys_root)
    message = str(caught.value)
    assert "\n" not in message and message.startswith("spacemouse: none found")
    assert "spacemouse.device" in message


def test_opening_a_node_that_is_no_event_device_is_one_line(roots):
    dev_root, sys_root = roots
    fake_event_device(sys_root, dev_root, "event4", "Pad", 0x054C, 0x09CC, XPAD_KEY_CAPS,
                      XPAD_ABS_CAPS)  # fmt: skip
    with pytest.raises(DeviceUnavailable, match=r"Pad \(.*event4\): not an input event device"):
        open_gamepad(GamepadConfig(), dev_root=dev_root, sys_root=sys_root)


# -- readers over real file descriptors -----------------------------------------------------


@pytest.fixture
def pipe():
    read_fd, write_fd = os.pipe()
    os.set_blocking(read_fd, False)
    yield read_fd, write_fd
    for fd in (write_fd,):
        try:
            os.close(fd)
        except OSError:
            pass


def test_gamepad_reader_decodes_what_a_pipe_carries(pipe):
    read_fd, write_fd = pipe
    with GamepadReader(read_fd, GamepadConfig(), XPAD_ABSINFO, name="pad") as reader:
        assert reader.read(0.0) == reader.intent() and not reader.intent().moving
        data = frame((EV_ABS, ABS_Y, -32768), (EV_KEY, BTN_SOUTH, 1))
        os.write(write_fd, data[:40])  # half a frame: nothing applies yet
        assert not reader.read(0.5).moving
        os.write(write_fd, data[40:])
        intent = reader.read(1.0)
        assert intent.velocity_fraction == (1.0, 0.0, 0.0) and intent.gripper_closed
        assert not reader.has_rumble
        reader.rumble(8.0)  # no rumble: nothing happens
        os.close(write_fd)
        with pytest.raises(DeviceUnavailable, match=r"^pad: disconnected"):
            reader.read(1.0)
    reader.close()  # twice is safe


def test_gamepad_reader_waits_no_longer_than_its_timeout(pipe):
    read_fd, _ = pipe
    clock = FakeClock()
    with GamepadReader(read_fd, GamepadConfig(), XPAD_ABSINFO, clock=clock) as reader:
        assert not reader.read(0.01).moving  # nothing written: returns after the timeout


def test_spacemouse_reader_reads_one_hid_report_per_read():
    """hidraw gives one report per read: a SOCK_SEQPACKET pair keeps the same boundaries."""
    reader_end, device_end = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    fd = os.dup(reader_end.fileno())
    reader_end.close()
    os.set_blocking(fd, False)
    try:
        with SpaceMouseReader(fd, SpaceMouseConfig(), HIDRAW, clock=FakeClock()) as reader:
            assert not reader.read(0.0).moving and reader.armed
            device_end.send(hid_report(1, 0, -350, 0))
            device_end.send(hid_report(2, 100, 0, 0))
            device_end.send(bytes([3, 1, 0]))
            intent = reader.read(1.0)
            while reader.state.reports < 3:
                intent = reader.read(1.0)
            assert intent.velocity_fraction == (1.0, 0.0, 0.0) and intent.gripper_closed
            device_end.send(hid_report(1, 0, 0, 0, 0, 0, 0))
            assert not reader.read(1.0).moving
    finally:
        device_end.close()


def test_spacemouse_reader_through_evdev_on_a_pipe(pipe):
    read_fd, write_fd = pipe
    clock = FakeClock(start_ns=NS_PER_S)
    config = SpaceMouseConfig()
    with SpaceMouseReader(read_fd, config, EVDEV, clock=clock) as reader:
        assert not reader.read(0.0).moving
        os.write(write_fd, frame((EV_REL, REL_Z, -350)))
        assert reader.read(1.0).velocity_fraction == (0.0, 0.0, 1.0)
        clock.advance(round(config.rel_hold_s * NS_PER_S))
        assert not reader.read(0.0).moving  # the release was never reported
        os.write(write_fd, event(EV_SYN, SYN_DROPPED, 0) + frame((EV_REL, REL_Z, -350)))
        assert not reader.read(1.0).moving  # discarded through the next report


def test_open_spacemouse_finds_and_reads_a_hidraw_node(roots):
    """Discovery in a fake sysfs, the node a FIFO standing in for /dev/hidrawN."""
    dev_root, sys_root = roots
    node = fake_hidraw(sys_root, dev_root, "hidraw4", "3Dconnexion SpaceMouse Wireless",
                       0x256F, 0xC62E)  # fmt: skip
    node.unlink()
    os.mkfifo(node)
    with open_spacemouse(SpaceMouseConfig(), dev_root=dev_root, sys_root=sys_root,
                         clock=FakeClock()) as reader:  # fmt: skip
        assert reader.interface == HIDRAW and reader.name.startswith("3Dconnexion")
        assert not reader.read(0.0).moving
        writer = os.open(node, os.O_WRONLY)
        try:
            os.write(writer, hid_report(1, -350, 0, 0))
            assert reader.read(1.0).velocity_fraction == (0.0, 1.0, 0.0)
        finally:
            os.close(writer)


def test_a_rumble_the_fd_cannot_take_is_switched_off_not_raised(pipe):
    """EVIOCSFF on something that is not an input device fails (ENOTTY): rumble is best
    effort and never stops control."""
    _, write_fd = pipe
    rumble = EvdevRumble(write_fd, GamepadConfig())
    rumble.set_force(8.0, 0)
    rumble.set_force(8.0, NS_PER_S)
    assert rumble.errors == 1 and rumble.effect_id == -1
