"""The controller's cycles without a bus: records in, records out, on a fake clock."""

from __future__ import annotations

import collections
import math
import threading

import numpy as np
import pytest

from teleop.bus.messages import HAND_INPUT, HAPTIC_STATE, HEAD_POSE, PLANT_STATE, Stage
from teleop.control.cycle import BilateralCycle, PathCycle
from teleop.control.kinematics import build_arm_model, tool_position_and_jacobian
from teleop.core.clock import FakeClock
from teleop.core.config import load_config
from teleop.devices.haptic.device import EmulatedDevice
from teleop.devices.haptic.loop import HapticLoop
from teleop.run.experiments import run_path_following_inprocess
from teleop.sim.plant_loop import PlantLoop

GRASP = 'run.scenario="grasp"'
LOCKSTEP = 'run.mode="lockstep"'
REALTIME = 'run.mode="realtime"'
# Standard gravity (m/s^2), as the scene and the weight feedback use it.
GRAVITY_M_S2 = 9.81
# The path error (m) the in-process path-following test holds a settled run to.
PATH_RMS_BAR_M = 0.001


class Sent:
    """ControllerOutputs that keep a copy of every record, by stream, in order."""

    def __init__(self) -> None:
        self.log: list[tuple[str, np.ndarray]] = []
        self.resent: list[str] = []  # the streams of the records sent again

    def put(self, stream: str, rec: np.ndarray) -> None:
        self.log.append((stream, rec.copy()))

    def resend(self, stream: str, rec: np.ndarray) -> None:
        self.log.append((stream, rec.copy()))
        self.resent.append(stream)

    def streams(self) -> list[str]:
        return [stream for stream, _ in self.log]

    def last(self, stream: str) -> np.ndarray:
        return [rec for s, rec in self.log if s == stream][-1]


def make(cycle_class, *overrides: str):
    config = load_config(None, overrides)
    arm = build_arm_model(config.robot)
    sent, clock = Sent(), FakeClock(start_ns=10**12)
    return cycle_class(config, arm, sent, clock), sent, clock, config


def state(config, seq: int, now_ns: int, start_ns: int = 1) -> np.ndarray:
    rec = PLANT_STATE.new()
    n = len(config.robot.arm_joints)
    rec["seq"] = seq
    rec["step"] = seq
    rec["n_joints"] = n
    rec["q_rad"][:n] = config.robot.home_q_rad
    rec["sim_time_ns"] = seq * round(config.tick_s * 1e9)
    rec["t_source_ns"] = start_ns if seq == 0 else now_ns
    rec["obstacle_geom"] = -1
    rec["trace_ns"][Stage.PLANT_STATE_TX] = now_ns
    return rec


def handle(seq: int, tick: int, now_ns: int, device_p_m=(0.03, 0.0, 0.0)) -> np.ndarray:
    rec = HAPTIC_STATE.new()
    rec["seq"] = seq
    rec["tick"] = tick
    rec["device_p_m"] = device_p_m
    rec["device_deadline_ns"] = now_ns
    rec["trace_ns"][Stage.HAPTIC_SAMPLE] = now_ns
    return rec


def test_lockstep_cycle_sends_feedback_then_a_command_that_moves_the_tool():
    cycle, sent, clock, config = make(BilateralCycle, 'run.mode="lockstep"', 'run.scenario="grasp"')
    cycle.on_state(state(config, 0, clock.now_ns()), clock.now_ns())
    assert sent.log == []  # the tick waits for its handle sample
    cycle.on_haptic(handle(1, 0, clock.now_ns()), clock.now_ns())
    assert sent.streams()[:2] == ["force_feedback", "joint_command"]
    command = sent.last("joint_command")
    assert command["state_seq"] == 0 and command["seq"] == 1
    assert np.abs(command["qd_ref_rad_s"]).max() > 0  # the handle's offset asks for motion
    feedback = sent.last("force_feedback")
    assert feedback["tick"] == 0 and np.isfinite(feedback["device_f_n"]).all()
    summary = cycle.summary()
    assert (summary["cycles"], summary["runs"], summary["no_input_cycles"]) == (1, 1, 0)


