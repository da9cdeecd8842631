"""Message schemas: layout, round trip, every rejection reason, drop counting, docs."""

from __future__ import annotations

import logging
import struct
from pathlib import Path

import numpy as np
import pytest

from teleop.bus import messages as m
from teleop.bus.topics import Topics

PROTOCOL_DOC = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"
LAYOUT_BEGIN = "<!-- layout_table() begin -->"
LAYOUT_END = "<!-- layout_table() end -->"

ALL = list(m.SCHEMAS.values())
IDS = [s.kind.name for s in ALL]


def _filled(schema: m.Schema, rng: np.random.Generator) -> np.ndarray:
    """A valid record with every float inside its limits and counts at their maximum."""
    rec = schema.new()
    rec["seq"] = 123
    rec["t_source_ns"] = 456
    rec["trace_ns"][m.Stage.PLANT_STATE_TX] = 789
    for f in schema.fields[len(m.HEADER_FIELDS) :]:
        if f.is_float:
            lo = -1.0 if f.lo is None else max(f.lo, -1.0)
            hi = 1.0 if f.hi is None else min(f.hi, 1.0)
            rec[f.name] = rng.uniform(lo, hi, size=f.shape)
        elif f.hi is not None:
            rec[f.name] = f.hi
        else:
            rec[f.name] = 3
    if isinstance(schema, m.FrameSchema):  # a small image: the pixel tail stays tiny
        rec["width_px"], rec["height_px"] = 4, 2
    return rec


def _wire(schema: m.Schema, rec: np.ndarray) -> bytes:
    """The bytes a producer sends: the record, plus the pixels for a frame kind."""
    if isinstance(schema, m.FrameSchema):
        shape = (int(rec["height_px"]), int(rec["width_px"]), int(rec["channels"]))
        return schema.encode_frame(rec, np.arange(np.prod(shape), dtype=np.uint8).reshape(shape))
    return schema.encode(rec)


def test_header_layout_is_fixed():
    assert m.HEADER_SIZE == 104
    offsets = {name: m.HEADER_DTYPE.fields[name][1] for name in m.HEADER_DTYPE.names}
    assert offsets == {
        "version": 0,
        "kind": 2,
        "flags": 4,
        "seq": 8,
        "t_source_ns": 16,
        "trace_ns": 24,
    }
    assert len(m.Stage) == m.N_STAGES


def test_every_field_is_naturally_aligned_and_little_endian():
    for schema in ALL:
        for name in schema.dtype.names:
            sub, offset = schema.dtype.fields[name][:2]
            base = sub.base if sub.shape else sub
            assert offset % base.itemsize == 0, (schema, name)
            assert base.str[0] in ("<", "|"), (schema, name)  # "=" would be host order


def test_kinds_are_unique_and_registered():
    assert set(m.SCHEMAS) == set(m.Kind)
    assert all(m.SCHEMAS[k].kind is k for k in m.Kind)
    assert not set(m.RETIRED_KINDS) & {int(k) for k in m.Kind}  # retired values stay unused


@pytest.mark.parametrize("schema", ALL, ids=IDS)
def test_round_trip(schema: m.Schema):
    rec = _filled(schema, np.random.default_rng(0))
    buf = _wire(schema, rec)
    assert len(buf) == schema.size + (
        schema.pixel_bytes(rec) if schema.kind == m.Kind.EYE_VIEW else 0
    )
    out = schema.decode(buf)
    assert out.tobytes() == buf[: schema.size]
    assert int(out["version"]) == m.PROTOCOL_VERSION and int(out["kind"]) == schema.kind
    assert m.peek_kind(buf) == schema.kind
    assert not out.flags.writeable  # a view of the received bytes, not a copy
    assert schema.decode(memoryview(bytearray(buf))).tobytes() == buf[: schema.size]


