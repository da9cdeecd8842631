"""Property-based fuzzing (hypothesis) of every decoder and the receivers' acceptance logic.

Every record goes through the code that handles it on the wire (``deliver``, ``Inbound``,
the plant's admission, the event-ownership filter), never a copy of it. The examples are
derandomised (the same in every run, so CI cannot flake) and each test counts the
records it generated: together well over 100,000, well-formed hostile ones included
(extreme counters, stamps and values).
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from teleop.bus import graph
from teleop.bus import messages as m
from teleop.bus.session import deliver, owned_events
from teleop.bus.stamps import RESYNC_RECORDS, SEQ_WINDOW, Inbound
from teleop.core.clock import FakeClock
from teleop.core.config import load_config
from teleop.sim.pacing import TickPacer, make_pacer
from teleop.sim.plant import Plant

FUZZ = settings(
    deadline=None,
    database=None,  # no .hypothesis directory in the tree
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
U64_MAX = 2**64 - 1
I64_MAX = 2**63 - 1
RECORD_SCHEMAS = [s for s in m.SCHEMAS.values() if not isinstance(s, m.FrameSchema)]


# -- decoders -----------------------------------------------------------------------------


def _float_pool(field: m.Field) -> np.ndarray:
    lo = -m.F64_MAX if field.lo is None else field.lo
    hi = m.F64_MAX if field.hi is None else field.hi
    with np.errstate(over="ignore"):  # one step beyond F64_MAX is infinity: wanted
        return _pool(lo, hi)


def _pool(lo: float, hi: float) -> np.ndarray:
    return np.array(
        [0.0, lo, hi, np.nextafter(lo, -np.inf), np.nextafter(hi, np.inf), np.nan, np.inf,
         -np.inf, m.F64_MAX, -m.F64_MAX, 1e300, -1e-300, 0.5 * (lo + hi)]
    )  # fmt: skip


def _int_pool(field: m.Field, dtype: np.dtype) -> np.ndarray:
    info = np.iinfo(dtype)
    values = [0, 1, info.max, info.min, info.max // 2]
    for bound in (field.lo, field.hi):
        if bound is not None:
            values += [int(bound), int(bound) + 1, max(int(bound) - 1, info.min)]
    return np.array([min(max(v, info.min), info.max) for v in values], dtype=dtype)


def hostile_records(schema: m.Schema, rng: np.random.Generator, n: int) -> list[bytes]:
    """``n`` buffers for ``schema``: mostly well-formed records whose every field takes
    an extreme value, valid or not (limits, one step beyond, NaN, infinities, the ends of
    the integer ranges), some with a wrong version or kind, some random bytes of a
    size near the record's."""
    buffers = []
    for _ in range(n):
        roll = rng.random()
        if roll < 0.1:
            size = schema.size + int(rng.integers(-2, 3))
            buffers.append(rng.bytes(max(size, 0)))
            continue
        rec = schema.new()
        for field in schema.fields:
            if field.name in ("version", "kind"):
                continue
            column = rec[field.name]
            shape = column.shape
            if field.is_float:
                pool = _float_pool(field)
                values = pool[rng.integers(0, len(pool), size=shape)]
                plain = rng.random(size=shape) < 0.6  # most elements ordinary
                values = np.where(plain, 0.5 * (np.nan_to_num(pool[-1])), values)
            else:
                pool = _int_pool(field, column.dtype)
                values = pool[rng.integers(0, len(pool), size=shape)]
            rec[field.name] = values
        if roll > 0.95:
            rec["version"] = int(rng.integers(0, 2**16))
        elif roll > 0.9:
            rec["kind"] = int(rng.integers(0, 2**16))
        buffers.append(rec.tobytes())
    return buffers


def valid(schema: m.Schema, buf: bytes) -> bool:
    """The oracle: the declared rules of docs/protocol.md, checked field by field."""
    if len(buf) != schema.size:
        return False
    rec = np.frombuffer(buf, dtype=schema.dtype)[0]
    if int(rec["version"]) != schema.version or int(rec["kind"]) != schema.kind:
        return False
    for field in schema.fields:
        values = np.asarray(rec[field.name], dtype=np.float64 if field.is_float else object)
        if field.is_float and not np.isfinite(values).all():
            return False
        flat = values.reshape(-1).tolist()
        if field.lo is not None and any(v < field.lo for v in flat):
            return False
        if field.hi is not None and any(v > field.hi for v in flat):
            return False
    return True


