"""Hostile inputs against a running realtime grasp (`teleop run grasp --mode realtime`).

While the scripted operator does the task, this script attacks the stack's bus and then
reads what the stack measured. Attackers:

- an *outsider*: a session with no credentials (any local process, another stack);
- *another user* (``nobody``, when run as root): the same, from another uid, which also
  cannot read the run's 0600 credential files;
- an *observer thief*: the run's read-only observer certificate under another Zenoh
  id, publishing anyway;
- *insiders*: sessions holding a stolen certificate (or, with ``bus.tls = false``,
  password) of the controller, the haptic service or the HMD under another Zenoh id, which the
  access list must give no right; they aim with the run's genuine observer file (a
  viewer's, as handed out), which sees the newest state.

Timeline after the plant's first state (seconds): poisoned counters (seq, state_seq,
tick = 2^64-1) of a command, a feedback and a handle sample; spoofed run events;
commands at 3 rad/s per joint, 1 kHz, answering the newest state; stale-stamped commands; then a
flood at 10x the nominal rate of every stream the insider may or may not publish. Writes
JSON with the run's summary figures and every attacker's counts::

    .venv/bin/python tests/benchmarks/hostile_inputs.py --json runs/bench/hostile.json
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
import traceback
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from teleop.bus import graph
from teleop.bus import messages as m
from teleop.bus.access import new_zid
from teleop.bus.session import Publisher, close_session, open_session, subscribe
from teleop.bus.topics import Topics
from teleop.core.config import load_config
from teleop.core.net import free_loopback_port

U64_MAX = 2**64 - 1
START_TIMEOUT_S = 120.0
OUTSIDER = """
import sys, time, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("connect/endpoints", '[' + ','.join('"%s"' % e for e in sys.argv[2:]) + ']')
try:
    open(sys.argv[1]).read()
    readable = True
except OSError:
    readable = False
s = zenoh.open(conf)
got = []
sub = s.declare_subscriber("teleop/arm0/state/**", lambda sample: got.append(1))
pub = s.declare_publisher("teleop/arm0/cmd/joint_velocity")
for _ in range(3000):
    pub.put(bytes(193))
    time.sleep(0.001)