def test_frame_pixels_round_trip_and_a_wrong_tail_is_dropped():
    rec = _filled(m.EYE_VIEW, np.random.default_rng(1))
    buf = _wire(m.EYE_VIEW, rec)
    out, pixels = m.EYE_VIEW.decode_frame(buf)
    assert pixels.shape == (2, 4, 3) and not pixels.flags.writeable
    assert pixels.tobytes() == buf[m.EYE_VIEW.size :]
    assert out.tobytes() == rec.tobytes()
    for bad in (buf[:-1], buf + b"\0", buf[: m.EYE_VIEW.size], buf[:10]):
        _expect(m.EYE_VIEW, bad, m.Reason.SIZE)
    rec["channels"] = 4  # only RGB
    _expect(m.EYE_VIEW, m.EYE_VIEW.encode(rec) + bytes(32), m.Reason.COUNT)
    with pytest.raises(ValueError):
        m.EYE_VIEW.encode_frame(rec, np.zeros((2, 4, 3), np.uint8))


def test_header_values_are_little_endian_on_the_wire():
    rec = m.PLANT_STATE.new()
    rec["seq"] = 0x0102030405060708
    rec["flags"] = m.Flag.BRAKING
    buf = m.PLANT_STATE.encode(rec)
    version, kind, flags, seq = struct.unpack_from("<HHIQ", buf, 0)
    assert (version, kind, flags, seq) == (
        m.PROTOCOL_VERSION,
        m.Kind.PLANT_STATE,
        1,
        0x0102030405060708,
    )


def test_encode_rejects_a_record_of_another_kind():
    with pytest.raises(TypeError):
        m.PLANT_STATE.encode(m.JOINT_COMMAND.new())


def _expect(schema: m.Schema, buf: bytes, reason: m.Reason) -> m.DecodeError:
    with pytest.raises(m.DecodeError) as info:
        schema.decode(buf)
    assert info.value.reason is reason and info.value.kind is schema.kind
    return info.value


def test_rejects_wrong_size_version_kind():
    good = m.PLANT_STATE.encode(m.PLANT_STATE.new())
    _expect(m.PLANT_STATE, good[:-1], m.Reason.SIZE)
    _expect(m.PLANT_STATE, good + b"\0", m.Reason.SIZE)
    _expect(m.PLANT_STATE, b"", m.Reason.SIZE)
    _expect(m.PLANT_STATE, struct.pack("<H", m.PROTOCOL_VERSION + 1) + good[2:], m.Reason.VERSION)
    wrong_kind = struct.pack("<HH", m.PROTOCOL_VERSION, m.Kind.TOOL_POSE) + good[4:]
    _expect(m.PLANT_STATE, wrong_kind, m.Reason.KIND)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("schema", ALL, ids=IDS)
def test_rejects_non_finite_in_every_float_field(schema: m.Schema, value: float):
    rng = np.random.default_rng(0)
    for f in schema.fields:
        if not f.is_float:
            continue
        rec = _filled(schema, rng)
        rec[f.name].flat[-1] = value  # the last element of arrays: padding is checked too
        err = _expect(schema, schema.encode(rec), m.Reason.NON_FINITE)
        assert err.detail == f.name


@pytest.mark.parametrize(
    ("schema", "name", "value"),
    [
        (m.PLANT_STATE, "q_rad", 1.0e6 + 1.0),
        (m.PLANT_STATE, "qd_rad_s", -101.0),
        (m.JOINT_COMMAND, "qd_ref_rad_s", 1e3),
        (m.JOINT_COMMAND, "gripper_cmd", 1.01),
        (m.JOINT_COMMAND, "gripper_cmd", -0.01),
        (m.TOOL_POSE, "world_p_tool_m", 1e3),
        (m.TOOL_POSE, "world_q_tool_wxyz", 1.5),
        (m.PLANT_STATE, "world_f_contact_n", 2e6),
        (m.PLANT_STATE, "held_mass_kg", -0.1),
        (m.PLANT_STATE, "world_n_away", 1.5),
        (m.OBJECT_POSES, "world_p_m", -200.0),
        (m.CONTROL_STATUS, "path_error_m", -1.0),
        (m.CONTROL_STATUS, "manipulability", -1e-3),
    ],
)
def test_rejects_values_outside_limits(schema: m.Schema, name: str, value: float):
    rec = schema.new()
    rec[name].flat[0] = value
    err = _expect(schema, schema.encode(rec), m.Reason.RANGE)
    assert name in err.detail


