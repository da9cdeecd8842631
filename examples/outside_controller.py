"""A joint-velocity controller that takes the place of the stack's own, from outside.

Written from docs/protocol.md alone: it imports nothing from the teleop package. Start
the stack without its controller; it prints the Zenoh config file to use:

    teleop run path-following --mode lockstep --without controller
    python examples/outside_controller.py runs/latest/outside/controller.json5

The arm follows a joint-space path: each joint swings about a centre a little away from
where the arm starts, q_d(t) = q_c + A sin(2 pi t / T) on the plant's clock. The law is
velocity feed-forward plus a proportional correction, qd_ref = dq_d/dt + K (q_d - q),
which the plant's velocity loops track. Every PLANT_STATE is answered by one
JOINT_COMMAND naming it (state_seq), in realtime and lockstep alike. At the plant's
FINISHED event it prints a JSON summary (tracking error, commands, braking) and exits.

Zenoh calls each subscriber's callback on its own thread: FINISHED may be handled
before the run's last state. The event's `step` names that state's step, so the client
waits for it (a moment at most) before it sums up.
"""

import argparse
import json
import struct
import threading
import time

import numpy as np
import zenoh

# -- the wire format (docs/protocol.md, "Records") --------------------------------------
VERSION = 8
# How long to wait for a first link to the stack before giving up (s).
LINK_TIMEOUT_S = 10.0
HEADER = struct.Struct("<HHIQq10q")  # version, kind, flags, seq, t_source_ns, trace_ns[10]
PLANT_STATE, JOINT_COMMAND, RUN_EVENT = 1, 2, 7  # kinds
PLANT_STATE_SIZE, RUN_EVENT_SIZE = 491, 130
COMMAND_BODY = struct.Struct("<Qq8ddB")  # state_seq, device_deadline_ns, qd_ref[8], gripper, n
MAX_JOINTS = 8
BRAKING = 1  # header flag of PLANT_STATE
CONTROLLER_RX, CONTROLLER_TX = 1, 2  # trace_ns stages this controller stamps
FINISHED = 2  # RUN_EVENT code
STEP_OFFSET = 112  # u8 `step` of PLANT_STATE and RUN_EVENT (after the header and sim_time_ns)
LAST_STATE_WAIT_S = 1.0  # after FINISHED, how long the run's last state may still take
GRIPPER_OPEN = 1.0

# -- the path and the law ---------------------------------------------------------------
AMPLITUDE_RAD = 0.1  # swing of every joint about its centre (the plant cuts the tool at 0.30 m/s)
PERIOD_S = 6.0  # one swing
CENTRE_OFFSET_RAD = 0.1  # the centre is this far from the start: the error starts at 0.1 rad
GAIN_PER_S = 20.0  # K: a joint error of 0.01 rad asks for 0.2 rad/s more
SPEED_LIMIT_RAD_S = 2.0  # the command is scaled down to this on its fastest joint
SETTLE_S = 2.0  # tracking error statistics start after this much plant time


class PathController:
    """The control law, apart from the bus: a state in, a velocity command out."""

    def __init__(self) -> None:
        self.centre_rad = None  # set from the first state of a run
        self.errors_rad = []  # max joint error per state after SETTLE_S

    def command(self, t_s: float, q_rad: np.ndarray) -> np.ndarray:
        if self.centre_rad is None:
            self.centre_rad = q_rad + CENTRE_OFFSET_RAD
        w = 2 * np.pi / PERIOD_S
        q_d = self.centre_rad + AMPLITUDE_RAD * np.sin(w * t_s)
        qd_d = AMPLITUDE_RAD * w * np.cos(w * t_s) * np.ones_like(q_rad)
        error = q_d - q_rad
        if t_s >= SETTLE_S:
            self.errors_rad.append(float(np.max(np.abs(error))))
        qd_ref = qd_d + GAIN_PER_S * error
        fastest = np.max(np.abs(qd_ref))
        return qd_ref * min(1.0, SPEED_LIMIT_RAD_S / fastest) if fastest > 0 else qd_ref


