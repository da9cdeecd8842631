"""A haptic device that takes the place of the stack's own, from outside.

Written from docs/protocol.md alone: it imports nothing from the teleop package. Start
the grasp scenario without its haptic service; it prints the Zenoh config file to use:

    teleop run grasp --without haptic
    python examples/outside_haptic.py runs/latest/outside/haptic.json5

`Handle` has the methods of the project's device interface (connect, disconnect, read,
send_force, next_sample, reset; a context manager): a driver for a real device fills the
same methods with its hardware calls. This one emulates a Falcon-like handle: a 0.15 kg
mass with damping, pulled by the operator's hand (a spring-damper towards where the hand
is) and pushed by the feedback force. No person holds it here: the scripted operator
publishes HAND_INPUT (where its hand pulls, and the buttons), which this device follows.
Every millisecond it publishes HAPTIC_STATE; it renders each FORCE_FEEDBACK on arrival.
At the plant's FINISHED event it prints a JSON summary and exits.
"""

import argparse
import json
import struct
import threading
import time

import numpy as np
import zenoh

# -- the wire format (docs/protocol.md, "Records") --------------------------------------
VERSION = 4
HEADER = struct.Struct("<HHIQq10q")  # version, kind, flags, seq, t_source_ns, trace_ns[10]
HAPTIC_STATE, HAND_INPUT, FORCE_FEEDBACK, RUN_EVENT = 8, 9, 10, 7  # kinds
HAND_INPUT_SIZE, FORCE_FEEDBACK_SIZE, RUN_EVENT_SIZE = 137, 240, 130
STATE_BODY = struct.Struct("<qQq9dB")  # sim_time_ns, tick, device_deadline_ns, p, v, f, buttons
STALE = 2  # HAPTIC_STATE flag: the feedback force is old and fading out
HAPTIC_SAMPLE = 0  # trace_ns stage: when the handle was sampled
FINISHED = 2  # RUN_EVENT code
BATCH_RECORDS = 10  # the recorder's batched copy: this many records per message

# -- the device --------------------------------------------------------------------------
PERIOD_S = 0.001  # servo period: 1 kHz
MASS_KG, DAMPING_N_S_PER_M = 0.15, 3.0  # the handle, and its own viscous damping
HAND_STIFFNESS_N_PER_M, HAND_DAMPING_N_S_PER_M = 200.0, 8.0  # the hand holding it
WORKSPACE_HALF_M = 0.05  # end stops at +-5 cm on each axis
PEAK_FORCE_N = 8.0
STALE_AFTER_S, FADE_S = 0.020, 0.020  # older feedback fades out to zero over FADE_S