print(readable, len(got))
s.close()
"""


class Watch:
    """The newest plant state and applied-command seq an insider sees."""

    def __init__(self) -> None:
        self.state_seq = -1
        self.cmd_seq = 0
        self.states = 0
        self.first = threading.Event()

    def __call__(self, rec: np.ndarray, rx_ns: int) -> None:
        self.state_seq = max(self.state_seq, int(rec["seq"]))
        self.cmd_seq = max(self.cmd_seq, int(rec["cmd_seq_applied"]))
        self.states += 1
        self.first.set()


def endpoints(run_dir: Path) -> tuple[str, list[str]]:
    """The run's listener and every service's own listening endpoint (supervisord.conf)."""
    conf = (run_dir / "supervisord.conf").read_text()
    listener = re.search(r'bus\.endpoint="([^"]+)"', conf).group(1)
    return listener, sorted(set(re.findall(r'bus\.peer_listen_endpoint="([^"]+)"', conf)))


def stolen(run_dir: Path, service: str, out: Path) -> Path:
    """``service``'s credentials under another Zenoh id (a thief's own session)."""
    content = json.loads((run_dir / "auth" / f"{service}.json").read_text())
    content["zid"] = new_zid()
    out.write_text(json.dumps(content))
    return out


def session_for(run_dir: Path, credentials: Path | None) -> Any:
    listener, own = endpoints(run_dir)
    config = load_config(None, [])
    bus = replace(
        config.bus,
        endpoint=listener,
        gossip=False,
        # a thief holding certificates listens as the run's processes do (mutual TLS)
        peer_listen_endpoint=f"{listener.partition('/')[0]}/127.0.0.1:{free_loopback_port()}"
        if credentials and "tls" in json.loads(credentials.read_text())
        else f"tcp/127.0.0.1:{free_loopback_port()}",
        peer_connect_endpoints=tuple(own),
        credentials_file=str(credentials) if credentials else "",
    )
    return open_session(bus, listen=False)


def attack(run_dir: Path, work: Path, flood_s: float) -> dict[str, Any]:
    topics = Topics("arm0")
    drops = m.DropCounter()
    ctl = session_for(run_dir, stolen(run_dir, "controller", work / "thief-controller.json"))
    hap = session_for(run_dir, stolen(run_dir, "haptic", work / "thief-haptic.json"))
    obs = session_for(run_dir, stolen(run_dir, "observer", work / "thief-observer.json"))
    hmd = session_for(run_dir, stolen(run_dir, "hmd", work / "thief-hmd.json"))
    outsider = session_for(run_dir, None)
    # The thieves see nothing of the run (the access list gives a stolen certificate
    # under another id no right), so the attack aims with the run's genuine observer
    # credentials (a viewer's file, as handed out): the newest state and applied command.
    spy = session_for(run_dir, run_dir / "auth" / "observer.json")
    watch, thief_watch, outsider_seen = Watch(), Watch(), [0]
    keep = [
        subscribe(spy, topics.plant_state, m.PLANT_STATE, watch, drops),
        subscribe(ctl, topics.plant_state, m.PLANT_STATE, thief_watch, drops),
        subscribe(outsider, topics.plant_state, m.PLANT_STATE,
                  lambda r, t: outsider_seen.__setitem__(0, outsider_seen[0] + 1), drops),
    ]  # fmt: skip
    pubs = {
        "cmd": Publisher.declare(ctl, topics.joint_command, m.JOINT_COMMAND),
        "feedback": Publisher.declare(ctl, topics.force_feedback, m.FORCE_FEEDBACK),
        "haptic": Publisher.declare(hap, topics.haptic_state, m.HAPTIC_STATE),
        "op_events": Publisher.declare(ctl, topics.operator_events, m.RUN_EVENT),
        "plant_events": Publisher.declare(ctl, topics.plant_events, m.RUN_EVENT),
        "observer_cmd": Publisher.declare(obs, topics.joint_command, m.JOINT_COMMAND),
        "hmd_cmd": Publisher.declare(hmd, topics.joint_command, m.JOINT_COMMAND),
        "hmd_pose": Publisher.declare(hmd, topics.head_pose, m.HEAD_POSE),
        "outsider_cmd": Publisher.declare(outsider, topics.joint_command, m.JOINT_COMMAND),
    }
    sent: dict[str, int] = dict.fromkeys(pubs, 0)

    def put(name: str, rec: np.ndarray) -> None:
        pubs[name].put(rec)
        sent[name] += 1

    def command(seq: int, state_seq: int, qd: float, stamp_ns: int) -> np.ndarray:
        rec = m.JOINT_COMMAND.new()
        rec["seq"], rec["state_seq"], rec["n_joints"] = seq, state_seq, 6
        rec["qd_ref_rad_s"][:6] = qd
        rec["gripper_cmd"] = 1.0
        rec["trace_ns"][m.Stage.CONTROLLER_TX] = stamp_ns
        rec["t_source_ns"] = stamp_ns
        return rec

    assert watch.first.wait(START_TIMEOUT_S), "no plant state seen by the observer"
    t0 = time.monotonic()

    def at(t_s: float) -> None:
        time.sleep(max(0.0, t0 + t_s - time.monotonic()))

    at(2.0)  # one poisoned record of each loop stream
    put("cmd", command(U64_MAX, U64_MAX, 0.5, time.monotonic_ns()))
    fb = m.FORCE_FEEDBACK.new()
    fb["seq"], fb["tick"], fb["device_f_n"] = U64_MAX, U64_MAX, (8.0, 0.0, 0.0)
    fb["trace_ns"][m.Stage.FEEDBACK_TX] = time.monotonic_ns()
    put("feedback", fb)
    hs = m.HAPTIC_STATE.new()
    hs["seq"], hs["tick"] = U64_MAX, U64_MAX
    hs["trace_ns"][m.Stage.HAPTIC_SAMPLE] = time.monotonic_ns()
    put("haptic", hs)
    pose = m.HEAD_POSE.new()  # the view turned half a turn (HMD thief)
    pose["seq"], pose["valid_from_tick"] = U64_MAX, 0
    pose["predicted_yaw_rad"] = 3.0
    pose["t_source_ns"] = time.monotonic_ns()
    put("hmd_pose", pose)
    at(3.0)  # spoofed run events: the task is over, the run finished
    for name, event in (("op_events", m.Event.TASK_DONE), ("plant_events", m.Event.FINISHED)):
        ev = m.RUN_EVENT.new()
        ev["seq"], ev["event"], ev["step"], ev["value"] = 1, event, watch.state_seq, 1.0
        put(name, ev)
    for t_s, qd, age_ns in ((4.0, 3.0, 0), (6.0, 0.05, 1_000_000_000)):  # 3 rad/s, stale
        at(t_s)
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            stamp = time.monotonic_ns() - age_ns
            put("cmd", command(watch.cmd_seq + 1, watch.state_seq, qd, stamp))
            put("observer_cmd", command(watch.cmd_seq + 1, watch.state_seq, qd, stamp))
            put("hmd_cmd", command(watch.cmd_seq + 1, watch.state_seq, qd, stamp))
            put("outsider_cmd", command(watch.cmd_seq + 1, watch.state_seq, qd, stamp))
            time.sleep(0.001)
    # What the thief saw of the run: before the flood, whose plant states Zenoh hands
    # its own session's subscriber locally.
    insider_states_seen = thief_watch.states
    at(8.0)  # a flood: 10x the nominal rate of every stream (1 kHz ones at 10 kHz)
    flood_pubs = {
        s.name: Publisher.declare(ctl, getattr(topics, s.name), s.schema)
        for s in graph.STREAMS
        if not s.batch_of and s.schema is not m.EYE_VIEW
    }
    flood_sent = 0
    end = time.monotonic() + flood_s
    rng = np.random.default_rng(0)
    while time.monotonic() < end:
        tick_end = time.monotonic() + 0.001
        for name, pub in flood_pubs.items():
            rec = pub.schema.new()
            rec["seq"] = int(rng.integers(0, 2**63))
            rec["trace_ns"][:] = time.monotonic_ns()
            for _ in range(10 if "1 kHz" in graph.stream(name).rate else 1):
                pub.put(rec)
                flood_sent += 1
        time.sleep(max(0.0, tick_end - time.monotonic()))
    result = {
        "sent": {**sent, "flood": flood_sent},
        "outsider_states_seen": outsider_seen[0],
        "observer_states_seen": watch.states,
        "insider_states_seen": insider_states_seen,
    }
    for session, *entities in (
        (spy, keep[0]), (ctl, keep[1]), (outsider, keep[2]), (hap,), (obs,), (hmd,)
    ):  # fmt: skip
        close_session(session, *entities)
    return result


# Another user has only the zenoh wheel, under the system's Python (the project's venv
# may live where that user cannot read).
OTHER_USER_SITE = Path("/tmp/teleop-hostile-zenoh")
SYSTEM_PYTHON = "/usr/bin/python3"


def other_user_site() -> Path:
    """The zenoh wheel of this venv's version, installed for the system's Python."""
    if not (OTHER_USER_SITE / "zenoh").exists():
        import importlib.metadata

        wheels = OTHER_USER_SITE.with_suffix(".wheels")
        version = importlib.metadata.version("eclipse-zenoh")
        pip = [sys.executable, "-m", "pip", "download", "--no-deps", "-q", "-d", str(wheels)]
        subprocess.run([*pip, f"eclipse-zenoh=={version}"], check=True)
        wheel = next(wheels.glob("eclipse_zenoh-*.whl"))
        subprocess.run([SYSTEM_PYTHON, "-m", "pip", "install", "-q", "--no-deps", "--target",
                        str(OTHER_USER_SITE), str(wheel)], check=True)  # fmt: skip
    return OTHER_USER_SITE


def other_user(run_dir: Path) -> dict[str, Any] | None:
    """The outsider as the ``nobody`` user (root only): can it read the credentials,
    how many of the stack's samples does it get."""
    if os.geteuid() != 0 or not Path(SYSTEM_PYTHON).exists():
        return None
    site = other_user_site()
    listener, own = endpoints(run_dir)
    done = subprocess.run(
        ["runuser", "-u", "nobody", "--", "env", f"PYTHONPATH={site}", "HOME=/tmp",
         SYSTEM_PYTHON, "-c", OUTSIDER, str(run_dir / "auth" / "controller.json"), listener,
         *own],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    readable, got = done.stdout.split() if done.returncode == 0 else ("?", "?")
    return {
        "could_read_credentials": readable,
        "samples_seen": got,
        "rc": done.returncode,
        "stderr": done.stderr[-300:],
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run-dir", type=Path, default=Path("runs/bench/hostile"))
    parser.add_argument("--flood-s", type=float, default=10.0)
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args()
    run_dir = args.run_dir.absolute()
    summary_file = run_dir / "summary.json"
    run_dir.mkdir(parents=True, exist_ok=True)
    for stale in (run_dir / "supervisord.conf", summary_file):
        stale.unlink(missing_ok=True)
    stack = subprocess.Popen(
        [sys.executable, "-m", "teleop.cli", "run", "grasp", "--mode", "realtime", "--seed",
         "0", "--quiet", "--run-dir", str(run_dir), "--summary-json", str(summary_file),
         "--duration", "60"],
        stdout=subprocess.DEVNULL,
    )  # fmt: skip
    deadline = time.monotonic() + START_TIMEOUT_S
    while not (run_dir / "supervisord.conf").exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    results: dict[str, Any] = {"other_user": None}
    runner = threading.Thread(
        target=lambda: results.update(other_user=other_user(run_dir)), daemon=True
    )
    runner.start()
    try:
        results["attacks"] = attack(run_dir, run_dir, args.flood_s)
    except BaseException:
        traceback.print_exc()
        stack.send_signal(signal.SIGINT)  # the stack stops, not left running
        stack.wait(timeout=120)
        os._exit(1)  # the attack's open sessions would keep this process alive
    runner.join()
    code = stack.wait(timeout=300)
    summary = json.loads(summary_file.read_text()) if summary_file.exists() else {}
    services = summary.get("services", {})
    results["run"] = {
        "exit_code": code,
        **{k: summary.get(k) for k in (
            "success", "duration_s", "tool_speed_max_m_s", "max_device_force_n",
            "max_contact_force_n",
            "stale_commands", "commands_received", "commands_applied", "commands_clamped",
            "command_stream", "dropped_messages", "stale_feedback_events")},
        "dropped_by_service": {n: s.get("dropped_by_reason") for n, s in services.items()},
        "unknown_peers_by_service": {n: s.get("unknown_peers") for n, s in services.items()},
        "protective_stop": summary.get("protective_stop"),
        "controller_haptic_stream": services.get("controller", {}).get("haptic_stream"),
        "haptic_feedback_stream": services.get("haptic", {}).get("feedback_stream"),
    }  # fmt: skip
    text = json.dumps(results, indent=1, default=str)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text)
    return 0 if summary.get("success") else 1


if __name__ == "__main__":
    sys.exit(main())