def test_a_silent_handle_gives_no_motion_and_counts_as_no_input():
    """Realtime, a handle is silent when no sample has arrived for
    haptic.stale_feedback_s on the controller's clock, not when its tick lags: across a
    slow link every sample's tick is a round trip behind the newest state."""
    cycle, sent, clock, config = make(BilateralCycle, 'run.mode="realtime"', 'run.scenario="grasp"')
    now = clock.now_ns()
    cycle.on_state(state(config, 0, now), now)  # no handle yet: feedback without input
    assert sent.streams() == ["force_feedback"] and cycle.no_input_cycles == 1
    cycle.on_haptic(handle(1, 0, now), now)  # answered on state 0: a command
    command = sent.last("joint_command")
    assert command["device_deadline_ns"] == now and np.abs(command["qd_ref_rad_s"]).max() > 0
    far_tick = cycle.stale_ticks + 5  # the handle's tick far behind, its sample just in
    cycle.on_state(state(config, far_tick, now), now)
    assert cycle.no_input_cycles == 1
    clock.advance(cycle.handle_silent_ns + 1)  # no sample since: the handle went silent
    now = clock.now_ns()
    cycle.on_state(state(config, far_tick + 1, now), now)
    assert cycle.no_input_cycles == 2
    # with no input the workspace spring (on the handle's offset) is not rendered
    assert np.allclose(sent.last("force_feedback")["device_f_workspace_n"], 0.0)


def test_realtime_inputs_too_old_or_out_of_order_are_dropped_and_counted():
    cycle, sent, clock, config = make(BilateralCycle, 'run.mode="realtime"', 'run.scenario="grasp"')
    now = clock.now_ns()
    cycle.on_state(state(config, 0, now), now)
    cycle.on_haptic(handle(5, 0, now), now)
    cycle.on_haptic(handle(4, 0, now), now)  # older than the last one: dropped
    old = now - 10 * cycle.haptic_in.shed_age_ns
    cycle.on_haptic(handle(6, 0, old), now)  # sampled too long ago: shed, its loop logged
    for tick in (1, 2):  # the states' pace: an age is the time beyond the fastest ones
        cycle.on_state(state(config, tick, now), now)
    stale_state = state(config, 3, old)
    cycle.on_state(stale_state, now)
    summary = cycle.summary()
    assert summary["haptic_reordered"] == 1 and summary["haptic_shed"] == 1
    assert summary["states_shed"] == 1 and summary["cycles"] == 1
    assert len(cycle.shed_log) == 1  # the state carried no sample stamp


def test_the_path_cycle_answers_each_state_once_and_restarts_on_a_new_run():
    cycle, sent, clock, config = make(PathCycle, 'run.mode="lockstep"')
    now = clock.now_ns()
    for seq in (0, 1, 1, 0, 3):  # re-sends of 1 and 0, and state 2 never seen
        cycle.on_state(state(config, seq, now), now)
    commands = [rec for s, rec in sent.log if s == "joint_command"]
    # A re-sent state (the plant waited for an answer) gets the command that answered
    # it again, same seq.
    assert [int(c["state_seq"]) for c in commands] == [0, 1, 1, 0, 3]
    assert [int(c["seq"]) for c in commands] == [1, 2, 2, 1, 3]
    assert cycle.commands_resent == 2
    # to the plant only, not the recorder's copy
    assert sent.resent == ["joint_command", "joint_command"]
    assert cycle.skipped_states == 1 and cycle.runs == 1
    assert "control_status" in sent.streams()  # step 0 is a status step
    cycle.on_state(state(config, 0, now, start_ns=2), now)  # state 0 of a new run
    assert cycle.runs == 2 and cycle.summary()["cycles"] == 4