class Handle:
    """Device interface: connect, read, send_force, next_sample, reset, disconnect.
    Device frame: x forward, y left, z up, origin at the workspace centre; m, m/s, N."""

    period_s = PERIOD_S

    def __enter__(self) -> "Handle":
        self.connect()
        return self

    def __exit__(self, *exc_info) -> None:
        self.disconnect()

    def connect(self) -> None:
        self.reset()  # a driver opens its link here, motors enabled at zero force

    def disconnect(self) -> None:
        self.force_n = np.zeros(3)  # a driver zeroes the motors and closes its link

    def reset(self) -> None:
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
        self.feedback_n = np.zeros(3)
        self.hands = {}  # HAND_INPUT by valid_from_tick: (target_p_m, buttons)
        self.seq = self.feedbacks = self.stale_periods = self.late_periods = 0
        self.max_force_n, self.batch = 0.0, []
        key = f"teleop/{robot}"
        qos = dict(congestion_control=zenoh.CongestionControl.BLOCK, express=True)
        self.pub = session.declare_publisher(
            f"{key}/haptic/state", priority=zenoh.Priority.REAL_TIME, **qos
        )
        self.batch_pub = session.declare_publisher(f"{key}/haptic/state/batch", **qos)
        self.subs = [
            session.declare_subscriber(f"{key}/haptic/feedback", self.on_feedback),
            session.declare_subscriber(f"{key}/operator/hand", self.on_hand),
            session.declare_subscriber(f"{key}/events/**", self.on_event),
        ]

    def on_feedback(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        if len(data) != FORCE_FEEDBACK_SIZE or HEADER.unpack_from(data)[:2] != (VERSION, 10):
            return
        sim_time_ns, tick = struct.unpack_from("<qQ", data, 104)
        force = np.frombuffer(data, "<f8", 3, 120).copy()
        with self.lock:
            if tick < self.tick:  # older than the force the handle already feels
                return
            self.tick, self.sim_time_ns, self.feedback_n = tick, sim_time_ns, force
            self.feedback_rx_ns = time.monotonic_ns()
            self.feedbacks += 1
            self.device.send_force(force)  # rendered the moment it arrives

    def on_hand(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        if len(data) != HAND_INPUT_SIZE or HEADER.unpack_from(data)[:2] != (VERSION, 9):
            return
        valid_from = struct.unpack_from("<Q", data, 104)[0]
        target = np.frombuffer(data, "<f8", 3, 112).copy()
        with self.lock:
            self.hands[valid_from] = (target, data[136])
            for old in sorted(self.hands)[:-64]:  # keep the newest 64
                del self.hands[old]

    def on_event(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        if len(data) == RUN_EVENT_SIZE and struct.unpack_from("<H", data, 128)[0] == FINISHED:
            self.finished.set()

    def step(self, deadline_ns: int) -> None:
        """One device period that began at ``deadline_ns``: fade an old force, move the
        handle under the hand input valid at the newest tick, publish the sample."""
        with self.lock:
            flags = 0
            if self.feedback_rx_ns is not None:
                overdue_s = (time.monotonic_ns() - self.feedback_rx_ns) * 1e-9 - STALE_AFTER_S
                if overdue_s > 0:
                    flags, self.stale_periods = STALE, self.stale_periods + 1
                    self.device.send_force(self.feedback_n * max(0.0, 1 - overdue_s / FADE_S))
            valid = [k for k in self.hands if k <= self.tick]
            hand = self.hands[max(valid)] if valid else None
            p, v, f, buttons = self.device.next_sample(hand)
            tick, sim_time_ns = self.tick, self.sim_time_ns
        self.seq += 1
        now_ns = time.monotonic_ns()
        trace = [0] * 10
        trace[HAPTIC_SAMPLE] = now_ns  # the controller measures the sample's age from it
        header = HEADER.pack(VERSION, HAPTIC_STATE, flags, self.seq, now_ns, *trace)
        record = header + STATE_BODY.pack(sim_time_ns, tick, deadline_ns, *p, *v, *f, buttons)
        self.pub.put(record)
        self.batch.append(record)
        if len(self.batch) == BATCH_RECORDS:
            self.batch_pub.put(b"".join(self.batch))
            self.batch = []
        self.max_force_n = max(self.max_force_n, float(np.linalg.norm(f)))

    def run(self, timeout_s: float) -> None:
        """Step on absolute deadlines of the monotonic clock; after a stall, skip the
        periods missed (never step them in a burst)."""
        period_ns = round(PERIOD_S * 1e9)
        deadline_ns = time.monotonic_ns()
        end_ns = deadline_ns + round(timeout_s * 1e9)
        self.start_ns = deadline_ns
        while not self.finished.is_set() and deadline_ns < end_ns:
            now_ns = time.monotonic_ns()
            if now_ns < deadline_ns:
                time.sleep((deadline_ns - now_ns) * 1e-9)
            elif now_ns - deadline_ns > period_ns:
                missed = (now_ns - deadline_ns) // period_ns
                self.late_periods += missed
                deadline_ns += missed * period_ns
            self.step(deadline_ns)
            deadline_ns += period_ns
        self.wall_s = (time.monotonic_ns() - self.start_ns) * 1e-9

    def summary(self) -> dict:
        return {
            "samples_sent": self.seq,
            "sample_rate_hz": self.seq / self.wall_s,
            "skipped_periods": self.late_periods,
            "feedback_received": self.feedbacks,
            "stale_periods": self.stale_periods,
            "max_rendered_force_n": self.max_force_n,
        }


def wait_for_tokens(session: zenoh.Session, key: str, names: set, timeout_s: float) -> None:
    """Block until the liveliness tokens ``key/<name>`` of all ``names`` are present."""
    seen, changed = set(), threading.Condition()

    def on_token(sample: zenoh.Sample) -> None:
        with changed:
            name = str(sample.key_expr).rsplit("/", 1)[-1]
            (seen.add if sample.kind == zenoh.SampleKind.PUT else seen.discard)(name)
            changed.notify_all()

    sub = session.liveliness().declare_subscriber(f"{key}/*", on_token, history=True)
    with changed:
        if not changed.wait_for(lambda: names <= seen, timeout_s):
            raise SystemExit(f"not seen after {timeout_s} s: {sorted(names - seen)}")
    sub.undeclare()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("zenoh_config", help="the file teleop run/up --without printed")
    parser.add_argument("--robot", default="arm0", help="robot id (default: arm0)")
    parser.add_argument(
        "--peers", default="plant,controller,hmd,operator,recorder", help="the stack's services"
    )
    parser.add_argument("--timeout", type=float, default=600.0, help="give up after (s)")
    args = parser.parse_args()
    session = zenoh.open(zenoh.Config.from_file(args.zenoh_config))
    with Handle() as device:
        haptic = OutsideHaptic(session, args.robot, device)
        tokens = f"teleop/{args.robot}"
        alive = session.liveliness().declare_token(f"{tokens}/alive/haptic")
        wait_for_tokens(session, f"{tokens}/alive", set(args.peers.split(",")), args.timeout)
        ready = session.liveliness().declare_token(f"{tokens}/ready/haptic")  # plant starts
        haptic.run(args.timeout)
    finished = haptic.finished.is_set()
    print(json.dumps({"finished": finished, **haptic.summary()}), flush=True)
    for entity in (ready, alive, *haptic.subs, haptic.pub, haptic.batch_pub):
        entity.undeclare()
    session.close()


if __name__ == "__main__":
    main()