def test_limits_are_inclusive():
    rec = m.JOINT_COMMAND.new()
    rec["gripper_cmd"] = 1.0
    rec["qd_ref_rad_s"][:] = -m.JOINT_COMMAND_SPEED_LIMIT_RAD_S
    rec["n_joints"] = m.MAX_JOINTS
    m.JOINT_COMMAND.decode(m.JOINT_COMMAND.encode(rec))


@pytest.mark.parametrize(
    ("schema", "count", "maximum"),
    [
        (m.PLANT_STATE, "n_joints", m.MAX_JOINTS),
        (m.JOINT_COMMAND, "n_joints", m.MAX_JOINTS),
        (m.OBJECT_POSES, "n_objects", m.MAX_OBJECTS),
    ],
)
def test_rejects_counts_above_max(schema: m.Schema, count: str, maximum: int):
    rec = schema.new()
    rec[count] = maximum + 1
    _expect(schema, schema.encode(rec), m.Reason.COUNT)


def test_drop_counter_counts_per_kind_and_reason_and_logs_once_per_kind(caplog):
    drops = m.DropCounter()
    bad_size = b"\0" * 3
    with caplog.at_level(logging.WARNING, logger="teleop.bus.messages"):
        for _ in range(5):
            try:
                m.PLANT_STATE.decode(bad_size)
            except m.DecodeError as err:
                drops.record(err)
        rec = m.PLANT_STATE.new()
        rec["q_rad"][0] = np.nan
        try:
            m.PLANT_STATE.decode(rec.tobytes())
        except m.DecodeError as err:
            drops.record(err)
        drops.record(m.DecodeError(m.Kind.TOOL_POSE, m.Reason.VERSION))
    assert drops.counts() == {
        (int(m.Kind.PLANT_STATE), "size"): 5,
        (int(m.Kind.PLANT_STATE), "non_finite"): 1,
        (int(m.Kind.TOOL_POSE), "version"): 1,
    }
    assert drops.total == 7
    assert len(caplog.records) == 2  # one per kind, not per drop


def test_topics_registry():
    t = Topics("arm1")
    assert t.plant_state == "teleop/arm1/state/plant"
    assert t.tool_pose == "teleop/arm1/state/tool_pose"
    assert t.objects == "teleop/arm1/state/objects"
    assert t.joint_command == "teleop/arm1/cmd/joint_velocity"
    assert t.control_status == "teleop/arm1/control/status"
    assert t.alive("plant") == "teleop/arm1/alive/plant"
    assert t.alive_all == "teleop/arm1/alive/*"
    assert t.service_of(t.alive("plant")) == "plant"
    with pytest.raises(ValueError):
        Topics("a/b")
    with pytest.raises(ValueError):
        t.alive("x/y")


def test_protocol_doc_embeds_the_current_layout_table():
    text = PROTOCOL_DOC.read_text()
    begin = text.index(LAYOUT_BEGIN) + len(LAYOUT_BEGIN)
    end = text.index(LAYOUT_END)
    assert text[begin:end].strip() == m.layout_table().strip(), (
        "docs/protocol.md is stale: paste `python -m teleop.bus.messages` between the markers"
    )


def test_a_continuous_joint_many_turns_round_is_a_valid_state():
    """The shoulder_pan joint has no limits: on the paper's path it turns once per lap
    (about 0.29 rad/s), 100 rad after six minutes of `teleop up`; such a state is valid."""
    rec = m.PLANT_STATE.new()
    rec["q_rad"][0] = -0.29 * 3600.0  # an hour of laps
    assert m.PLANT_STATE.decode(m.PLANT_STATE.encode(rec))["q_rad"][0] == rec["q_rad"][0]