class OutsideController:
    """The bus side: decode states, answer each with a command, watch for the end."""

    def __init__(self, session: zenoh.Session, robot: str) -> None:
        self.law = PathController()
        self.last_state_seq = -1  # newest state answered (a re-sent state is not answered twice)
        self.run_stamp = None  # t_source_ns of this run's state 0
        self.command_seq = 0  # JOINT_COMMAND seq: 1 for the first
        self.states = self.braking_states = self.bad_records = 0
        self.first_ns = self.last_ns = 0
        self.finished = threading.Event()
        self.other_version = None  # the stack's protocol version, if not ours
        self.last_step = -1  # the step of the run's last state (FINISHED's step)
        self.newest_step = -1  # the step of the newest state handled
        self.lock = threading.Condition()  # notified when a state has been handled
        self.pub = session.declare_publisher(
            f"teleop/{robot}/cmd/joint_velocity",
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.REAL_TIME,
            express=True,
        )
        self.subs = [
            session.declare_subscriber(f"teleop/{robot}/state/plant", self.on_state),
            session.declare_subscriber(f"teleop/{robot}/events/plant", self.on_event),
        ]

    def on_state(self, sample: zenoh.Sample) -> None:
        rx_ns = time.monotonic_ns()
        data = sample.payload.to_bytes()
        version, kind, flags, seq, t_source_ns, *trace = HEADER.unpack_from(data)
        if version != VERSION:  # another protocol: nothing it sends can be read here
            self.other_version = version
            self.finished.set()
            return
        if len(data) != PLANT_STATE_SIZE or kind != PLANT_STATE:
            self.bad_records += 1
            return
        with self.lock:
            if seq == 0 and t_source_ns != self.run_stamp:  # state 0 of a new run
                self.run_stamp, self.last_state_seq, self.law = t_source_ns, -1, PathController()
            if seq <= self.last_state_seq:
                return  # a state sent again (lockstep, nothing answered it for 1 s)
            self.last_state_seq = seq
            self.states += 1
            self.braking_states += flags & BRAKING
            sim_time_ns = struct.unpack_from("<q", data, 104)[0]
            n = data[490]  # n_joints
            q_rad = np.frombuffer(data, "<f8", n, 160)
            qd_ref = np.zeros(MAX_JOINTS)
            qd_ref[:n] = self.law.command(sim_time_ns * 1e-9, q_rad)
            self.command_seq += 1
            trace[CONTROLLER_RX] = rx_ns  # the state's stamps, then ours: latency per hop
            now_ns = time.monotonic_ns()
            trace[CONTROLLER_TX] = now_ns
            header = HEADER.pack(VERSION, JOINT_COMMAND, 0, self.command_seq, now_ns, *trace)
            body = COMMAND_BODY.pack(seq, 0, *qd_ref, GRIPPER_OPEN, n)
            self.pub.put(header + body)
            self.first_ns = self.first_ns or now_ns
            self.last_ns = now_ns
            self.newest_step = struct.unpack_from("<Q", data, STEP_OFFSET)[0]
            self.lock.notify_all()

    def on_event(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        if len(data) == RUN_EVENT_SIZE and struct.unpack_from("<H", data, 128)[0] == FINISHED:
            self.last_step = struct.unpack_from("<Q", data, STEP_OFFSET)[0]
            self.finished.set()

    def wait_for_last_state(self) -> bool:
        """After FINISHED: wait until the state of FINISHED's step has been handled."""
        with self.lock:
            return self.lock.wait_for(lambda: self.newest_step >= self.last_step, LAST_STATE_WAIT_S)

    def summary(self) -> dict:
        errors = np.array(self.law.errors_rad or [np.nan])
        wall_s = (self.last_ns - self.first_ns) * 1e-9
        return {
            "states_received": self.states,
            "commands_sent": self.command_seq,
            "command_rate_hz": (self.command_seq - 1) / wall_s if wall_s > 0 else None,
            "braking_states": self.braking_states,
            "bad_records": self.bad_records,
            "tracking_error_rms_rad": float(np.sqrt(np.mean(errors**2))),
            "tracking_error_max_rad": float(np.max(errors)),
        }


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
    parser.add_argument("--peers", default="plant,recorder", help="the stack's services")
    parser.add_argument("--timeout", type=float, default=600.0, help="end after (s)")
    args = parser.parse_args()
    conf = zenoh.Config.from_file(args.zenoh_config)
    robot = args.robot or json.loads(str(conf))["metadata"]["robot_id"]  # the launcher's
    session = zenoh.open(conf)
    controller = OutsideController(session, robot)
    key = f"teleop/{robot}"
    tokens = [session.liveliness().declare_token(f"{key}/alive/controller")]  # dropped: gone
    wait_for_tokens(session, f"{key}/alive", set(args.peers.split(",")))
    versions = stack_versions(session, key)  # before any record: can we talk at all?
    if versions and VERSION not in versions:
        session.close()
        raise SystemExit(
            f"the stack speaks protocol version {min(versions)}, this client {VERSION}: "
            "take the example of the stack's own checkout (docs/protocol.md)"
        )
    tokens.append(session.liveliness().declare_token(f"{key}/ready/controller"))  # plant starts
    finished = controller.finished.wait(args.timeout)
    if controller.other_version is not None:
        session.close()
        raise SystemExit(
            f"the stack speaks protocol version {controller.other_version}, this client "
            f"{VERSION}: take the example of the stack's own checkout (docs/protocol.md)"
        )
    last_state = finished and controller.wait_for_last_state()
    summary = {"finished": finished, "last_state_handled": last_state, **controller.summary()}
    print(json.dumps(summary), flush=True)
    session.close()  # undeclares everything: the tokens are gone


if __name__ == "__main__":
    main()