def test_every_decoder_takes_exactly_the_valid_records_and_counts_the_rest():
    generated = [0]

    @settings(FUZZ, max_examples=200)
    @given(
        schema=st.sampled_from(RECORD_SCHEMAS),
        seed=st.integers(0, 2**32 - 1),
        n=st.integers(100, 300),
    )
    def check(schema: m.Schema, seed: int, n: int) -> None:
        buffers = hostile_records(schema, np.random.default_rng(seed), n)
        drops, taken = m.DropCounter(), []
        for buf in buffers:
            deliver(buf, 1, schema, lambda rec, rx_ns: taken.append(rec.tobytes()), drops)
        expected = [buf for buf in buffers if valid(schema, buf)]
        assert taken == expected
        assert drops.total == len(buffers) - len(expected)
        generated[0] += len(buffers)

    check()
    assert generated[0] >= 30_000


def test_an_eye_view_frame_is_taken_only_whole():
    generated = [0]

    @settings(FUZZ, max_examples=200)
    @given(
        width=st.integers(0, 70_000),
        height=st.integers(0, 70_000),
        channels=st.integers(0, 255),
        tail=st.integers(0, 4096),
    )
    def check(width: int, height: int, channels: int, tail: int) -> None:
        rec = m.EYE_VIEW.new()
        rec["width_px"], rec["height_px"] = width % 2**16, height % 2**16
        rec["channels"] = channels
        buf = rec.tobytes() + bytes(tail)
        announced = int(rec["width_px"]) * int(rec["height_px"]) * channels
        try:
            _, pixels = m.EYE_VIEW.decode_frame(buf)
        except m.DecodeError:
            whole = announced == tail and valid(m.EYE_VIEW, buf[: m.EYE_VIEW.size])
            assert not whole
        else:
            assert pixels.size == tail == announced
        generated[0] += 1

    check()
    assert generated[0] == 200


# -- the receivers' sequence and freshness checks -----------------------------------------

NOW_NS = 10**15


@st.composite
def hostile_stream(draw: st.DrawFn) -> list[tuple[bool, int, int]]:
    """(hostile, seq, stamp) records: a producer's stream (seq + 1 to + 3, fresh stamps)
    with single hostile records between (at least RESYNC_RECORDS + 1 of the producer's
    apart: a sustained attack is for access control to stop), whose seq and stamp are
    anything."""
    n = draw(st.integers(50, 400))
    records, seq, since_hostile = [], draw(st.integers(0, 10)), RESYNC_RECORDS + 1
    for _ in range(n):
        since_hostile += 1
        if since_hostile > RESYNC_RECORDS + 1 and draw(st.booleans()):
            since_hostile = 0
            hostile_seq = draw(
                st.one_of(
                    st.just(U64_MAX),
                    st.just(0),
                    st.integers(0, U64_MAX),
                    st.integers(max(seq - 5, 0), seq + SEQ_WINDOW + 5),
                )
            )
            stamp = draw(st.one_of(st.integers(-(2**63), I64_MAX), st.just(NOW_NS + 10**9)))
            records.append((True, hostile_seq, stamp))
        seq += draw(st.integers(1, 3))
        records.append((False, seq, NOW_NS - draw(st.integers(0, 10**6))))
    return records


def test_no_single_hostile_record_locks_out_a_producer_and_every_rejection_is_counted():
    generated = [0]

    @settings(FUZZ, max_examples=300)
    @given(stream=hostile_stream())
    def check(stream: list[tuple[bool, int, int]]) -> None:
        inbound = Inbound(m.Stage.CONTROLLER_TX, name="fuzz")
        rec = m.JOINT_COMMAND.new()
        accepted, rejected_run, last_taken = 0, 0, -1
        for hostile, seq, stamp in stream:
            rec["seq"], rec["trace_ns"][m.Stage.CONTROLLER_TX] = seq, stamp
            taken = inbound.accept(rec, NOW_NS)
            accepted += taken
            if not hostile:
                rejected_run = 0 if taken else rejected_run + 1
                # a hostile seq just above the producer's costs it a few records at most
                assert rejected_run <= RESYNC_RECORDS
            if taken:
                assert seq > last_taken or inbound.seq.restarts > 0
                last_taken = seq
        counts = inbound.counts()
        rejected = counts["reordered"] + counts["jumps"] - counts["restarts"]
        assert accepted + rejected + counts["shed"] + counts["future_stamps"] == len(stream)
        assert counts["lost"] <= SEQ_WINDOW * accepted  # a sender moves it a window at most
        generated[0] += len(stream)

    check()
    assert generated[0] >= 30_000


# -- run events: only from their owner's stream -------------------------------------------


def test_a_run_event_is_taken_only_on_its_owners_stream():
    @settings(FUZZ, max_examples=300)
    @given(
        event=st.sampled_from(list(m.Event)),
        stream=st.sampled_from(["plant_events", "operator_events"]),
        step=st.integers(0, U64_MAX),
    )
    def check(event: m.Event, stream: str, step: int) -> None:
        rec = m.RUN_EVENT.new()
        rec["event"], rec["step"] = event, step
        drops, taken = m.DropCounter(), []
        take = owned_events(stream, lambda rec, rx_ns: taken.append(rec), drops)
        deliver(rec.tobytes(), 1, m.RUN_EVENT, take, drops)
        owner = graph.EVENT_STREAM[event] == stream
        assert len(taken) == int(owner) and drops.total == int(not owner)
        if not owner:
            assert drops.counts() == {(int(m.Kind.RUN_EVENT), m.Reason.SOURCE.value): 1}

    check()