def test_a_realtime_cycle_takes_seqs_going_back_for_a_new_run_whose_state_0_it_skipped():
    """Realtime: the state stream is taken newest-only, so a controller busy when the
    plant starts over may never see the new run's state 0; lower seqs in order say it.
    One state going back (stale, or forged) is refused and changes nothing."""
    cycle, sent, clock, config = make(PathCycle, 'run.mode="realtime"')
    now = clock.now_ns()
    for seq in (0, 1, 2, 5):  # 3 and 4 skipped (behind): counted
        cycle.on_state(state(config, seq, now), now)
    assert cycle.runs == 1 and cycle.skipped_states == 2
    cycle.on_state(state(config, 1, now, start_ns=7), now)  # one stale or forged state
    assert cycle.runs == 1 and cycle.states_refused == 1
    cycle.on_state(state(config, 6, now), now)  # the run goes on
    assert cycle.runs == 1 and cycle.summary()["cycles"] == 5
    for seq in (3, 4, 5):  # a new run, its 0-2 skipped: taken up on its third state
        cycle.on_state(state(config, seq, now, start_ns=2), now)
    assert cycle.runs == 2 and cycle.states_refused == 3 and cycle.summary()["cycles"] == 6
    lockstep, _, _, _ = make(PathCycle, 'run.mode="lockstep"')
    for seq in (0, 1, 2, 5, 3):  # lockstep: a lower seq is a re-send, never a new run
        lockstep.on_state(state(config, seq, now), now)
    assert lockstep.runs == 1


class DeviceSent:
    """HapticOutputs that queue the handle samples for the test to deliver."""

    def __init__(self) -> None:
        self.samples: collections.deque[np.ndarray] = collections.deque()

    def sample(self, rec: np.ndarray, robot: int = 0) -> None:
        self.samples.append(rec.copy())

    def resend(self, rec: np.ndarray, robot: int = 0) -> None:
        self.samples.append(rec.copy())


def test_a_lost_feedback_is_sent_again_when_the_plant_re_sends_its_states():
    """Lockstep, controller and haptic device joined: the feedback of tick 2 is lost on
    the way (a link that dropped). The device then never steps tick 3, so the controller
    never answers state 3 and the plant waits. Its re-send of the states in flight (3
    and 4) makes the controller send the feedback of the state before each again: the
    device steps, and state 3 gets its answer."""
    cycle, sent, clock, config = make(BilateralCycle, LOCKSTEP, GRASP)
    device = DeviceSent()
    loop = HapticLoop(
        config,
        EmulatedDevice(config.haptic, config.haptic.render_period_s),
        device,
        clock,
        lockstep=True,
    )
    lost_tick = 2
    lost: list[np.ndarray] = []  # the feedback records lost on the way
    delivered = 0  # records of `sent.log` already handed on

    def pump() -> None:
        nonlocal delivered
        while device.samples or delivered < len(sent.log):
            while device.samples:
                cycle.on_haptic(device.samples.popleft(), clock.now_ns())
            for stream, rec in sent.log[delivered:]:
                delivered += 1
                if stream != "force_feedback":
                    continue
                if int(rec["tick"]) == lost_tick and not lost:
                    lost.append(rec)  # its first copy only
                    continue
                loop.on_feedback(rec, clock.now_ns())

    def answered() -> list[int]:
        return [int(rec["state_seq"]) for s, rec in sent.log if s == "joint_command"]

    def publish(seq: int, resent: bool = False) -> None:  # the plant's state, to both
        rec = state(config, seq, clock.now_ns())
        cycle.on_state(rec, clock.now_ns())
        loop.on_state(rec.copy())
        # The operator: on its sample ticks, an input for `lead_ticks` later (a hand at
        # rest). The device waits for it from tick `lead_ticks` on (2 at 250 Hz).
        if not resent and loop.hand_schedule.is_sample(seq):
            hand = HAND_INPUT.new()
            hand["valid_from_tick"] = seq + loop.hand_schedule.lead_ticks
            loop.on_hand(hand)
        pump()

    for seq in range(lost_tick + 3):  # states 0..4: the answer to 2 lets the plant send 4
        publish(seq)
    assert len(lost) == 1
    assert max(answered()) == lost_tick  # state 3 waits for the device's tick 3
    for seq in (lost_tick + 1, lost_tick + 2):  # a second without an answer: re-sent
        publish(seq, resent=True)
    assert lost_tick + 1 in answered()
    # State 3's re-send brought the feedback of 2 again; state 4's (answered by then,
    # the device unblocked) the feedback of 3 and its own answer.
    assert cycle.commands_resent == 2


