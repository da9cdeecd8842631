"""A haptic device that takes the place of the stack's own, from outside. Written from
docs/protocol.md alone (nothing from the teleop package). Start the grasp scenario
without its haptic service; it prints the Zenoh config file to use:

    teleop run grasp --without haptic
    python examples/outside_haptic.py runs/latest/outside/haptic.json5

`Handle` has the methods of the project's device interface (a driver for a real device
fills them with its hardware calls). It emulates a Falcon-like handle: a damped 0.15 kg
mass pulled by a hand (a spring-damper towards where the hand is) and pushed by the
feedback force. The hand is the scripted operator's: it publishes HAND_INPUT (where it
pulls, which buttons). Its servo runs every millisecond: it renders the newest
FORCE_FEEDBACK's local contact model (the force at a reference handle position plus its
stiffness about it) at the handle's position, and once per bus period (the stack's
loop rate, the config file's metadata/loop_rate_hz) it publishes HAPTIC_STATE; at the
plant's FINISHED event it prints a summary and exits.
"""

import argparse
import json
import struct
import threading
import time
from collections.abc import Callable

import numpy as np
import zenoh

# -- the wire format (docs/protocol.md, "Records") --------------------------------------
VERSION = 8
# How long to wait for a first link to the stack before giving up (s).
LINK_TIMEOUT_S = 10.0
HEADER = struct.Struct("<HHIQq10q")  # version, kind, flags, seq, t_source_ns, trace_ns[10]
HAPTIC_STATE, HAND_INPUT, FORCE_FEEDBACK, RUN_EVENT = 8, 9, 10, 7  # kinds
HAND_INPUT_SIZE, FORCE_FEEDBACK_SIZE, RUN_EVENT_SIZE = 137, 408, 130
# sim_time_ns, tick, device_deadline_ns, p, v, f, passivity_observed_j,
# passivity_dissipated_j, wave_u (3: zero, no wave variables here), buttons
STATE_BODY = struct.Struct("<qQq14dB")
STALE, FINISHED = 2, 2  # HAPTIC_STATE flag: an old force fades out; RUN_EVENT code
BATCH_RECORDS = 10  # the recorder's batched copy: this many records per message

# -- the device --------------------------------------------------------------------------
PERIOD_S = 0.001  # servo period: 1 kHz
DEFAULT_BUS_RATE_HZ = 250.0  # the stack's loop.rate_hz unless its config file says
MASS_KG, DAMPING_N_S_PER_M = 0.15, 3.0  # the handle, and its own viscous damping
HAND_STIFFNESS_N_PER_M, HAND_DAMPING_N_S_PER_M = 200.0, 8.0  # the hand holding it
WORKSPACE_HALF_M, PEAK_FORCE_N = 0.05, 8.0  # end stops at +-5 cm per axis; motors' peak
STALE_AFTER_S, FADE_S = 0.020, 0.020  # older feedback fades out to zero over FADE_S


class OtherVersion(Exception):
    """A record of another protocol version: nothing the stack sends can be read here."""


def valid(sample: zenoh.Sample, kind: int, size: int) -> bytes | None:
    """The record's bytes if it is one of ``kind`` of our version and size, else None;
    OtherVersion for a record of another version."""
    data = sample.payload.to_bytes()
    if len(data) < HEADER.size:
        return None
    version, own_kind = HEADER.unpack_from(data)[:2]
    if version != VERSION:
        raise OtherVersion(version)
    return data if len(data) == size and own_kind == kind else None


class Handle:
    """Device interface: connect, read, send_force, next_sample, reset, disconnect.
    Device frame: x forward, y left, z up, origin at the workspace centre; m, m/s, N."""

    period_s = PERIOD_S

    def __enter__(self) -> "Handle":
        self.connect()
        return self

    def __exit__(self, *exc_info) -> None:
        self.disconnect()

    def connect(self) -> None:  # a driver: open the link, motors on at zero force
        self.reset()

    def disconnect(self) -> None:  # a driver: motors to zero force, close the link
        self.force_n = np.zeros(3)

    def reset(self) -> None:  # a new run: handle at the centre, at rest
        self.p_m, self.v_m_s, self.force_n, self.buttons = np.zeros(3), np.zeros(3), np.zeros(3), 0

    def send_force(self, force_n: np.ndarray) -> None:
        norm = np.linalg.norm(force_n)
        self.force_n = force_n * min(1.0, PEAK_FORCE_N / norm) if norm > 0 else np.zeros(3)

    def read(self) -> tuple:
        return self.p_m.copy(), self.v_m_s.copy(), self.force_n.copy(), self.buttons

    def next_sample(self, hand: tuple | None) -> tuple:
        """One period under ``hand`` = (target_p_m, buttons), or None (let go): damping
        implicit, springs semi-implicit (velocity first), end stops inelastic."""
        force, damping = self.force_n.copy(), DAMPING_N_S_PER_M
        if hand is not None:
            force += HAND_STIFFNESS_N_PER_M * (hand[0] - self.p_m)
            damping += HAND_DAMPING_N_S_PER_M
            self.buttons = hand[1]
        dt = self.period_s
        self.v_m_s = (self.v_m_s + dt / MASS_KG * force) / (1.0 + dt * damping / MASS_KG)
        self.p_m = np.clip(self.p_m + dt * self.v_m_s, -WORKSPACE_HALF_M, WORKSPACE_HALF_M)
        self.v_m_s[np.abs(self.p_m) >= WORKSPACE_HALF_M] = 0.0
        return self.read()