# -- the plant: admission and its own limits ----------------------------------------------


def test_the_plant_admits_its_controller_through_hostile_commands():
    config = load_config(None, ['run.mode="realtime"'])
    generated = [0]

    @settings(FUZZ, max_examples=25)
    @given(
        seed=st.integers(0, 2**32 - 1),
        hostile=st.lists(
            st.tuples(
                st.one_of(st.just(U64_MAX), st.integers(0, U64_MAX), st.integers(0, 300)),
                st.one_of(st.just(U64_MAX), st.integers(0, U64_MAX), st.integers(0, 300)),
                st.one_of(st.integers(-(2**63), I64_MAX), st.just(0)),
            ),
            min_size=20,
            max_size=60,
        ),
    )
    def check(seed: int, hostile: list[tuple[int, int, int]]) -> None:
        """One hostile command every RESYNC_RECORDS + 2 cycles (a sustained attack is for
        access control to stop), the controller's own every cycle."""
        clock = FakeClock(start_ns=NOW_NS)
        pacer = make_pacer(config, _Discard(), clock)
        assert isinstance(pacer, TickPacer)
        core = pacer.core
        core.begin_run(None)
        pacer.start()
        rng = np.random.default_rng(seed)
        rejected_run = 0
        cycles = len(hostile) * (RESYNC_RECORDS + 2)
        for k in range(cycles):
            seq, state_seq, stamp = hostile[k // (RESYNC_RECORDS + 2)]
            bad = m.JOINT_COMMAND.new()
            bad["seq"], bad["state_seq"] = seq, state_seq
            bad["trace_ns"][m.Stage.CONTROLLER_TX] = stamp
            bad["n_joints"] = 6
            bad["qd_ref_rad_s"][:6] = rng.uniform(-math.pi, math.pi, 6)
            good = m.JOINT_COMMAND.new()
            good["seq"], good["state_seq"] = k + 1, core.state_seq
            good["trace_ns"][m.Stage.CONTROLLER_TX] = clock.now_ns()
            good["n_joints"] = 6
            good["qd_ref_rad_s"][:6] = 0.05
            if k % (RESYNC_RECORDS + 2) == 0:
                pacer.on_command(bad, clock.now_ns())
            pacer.on_command(good, clock.now_ns())
            newest = pacer.commands.get()
            admitted = newest is not None and int(newest[0]["seq"]) == k + 1
            rejected_run = 0 if admitted else rejected_run + 1
            assert rejected_run <= RESYNC_RECORDS
            clock.advance(1_000_000)
            pacer.tick()
        assert core.commands_received == cycles + len(hostile)
        generated[0] += cycles + len(hostile)

    check()
    assert generated[0] >= 2_000


class _Discard:
    """PlantOutputs that drop everything (the plant's records are not under test)."""

    def put(self, stream: str, rec: np.ndarray) -> bytes:
        return b""

    def put_bytes(self, stream: str, data: bytes) -> None:
        pass

    def flush(self) -> None:
        pass


def test_the_plant_holds_any_command_to_the_robots_limits():
    config = load_config()
    plant = Plant(config)
    cap_m_s = config.plant.tool_speed_limit_m_s

    @settings(FUZZ, max_examples=300)
    @given(
        q=st.lists(st.floats(-math.pi, math.pi), min_size=6, max_size=6),
        qd=st.lists(
            st.floats(-m.JOINT_COMMAND_SPEED_LIMIT_RAD_S, m.JOINT_COMMAND_SPEED_LIMIT_RAD_S),
            min_size=6,
            max_size=6,
        ),
    )
    def check(q: list[float], qd: list[float]) -> None:
        plant.reset(np.array(q))
        slowed = plant.approach_slowed_steps
        limited = plant.limit(np.array(qd))
        assert np.all(limited >= plant.ctrl_low) and np.all(limited <= plant.ctrl_high)
        hold = plant.data.qfrc_bias[plant.dof_index] / plant.kv  # what holds the arm still
        speed = np.linalg.norm(plant.tool_jacobian() @ (limited - hold))
        assert speed <= cap_m_s * (1 + 1e-9)
        if plant.approach_slowed_steps > slowed:  # near the scene: the motion slowed down
            asked = np.clip(qd, plant.ctrl_low, plant.ctrl_high) - hold
            assert np.linalg.norm(limited - hold) <= np.linalg.norm(asked) * (1 + 1e-9)
        elif speed < cap_m_s * (1 - 1e-9):  # not cut: exactly what was asked
            assert np.array_equal(limited, np.array(qd))

    check()