def test_two_answers_lost_together_are_both_sent_again():
    """Lockstep: the commands answering states 2 and 3 both lost (a link that dropped on
    a loaded machine). The plant waits on state 2 and sends its states in flight, 2 and
    3, again: each gets its own answer again, not only the newest (which alone would
    leave the plant waiting on state 2 for ever)."""
    cycle, sent, clock, config = make(PathCycle, 'run.mode="lockstep"')
    now = clock.now_ns()
    for seq in (0, 1, 2, 3):
        cycle.on_state(state(config, seq, now), now)
    first = len(sent.log)
    for seq in (2, 3):  # the plant's re-send
        cycle.on_state(state(config, seq, now), now)
    again = [rec for s, rec in sent.log[first:] if s == "joint_command"]
    assert [int(c["state_seq"]) for c in again] == [2, 3]
    assert [int(c["seq"]) for c in again] == [3, 4]  # the same records, byte for byte
    assert cycle.commands_resent == 2


@pytest.mark.parametrize("cycle_class", [PathCycle, BilateralCycle])
def test_a_cycle_spends_its_compute_time_on_the_injected_clock(cycle_class):
    cycle, sent, clock, config = make(cycle_class, 'run.mode="lockstep"', 'run.scenario="grasp"')
    cycle.on_state(state(config, 0, clock.now_ns()), clock.now_ns())
    if isinstance(cycle, BilateralCycle):
        cycle.on_haptic(handle(1, 0, clock.now_ns()), clock.now_ns())
    assert cycle.summary()["compute_mean_us"] == 0.0  # a fake clock stands still