class OutsideHaptic:
    """The bus side: feedback and hand inputs in, a HAPTIC_STATE per period out."""

    def __init__(self, session: zenoh.Session, robot: str, device: Handle) -> None:
        self.device, self.lock, self.finished = device, threading.Lock(), threading.Event()
        self.tick, self.sim_time_ns, self.feedback_rx_ns = 0, 0, None  # newest feedback's
        self.feedback_n, self.hands, self.batch = np.zeros(3), {}, []  # hands: by valid_from
        self.p_ref_m, self.k_n_per_m = np.zeros(3), np.zeros((3, 3))  # the local model
        self.seq = self.stale_periods = self.skipped_periods = 0
        self.observed_j = 0.0  # passivity observer: energy the force took from the hand
        self.other_version = None  # the stack's protocol version, if not ours
        key = f"teleop/{robot}"
        self.pub = session.declare_publisher(
            f"{key}/haptic/state", priority=zenoh.Priority.REAL_TIME, express=True,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )  # fmt: skip
        self.batch_pub = session.declare_publisher(f"{key}/haptic/state/batch")  # recorder's
        self.subs = [session.declare_subscriber(f"{key}/{stream}", self.checked(callback))
                     for stream, callback in (("haptic/feedback", self.on_feedback),
                                              ("operator/hand", self.on_hand),
                                              ("events/plant", self.on_event))]  # fmt: skip

    def checked(self, callback: Callable[[zenoh.Sample], None]) -> Callable[[zenoh.Sample], None]:
        """``callback``, ending the run at a record of another protocol version."""

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                callback(sample)
            except OtherVersion as exc:
                self.other_version = exc.args[0]
                self.finished.set()

        return on_sample

    def on_feedback(self, sample: zenoh.Sample) -> None:
        if (data := valid(sample, FORCE_FEEDBACK, FORCE_FEEDBACK_SIZE)) is None:
            return
        sim_time_ns, tick = struct.unpack_from("<qQ", data, 104)
        with self.lock:
            if tick >= self.tick:  # not older than the force the handle already feels
                self.tick, self.sim_time_ns = tick, sim_time_ns
                self.feedback_n = np.frombuffer(data, "<f8", 3, 120).copy()
                self.p_ref_m = np.frombuffer(data, "<f8", 3, 312).copy()
                self.k_n_per_m = np.frombuffer(data, "<f8", 9, 336).reshape(3, 3).copy()
                self.feedback_rx_ns = time.monotonic_ns()

    def on_hand(self, sample: zenoh.Sample) -> None:
        if (data := valid(sample, HAND_INPUT, HAND_INPUT_SIZE)) is None:
            return
        valid_from = struct.unpack_from("<Q", data, 104)[0]
        with self.lock:
            self.hands[valid_from] = (np.frombuffer(data, "<f8", 3, 112).copy(), data[136])
            self.hands = dict(sorted(self.hands.items())[-64:])  # the newest 64

    def on_event(self, sample: zenoh.Sample) -> None:
        data = valid(sample, RUN_EVENT, RUN_EVENT_SIZE)
        if data is not None and struct.unpack_from("<H", data, 128)[0] == FINISHED:
            self.finished.set()

    def step(self, deadline_ns: int, publish: bool) -> None:
        """One servo period (begun at ``deadline_ns``) under the newest inputs; with
        ``publish``, the HAPTIC_STATE of the bus period that begins with it."""
        with self.lock:
            flags, rx_ns = 0, self.feedback_rx_ns
            overdue_s = (time.monotonic_ns() - (rx_ns or 0)) * 1e-9 - STALE_AFTER_S
            fade = 1.0
            if rx_ns is not None and overdue_s > 0:
                flags, self.stale_periods = STALE, self.stale_periods + 1
                fade = max(0.0, 1 - overdue_s / FADE_S)
            # The local model at the handle's position now, faded out when stale.
            model_n = self.feedback_n + self.k_n_per_m @ (self.device.p_m - self.p_ref_m)
            self.device.send_force(model_n * fade)
            hand = max((k for k in self.hands if k <= self.tick), default=None)  # applies now
            p, v, f, buttons = self.device.next_sample(self.hands.get(hand))
            # The energy the force took from the hand, net (no controller here: none dissipated).
            self.observed_j -= sum(fi * vi for fi, vi in zip(f, v, strict=True)) * PERIOD_S
            if not publish:
                return
            body = STATE_BODY.pack(
                self.sim_time_ns,
                self.tick,
                deadline_ns,
                *p,
                *v,
                *f,
                self.observed_j,
                0.0,
                0.0,
                0.0,
                0.0,
                buttons,
            )
        self.seq += 1
        now_ns = time.monotonic_ns()
        trace = [now_ns] + [0] * 9  # HAPTIC_SAMPLE: the controller measures the age from it
        record = HEADER.pack(VERSION, HAPTIC_STATE, flags, self.seq, now_ns, *trace) + body
        self.pub.put(record)
        self.batch.append(record)
        if len(self.batch) == BATCH_RECORDS:
            self.batch_pub.put(b"".join(self.batch))
            self.batch = []

    def run(self, servo_per_bus: int) -> float:
        """Step on absolute deadlines until FINISHED, skipping (not bursting) after a
        stall; publish every ``servo_per_bus`` servo periods (one bus period)."""
        period_ns = round(PERIOD_S * 1e9)
        start_ns = deadline_ns = time.monotonic_ns()
        servo = 0
        while not self.finished.is_set():
            now_ns = time.monotonic_ns()
            if now_ns < deadline_ns:
                time.sleep((deadline_ns - now_ns) * 1e-9)
            elif (missed := (now_ns - deadline_ns) // period_ns) > 0:
                self.skipped_periods += missed
                deadline_ns += missed * period_ns
            self.step(deadline_ns, publish=servo % servo_per_bus == 0)
            servo += 1
            deadline_ns += period_ns
        return (time.monotonic_ns() - start_ns) * 1e-9


def wait_for_tokens(session: zenoh.Session, key: str, names: set) -> None:
    """Poll until the liveliness tokens ``key/<name>`` of all ``names`` are present.

    A session with the wrong credentials opens all the same and never links: no token
    of a peer after LINK_TIMEOUT_S ends the program with that cause."""
    start = time.monotonic()
    while True:
        seen = {str(r.ok.key_expr).rsplit("/", 1)[-1]
                for r in session.liveliness().get(f"{key}/*") if r.ok}  # fmt: skip
        if not names - seen:
            return
        if not seen & names and time.monotonic() - start > LINK_TIMEOUT_S:
            session.close()
            raise SystemExit(
                f"no link to the stack after {LINK_TIMEOUT_S:g} s: is the stack up, and is "
                "this the config file it printed for this run (its certificates)?"
            )
        time.sleep(0.1)


def stack_versions(session: zenoh.Session, key: str) -> set:
    """The protocol versions the stack's services declare (tokens ``key/protocol/<n>``)."""
    return {int(str(r.ok.key_expr).rsplit("/", 1)[-1])
            for r in session.liveliness().get(f"{key}/protocol/*") if r.ok}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("zenoh_config", help="the file teleop run/up --without printed")
    parser.add_argument("--robot", help="robot id (default: the config file's metadata)")
    parser.add_argument("--peers", default="plant,controller,hmd,operator,recorder")
    args = parser.parse_args()
    conf = zenoh.Config.from_file(args.zenoh_config)
    metadata = json.loads(str(conf))["metadata"]  # the launcher's
    robot = args.robot or metadata["robot_id"]
    # The stack's bus rate (its default where the file does not say).
    servo_per_bus = round(1.0 / (metadata.get("loop_rate_hz", DEFAULT_BUS_RATE_HZ) * PERIOD_S))
    session = zenoh.open(conf)
    with Handle() as device:
        haptic = OutsideHaptic(session, robot, device)
        key = f"teleop/{robot}"
        tokens = [session.liveliness().declare_token(f"{key}/alive/haptic")]  # dropped: gone
        wait_for_tokens(session, f"{key}/alive", set(args.peers.split(",")))
        versions = stack_versions(session, key)  # before any record: can we talk at all?
        if versions and VERSION not in versions:
            session.close()
            raise SystemExit(
                f"the stack speaks protocol version {min(versions)}, this device {VERSION}: "
                "take the example of the stack's own checkout (docs/protocol.md)"
            )
        tokens.append(session.liveliness().declare_token(f"{key}/ready/haptic"))  # plant starts
        wall_s = haptic.run(servo_per_bus)
    if haptic.other_version is not None:
        session.close()
        raise SystemExit(
            f"the stack speaks protocol version {haptic.other_version}, this device "
            f"{VERSION}: take the example of the stack's own checkout (docs/protocol.md)"
        )
    print(json.dumps({"samples_sent": haptic.seq, "sample_rate_hz": haptic.seq / wall_s,
                      "skipped_periods": haptic.skipped_periods, "stale_periods":
                      haptic.stale_periods}), flush=True)  # fmt: skip
    session.close()  # undeclares everything: the tokens are gone


if __name__ == "__main__":
    main()
