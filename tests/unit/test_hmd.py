"""The HMD emulator and its loop: filter and prediction against the scripted truth, the
plant-tick clock with re-sends and new runs.

Deterministic throughout: fixed seeds, sim time from plant ticks. The measured errors are
printed (``pytest -s``) and appear in the assertion messages.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from teleop.bus.messages import HEAD_POSE
from teleop.core.config import ConfigError, load_config
from teleop.core.ticks import head_schedule
from teleop.devices.hmd import (
    ErrorStats,
    HeadFilter,
    HeadMotion,
    HeadPose,
    HmdEmulator,
    HmdLoop,
    Tracker,
    fill_head_pose,
    wrap_angle,
)

SIM_S = 20.0  # simulated seconds of head motion per accuracy test
# A head moving faster than the default script (peak yaw rate 0.84 rad/s, sway 0.1 m/s).
MOVING_HEAD = (
    "hmd.motion_period_s=3.0",
    "hmd.yaw_amplitude_rad=0.4",
    "hmd.sway_amplitude_m=0.05",
)


def run_emulator(emulator: HmdEmulator, sim_s: float = SIM_S) -> list:
    ticks = round(sim_s / emulator.schedule.tick_s)
    return [s for k in range(ticks) if (s := emulator.on_tick(k)) is not None]


def rms_position(estimates: list[HeadPose], truths: list[HeadPose]) -> float:
    """Reference RMS of the 3-D position error, written independently of ErrorStats."""
    err = np.array([e.p_m - t.p_m for e, t in zip(estimates, truths, strict=True)])
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def rms_yaw(estimates: list[HeadPose], truths: list[HeadPose]) -> float:
    err = np.array([e.yaw_rad - t.yaw_rad for e, t in zip(estimates, truths, strict=True)])
    err = np.angle(np.exp(1j * err))  # wrapped the other way than wrap_angle
    return float(np.sqrt(np.mean(err**2)))


def test_filter_reduces_the_error_below_the_raw_noise():
    config = load_config(None, ["run.seed=3"])
    emulator = HmdEmulator(config)
    samples = run_emulator(emulator)
    assert len(samples) == round(SIM_S * config.hmd.rate_hz)
    truth = [s.truth for s in samples]
    measured = [s.measured for s in samples]
    filtered = [s.filtered for s in samples]
    raw_p, raw_yaw = rms_position(measured, truth), rms_yaw(measured, truth)
    filt_p, filt_yaw = rms_position(filtered, truth), rms_yaw(filtered, truth)
    report = (
        f"position RMS raw {raw_p * 1e3:.2f} mm -> filtered {filt_p * 1e3:.2f} mm; "
        f"yaw RMS raw {raw_yaw * 1e3:.2f} mrad -> filtered {filt_yaw * 1e3:.2f} mrad"
    )
    print(report)
    # The raw error is the configured noise (3 axes for position).
    assert raw_p == pytest.approx(math.sqrt(3) * config.hmd.position_noise_m, rel=0.05)
    assert raw_yaw == pytest.approx(config.hmd.yaw_noise_rad, rel=0.05)
    assert filt_p < 0.5 * raw_p, report
    assert filt_yaw < 0.6 * raw_yaw, report
    # The service's running statistics agree with the reference computation.
    assert emulator.filtered_error.position_rms_m == pytest.approx(filt_p, rel=1e-9)
    assert emulator.filtered_error.yaw_rms_rad == pytest.approx(filt_yaw, rel=1e-9)
    assert emulator.measured_error.position_rms_m == pytest.approx(raw_p, rel=1e-9)


def test_prediction_by_the_horizon_beats_the_unpredicted_pose_of_a_moving_head():
    config = load_config(None, ["run.seed=4", *MOVING_HEAD])
    emulator = HmdEmulator(config)
    samples = run_emulator(emulator)
    horizon_s = emulator.schedule.lead_s
    assert horizon_s == pytest.approx(config.hmd.prediction_s)
    motion = HeadMotion(config.hmd)
    future = [motion.pose(s.t_s + horizon_s) for s in samples]
    pred_p = rms_position([s.predicted for s in samples], future)
    pred_yaw = rms_yaw([s.predicted for s in samples], future)
    late_p = rms_position([s.filtered for s in samples], future)
    late_yaw = rms_yaw([s.filtered for s in samples], future)
    report = (
        f"vs pose {horizon_s * 1e3:.0f} ms ahead: position predicted {pred_p * 1e3:.2f} mm, "
        f"un-predicted {late_p * 1e3:.2f} mm; yaw predicted {pred_yaw * 1e3:.2f} mrad, "
        f"un-predicted {late_yaw * 1e3:.2f} mrad"
    )
    print(report)
    assert pred_p < 0.95 * late_p, report
    assert pred_yaw < 0.5 * late_yaw, report
    assert emulator.predicted_error.yaw_rms_rad == pytest.approx(pred_yaw, rel=1e-9)
    assert emulator.unpredicted_error.position_rms_m == pytest.approx(late_p, rel=1e-9)


def test_predict_ahead_leaves_the_filter_unchanged():
    config = load_config(None, list(MOVING_HEAD))
    emulator = HmdEmulator(config)
    run_emulator(emulator, sim_s=1.0)
    kf = emulator.filter.kf
    x, p = kf.x.copy(), kf.P.copy()
    ahead = emulator.filter.predict_ahead(0.05)
    assert np.array_equal(kf.x, x) and np.array_equal(kf.P, p)
    # Constant velocity: the prediction is the state moved by rate * horizon.
    assert np.allclose(ahead.p_m, x[:3, 0] + 0.05 * x[5:8, 0])
    assert ahead.yaw_rad == pytest.approx(float(wrap_angle(x[3, 0] + 0.05 * x[8, 0])))


def test_yaw_crossing_plus_pi_is_tracked_without_a_jump():
    config = load_config(
        None, ["run.seed=5", f"hmd.head_yaw_rad={math.pi - 0.2}", "hmd.yaw_amplitude_rad=0.5"]
    )
    emulator = HmdEmulator(config)
    samples = run_emulator(emulator)
    truth_yaw = np.array([s.truth.yaw_rad for s in samples])
    assert truth_yaw.max() > 3.0 and truth_yaw.min() < -3.0, "the head must cross +-pi"
    for s in samples:
        for yaw in (s.measured.yaw_rad, s.filtered.yaw_rad, s.predicted.yaw_rad):
            assert -math.pi <= yaw < math.pi
    filt_err = np.abs(wrap_angle(np.array([s.filtered.yaw_rad for s in samples]) - truth_yaw))
    truth = [s.truth for s in samples]
    raw_yaw = rms_yaw([s.measured for s in samples], truth)
    filt_yaw = rms_yaw([s.filtered for s in samples], truth)
    print(f"yaw across +-pi: raw {raw_yaw * 1e3:.2f} mrad -> filtered {filt_yaw * 1e3:.2f} mrad")
    # No 2 pi excursion anywhere, and the filter still beats the raw measurement.
    assert filt_err.max() < 5 * config.hmd.yaw_noise_rad
    assert filt_yaw < raw_yaw


def test_yaw_innovation_is_wrapped():
    """A sample just across -pi from a state near +pi is a small step, not -2 pi."""
    head_filter = HeadFilter(period_s=1 / 90, measurement_std=np.full(5, 0.01))
    p_m = np.zeros(3)
    head_filter.update(HeadPose(p_m, math.pi - 0.01, 0.0))
    filtered = head_filter.update(HeadPose(p_m, -math.pi + 0.01, 0.0))
    assert abs(float(wrap_angle(filtered.yaw_rad - math.pi))) < 0.02


def test_same_seed_gives_the_same_sequence():
    def sequence(seed: int, start_tick: int = 0) -> list[tuple]:
        emulator = HmdEmulator(load_config(None, [f"run.seed={seed}"]))
        ticks = range(start_tick, 2000)
        samples = [s for k in ticks if (s := emulator.on_tick(k)) is not None]
        return [
            (s.tick, s.valid_from_tick, *s.measured.as_vector(), *s.predicted.as_vector())
            for s in samples
        ]

    first = sequence(11)
    assert first == sequence(11)  # bit-identical floats
    assert first != sequence(12)
    # Measurements depend on (seed, tick) only: joining late gives the same noise.
    late = sequence(11, start_tick=1000)
    assert [row[2:7] for row in late] == [row[2:7] for row in first if row[0] >= 1000]


def test_tracker_noise_has_the_configured_spread():
    config = load_config(None, ["hmd.position_noise_m=0.01", "hmd.yaw_noise_rad=0.02"])
    tracker = Tracker(config.hmd, seed=0)
    pose = HeadPose(np.zeros(3), 0.0, 0.0)
    draws = np.array([tracker.measure(pose, k).as_vector() for k in range(4000)])
    assert np.allclose(draws.std(axis=0), [0.01] * 3 + [0.02] * 2, rtol=0.05)
    assert np.allclose(draws.mean(axis=0), 0.0, atol=0.002)


def test_schedule_says_which_record_applies_at_a_tick():
    config = load_config()
    schedule = head_schedule(config)
    tick_s = config.tick_s  # one tick: a bus period (loop.rate_hz)
    # hmd.prediction_s (20 ms) in whole ticks
    assert schedule.lead_ticks * tick_s == pytest.approx(config.hmd.prediction_s)
    two_s = round(2.0 / tick_s)
    sample_ticks = [k for k in range(two_s) if schedule.is_sample(k)]
    assert len(sample_ticks) == round(2.0 * config.hmd.rate_hz)  # 180: 90 Hz
    ticks_per_sample = 1.0 / (config.hmd.rate_hz * tick_s)  # not a whole number
    assert set(np.diff(sample_ticks)) == {math.floor(ticks_per_sample), math.ceil(ticks_per_sample)}
    valid_from = [k + schedule.lead_ticks for k in sample_ticks]
    assert schedule.valid_from_for(schedule.lead_ticks - 1) is None  # no record yet
    for tick in range(schedule.lead_ticks, two_s - schedule.lead_ticks):
        chosen = schedule.valid_from_for(tick)
        # The newest record whose prediction is for a tick not after this one.
        assert chosen == max(v for v in valid_from if v <= tick)


def test_error_stats_wrap_the_yaw():
    stats = ErrorStats()
    near_plus_pi = HeadPose(np.zeros(3), math.pi - 0.01, 0.0)
    near_minus_pi = HeadPose(np.ones(3), -math.pi + 0.01, 0.0)
    stats.add(near_plus_pi, near_minus_pi)
    assert stats.yaw_rms_rad == pytest.approx(0.02)
    assert stats.position_rms_m == pytest.approx(math.sqrt(3))


def test_hmd_loop_on_scene_ticks_gives_the_per_tick_samples_and_restarts_on_tick_0():
    """What the service does per TOOL_POSE: the samples of every HMD sample tick up to the
    clock tick, nothing for a re-sent tick, a fresh filter for a new run."""
    config = load_config(None, ["run.seed=9"])
    loop = HmdLoop(config)
    scene_period = round(1 / (config.plant.scene_rate_hz * config.tick_s))
    last_tick = 30 * scene_period
    reference = run_emulator(HmdEmulator(config), sim_s=(last_tick + 1) * config.tick_s)
    timestep_ns = round(config.tick_s * 1e9)
    rec = HEAD_POSE.new()
    for _run in range(2):
        samples = []
        for k in range(0, last_tick + 1, scene_period):
            samples += loop.on_clock(k)
            if k == 2 * scene_period:
                assert loop.on_clock(k) == []  # a re-send
        assert [s.tick for s in samples] == [r.tick for r in reference]
        for sample, ref in zip(samples, reference, strict=True):
            fill_head_pose(rec, sample, 5, 123, timestep_ns)
            assert np.array_equal(rec["predicted_p_m"], ref.predicted.p_m)
            assert float(rec["measured_yaw_rad"]) == ref.measured.yaw_rad
            assert int(rec["sim_time_ns"]) == ref.tick * timestep_ns
            assert int(rec["valid_from_tick"]) == ref.valid_from_tick
    assert loop.runs == 2 and loop.resent_states == 2
    assert loop.emulator.samples == len(reference)  # statistics of the current run only


def test_hmd_loop_refuses_a_prediction_shorter_than_the_scene_period():
    config = load_config(None, ["hmd.prediction_s=0.005"])
    with pytest.raises(ConfigError, match="hmd.prediction_s"):
        HmdLoop(config)