def rz(yaw_rad: float) -> np.ndarray:
    """View -> world rotation about z (3, 3), written out independently of the controller."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def head_pose(valid_from_tick: int, yaw_rad: float) -> np.ndarray:
    rec = HEAD_POSE.new()
    rec["valid_from_tick"] = valid_from_tick
    rec["predicted_yaw_rad"] = yaw_rad
    return rec


def one_cycle(cycle, sent, clock, config, device_p_m) -> tuple[np.ndarray, np.ndarray]:
    """State 0 and one handle sample: the (world tool-velocity reference, joint command)."""
    now = clock.now_ns()
    cycle.on_state(state(config, 0, now), now)
    cycle.on_haptic(handle(1, 0, now, device_p_m), now)
    world_v_ref_m_s = sent.last("teleop_status")["world_v_ref_m_s"]
    qd_ref_rad_s = sent.last("joint_command")["qd_ref_rad_s"][: cycle.arm.n_joints]
    return world_v_ref_m_s, qd_ref_rad_s


@pytest.mark.parametrize("yaw_rad", [0.0, math.pi / 2, -0.7])
@pytest.mark.parametrize("mode", ["lockstep", "realtime"])
def test_a_handle_displacement_commands_a_tool_velocity_in_the_view_frame(mode, yaw_rad):
    """Lockstep takes the view yaw from the config before the first HMD pose applies;
    realtime (no prediction lead) from the HEAD_POSE record valid at the tick."""
    overrides = [f'run.mode="{mode}"', GRASP]
    if mode == "lockstep":
        overrides.append(f"hmd.head_yaw_rad={yaw_rad}")
    else:
        overrides.append("hmd.prediction_s=0.0")
    device_p_m = np.array([0.03, 0.01, -0.005])  # outside the deadband

    cycle, sent, clock, config = make(BilateralCycle, *overrides)
    if mode == "realtime":
        cycle.on_head_pose(head_pose(0, yaw_rad), clock.now_ns())
    world_v_ref, qd_ref = one_cycle(cycle, sent, clock, config, device_p_m)
    rest, rest_sent, rest_clock, _ = make(BilateralCycle, *overrides)
    if mode == "realtime":
        rest.on_head_pose(head_pose(0, yaw_rad), rest_clock.now_ns())
    _, qd_rest = one_cycle(rest, rest_sent, rest_clock, config, np.zeros(3))

    tcfg = config.teleop
    norm = float(np.linalg.norm(device_p_m))
    speed = min(tcfg.rate_gain_per_s * (norm - tcfg.deadband_m), tcfg.max_tool_speed_m_s)
    expected = rz(yaw_rad) @ (speed * device_p_m / norm)  # handle forward = view forward
    np.testing.assert_allclose(world_v_ref, expected, atol=1e-12)
    # What the handle adds to the joint command moves the tool along the reference.
    _, jacobian = tool_position_and_jacobian(cycle.arm, np.array(config.robot.home_q_rad))
    world_v_added = jacobian[:3] @ (qd_ref - qd_rest)
    assert world_v_added @ expected > 0.0
    assert cycle.missing_head_poses == 0


def test_feedback_renders_contact_held_weight_obstacle_and_workspace_in_the_device_frame():
    yaw_rad = 0.3
    cycle, sent, clock, config = make(
        BilateralCycle, LOCKSTEP, GRASP, f"hmd.head_yaw_rad={yaw_rad}"
    )
    tcfg = config.teleop
    now = clock.now_ns()
    rec = state(config, 0, now)
    rec["world_f_contact_n"] = (1.0, -2.0, -3.0)  # measured on the gripper, weight included
    rec["held_mass_kg"] = 0.2
    distance_m = tcfg.obstacle_influence_m / 2
    rec["distance_m"] = distance_m
    rec["world_n_away"] = (0.0, 1.0, 0.0)
    rec["world_p_arm_m"] = (0.3, 0.1, 0.4)
    rec["world_p_obstacle_m"] = (0.3, 0.1 - distance_m, 0.4)
    rec["arm_body"] = 5
    rec["obstacle_geom"] = 2
    handle_m = tcfg.workspace_free_m + 0.005  # just outside the free sphere, along x
    cycle.on_state(rec, now)
    cycle.on_haptic(handle(1, 0, now, (handle_m, 0.0, 0.0)), now)
    feedback = sent.last("force_feedback")

    weight = np.array([0.0, 0.0, -0.2 * GRAVITY_M_S2])
    contact = np.array([1.0, -2.0, -3.0]) - weight
    obstacle = np.array(
        [0.0, tcfg.obstacle_stiffness_n_per_m * (tcfg.obstacle_influence_m - distance_m), 0.0]
    )
    workspace = np.array([-tcfg.workspace_stiffness_n_per_m * 0.005, 0.0, 0.0])
    np.testing.assert_allclose(feedback["world_f_weight_n"], weight, atol=1e-12)
    np.testing.assert_allclose(feedback["world_f_contact_n"], contact, atol=1e-12)
    np.testing.assert_allclose(feedback["world_f_obstacle_n"], obstacle, atol=1e-12)
    np.testing.assert_allclose(feedback["device_f_workspace_n"], workspace, atol=1e-12)
    device = tcfg.force_scale * rz(yaw_rad).T @ (contact + weight + obstacle) + workspace
    assert np.linalg.norm(device) < config.haptic.peak_force_n  # no saturation here
    np.testing.assert_allclose(feedback["device_f_n"], device, atol=1e-12)
    summary = cycle.summary()
    assert summary["max_obstacle_force_n"] == pytest.approx(np.linalg.norm(obstacle))
    assert summary["held_weight_n"] == pytest.approx(0.2 * GRAVITY_M_S2)
    assert summary["held_cycles"] == 1
    assert sent.last("teleop_status")["holding"] == 1


def test_feedback_saturates_at_the_device_peak_force_keeping_its_direction():
    cycle, sent, clock, config = make(BilateralCycle, LOCKSTEP, GRASP, "hmd.head_yaw_rad=0.0")
    now = clock.now_ns()
    rec = state(config, 0, now)
    rec["world_f_contact_n"] = (0.0, 0.0, -100.0)
    cycle.on_state(rec, now)
    cycle.on_haptic(handle(1, 0, now, (0.0, 0.0, 0.0)), now)
    device = sent.last("force_feedback")["device_f_n"]
    np.testing.assert_allclose(device, (0.0, 0.0, -config.haptic.peak_force_n), atol=1e-12)


def test_a_stale_handle_gives_zero_feedback_and_drives_no_motion():
    """A handle silent for haptic.stale_feedback_s on the clock is "no input": no
    workspace spring, so with no contact nor obstacle the device force is exactly zero;
    a sample older than the shed age on the clock is never answered with a command (the
    plant's watchdog brakes the arm)."""
    cycle, sent, clock, config = make(BilateralCycle, REALTIME, GRASP)
    handle_m = config.teleop.workspace_free_m + 0.01  # the spring pulls while the input is live
    now = clock.now_ns()
    cycle.on_state(state(config, 0, now), now)
    for seq in (1, 2, 3):  # the samples' pace: an age is the time beyond the fastest ones
        cycle.on_haptic(handle(seq, 0, now, (handle_m, 0.0, 0.0)), now)
    assert sent.streams().count("joint_command") == 3
    cycle.on_state(state(config, 1, now), now)  # the handle is fresh: the spring renders
    assert sent.last("force_feedback")["device_f_n"][0] < 0.0
    clock.advance(cycle.handle_silent_ns + 1)  # no sample since: it went silent
    late = clock.now_ns()
    cycle.on_state(state(config, 2, late), late)
    assert np.array_equal(sent.last("force_feedback")["device_f_n"], np.zeros(3))
    assert np.array_equal(sent.last("force_feedback")["device_f_workspace_n"], np.zeros(3))
    cycle.on_haptic(handle(4, 1, now, (handle_m, 0.0, 0.0)), late)  # sampled long ago
    assert sent.streams().count("joint_command") == 3  # no command: nothing drives the tool
    assert cycle.summary()["haptic_shed"] == 1


class Wire:
    """Plant and controller outputs in one process: each stream's records queue up for
    the test to deliver, so neither core calls the other from inside its own cycle."""

    def __init__(self) -> None:
        self.queues: dict[str, collections.deque[np.ndarray]] = collections.defaultdict(
            collections.deque
        )

    def put(self, stream: str, rec: np.ndarray) -> bytes:
        self.queues[stream].append(rec.copy())
        return rec.tobytes()

    def put_bytes(self, stream: str, data: bytes) -> None:
        """A lockstep re-send: the test delivers every record once, so none is needed."""

    def resend(self, stream: str, rec: np.ndarray) -> None:
        """The controller's lockstep re-send: likewise none needed."""

    def flush(self) -> None:
        """Nothing is batched here."""


def test_the_path_cycle_converges_on_the_in_process_plant_like_the_in_process_run():
    """The plant's lockstep loop and the path cycle, records handed from one to the
    other: from the seeded start off the path the tool settles on it, and the run is the
    in-process experiment's bit for bit (same figures, same final plant state)."""
    overrides = (LOCKSTEP, "run.duration_s=3", "run.settle_s=1", "run.seed=3")
    config = load_config(None, overrides)
    wire, clock = Wire(), FakeClock(start_ns=10**12)
    loop = PlantLoop(config, wire, clock)
    cycle = PathCycle(config, build_arm_model(config.robot), wire, clock)
    steps = round(config.run.duration_s / config.tick_s)
    stop = threading.Event()
    runner = threading.Thread(target=loop.run, args=(stop, steps))
    runner.start()
    states, commands = wire.queues["plant_state"], wire.queues["joint_command"]
    try:
        while not states and runner.is_alive():  # state 0 comes from the run's thread
            runner.join(timeout=0.001)
        while states:  # each command steps the plant, which publishes the next state
            cycle.on_state(states.popleft(), clock.now_ns())
            while commands:
                loop.on_command(commands.popleft(), clock.now_ns())
        runner.join(timeout=30)
        assert not runner.is_alive()
    finally:
        stop.set()
        runner.join(timeout=30)
    assert loop.core.finished and loop.core.plant.step_count == steps

    errors_m = [float(rec["path_error_m"]) for rec in wire.queues["control_status"]]
    assert errors_m[0] > 10 * PATH_RMS_BAR_M  # the seeded start is off the path
    summary = cycle.summary()
    assert summary["path_error_rms_m"] <= PATH_RMS_BAR_M
    assert summary["cycles"] == steps + 1  # every state answered, the last one too
    reference = run_path_following_inprocess(config, progress=None)
    for key in ("path_error_rms_m", "path_error_max_m", "min_manipulability"):
        assert summary[key] == reference[key]
    assert loop.core.plant.state_sha256() == reference["final_state_sha256"]


def test_a_silent_handle_zeroes_the_rendered_force_even_in_contact():
    """The handle went silent: whatever the plant feels (here a held cube's weight and a
    contact), the device is sent zero force, the components are still reported."""
    cycle, sent, clock, config = make(BilateralCycle, REALTIME, GRASP)
    now = clock.now_ns()
    loaded = state(config, 0, now)
    loaded["world_f_contact_n"] = (0.0, 0.0, -3.0)
    loaded["held_mass_kg"] = 0.2
    cycle.on_haptic(handle(1, 0, now), now)
    cycle.on_state(loaded, now)  # the handle is fresh: contact and weight render
    assert np.linalg.norm(sent.last("force_feedback")["device_f_n"]) > 0.5
    clock.advance(cycle.handle_silent_ns + 1)  # no handle sample since
    silent = loaded.copy()
    silent["seq"] = silent["step"] = 1
    silent["t_source_ns"] = clock.now_ns()
    cycle.on_state(silent, clock.now_ns())
    feedback = sent.last("force_feedback")
    assert np.array_equal(feedback["device_f_n"], np.zeros(3))
    assert np.linalg.norm(feedback["world_f_contact_n"]) > 0  # still reported


def test_a_silent_plant_stops_the_commands():
    """Handle samples keep coming but the newest plant state is older than the plant's
    watchdog: the controller commands nothing (the plant holds the arm), and commands
    again on the first fresh state."""
    cycle, sent, clock, config = make(BilateralCycle, REALTIME, GRASP)
    now = clock.now_ns()
    for tick in (0, 1, 2):  # the states' pace: an age is the time beyond the fastest ones
        cycle.on_state(state(config, tick, now), now)
    cycle.on_haptic(handle(1, 2, now), now)
    assert sent.streams().count("joint_command") == 1
    clock.advance(round(config.plant.watchdog_s * 1e9) + 1_000_000)
    for seq in (2, 3, 4):  # fresh samples, a silent plant
        now = clock.now_ns()
        cycle.on_haptic(handle(seq, 2, now), now)
    assert sent.streams().count("joint_command") == 1
    assert cycle.summary()["plant_silent_samples"] == 3
    assert cycle.haptic_in.shed == 3  # unanswered on purpose: the latency count's shed
    cycle.on_state(state(config, 3, now), now)
    cycle.on_haptic(handle(5, 3, now), now)
    assert sent.streams().count("joint_command") == 2
