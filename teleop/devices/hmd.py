"""The head-mounted-display emulator: scripted head motion, a noisy tracker, a Kalman filter.

Pure and process-free, so every piece is testable on its own: :class:`HmdLoop` is the
whole HMD minus the bus; ``services/hmd.py`` feeds it the plant's ticks and publishes
its samples.

Frames and units: world frame, z up, metres. The head pose is a position ``p_m`` (3,) and
two angles: ``yaw_rad`` about world z (0 = looking along +x, positive turns toward +y),
and ``pitch_rad`` about the head's own y axis after yaw (positive = nose down, the
right-hand rule with x forward and z up). Roll is not modelled. Yaw is reported in
[-pi, pi); the filter handles a head that turns through +-pi.

Timing: the HMD samples on the plant ticks where a ``rate_hz`` clock advances
(:func:`teleop.core.ticks.is_sample_tick`), so sample intervals are whole plant steps (at
90 Hz on a 1 ms plant: 11 or 12 ms). Each sample's pose is predicted ``lead_ticks`` plant
steps ahead and is valid from ``sample_tick + lead_ticks``
(:func:`teleop.core.ticks.head_schedule`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from filterpy.kalman import KalmanFilter

from teleop.core.config import SCRIPTED, Config, ConfigError, HmdConfig
from teleop.core.ticks import head_schedule, scene_schedule

# Head pitch nod of the scripted motion: amplitude (rad, about 3 degrees) and its period
# as a fraction of hmd.motion_period_s (a nod twice per yaw sway).
NOD_AMPLITUDE_RAD = 0.05
NOD_PERIOD_FRACTION = 0.5

# Pose vector layout shared by the tracker and the filter: [x, y, z, yaw, pitch].
POSE_DIM = 5
YAW_INDEX = 3
PITCH_INDEX = 4

# Process noise of the constant-velocity filter: standard deviation of the white
# acceleration the model does not explain, per coordinate. It sets the trade-off between
# smoothing (small) and lag on a turning head (large). Sized for a head like the scripted
# one, a little faster (peaks of about 0.2 m/s^2 and 2 rad/s^2, e.g. a 0.4 rad yaw sway
# with a 3 s period); a much faster head lags (raise these), a slower one is smoothed less
# than it could be. Measured errors: tests/unit/test_hmd.py.
HEAD_ACCEL_STD_M_S2 = 0.2  # head translation, m/s^2
HEAD_ANGULAR_ACCEL_STD_RAD_S2 = 2.0  # yaw and pitch, rad/s^2
# Initial standard deviation of the velocity states, before the filter has seen motion.
INITIAL_SPEED_STD_M_S = 0.5  # m/s
INITIAL_ANGULAR_SPEED_STD_RAD_S = 2.0  # rad/s
# Floor of the measurement noise the filter assumes, so a noise-free tracker (std 0) still
# gives a well-conditioned innovation covariance.
MIN_MEASUREMENT_STD = 1e-6

# Noise-stream id mixed into the run seed, so the tracker's draws differ from those of
# other services seeded from the same run.seed (e.g. the initial arm configuration).
TRACKER_STREAM_ID = 0x484D44  # "HMD"


def wrap_angle(angle_rad: float | np.ndarray) -> float | np.ndarray:
    """Wrap an angle (or array) to [-pi, pi): how a tracker reports yaw."""
    return (np.asarray(angle_rad) + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True)
class HeadPose:
    """A head pose in the world frame: position (m), yaw and pitch (rad, see module doc)."""

    p_m: np.ndarray  # (3,)
    yaw_rad: float
    pitch_rad: float

    def as_vector(self) -> np.ndarray:
        """The (5,) vector [x, y, z, yaw, pitch] the tracker and filter work on."""
        return np.array([*self.p_m, self.yaw_rad, self.pitch_rad], dtype=np.float64)

    @classmethod
    def from_vector(cls, v: np.ndarray) -> HeadPose:
        """Inverse of :meth:`as_vector`; yaw is wrapped to [-pi, pi)."""
        return cls(
            p_m=np.array(v[:3], dtype=np.float64),
            yaw_rad=float(wrap_angle(v[YAW_INDEX])),
            pitch_rad=float(v[PITCH_INDEX]),
        )


class HeadMotion:
    """The operator's scripted head motion, a pure function of sim time ``t_s``.

    Yaw sways ``yaw_amplitude_rad`` around ``head_yaw_rad`` with ``motion_period_s``; the
    head sways sideways (perpendicular to ``head_yaw_rad``, in the horizontal plane) by
    ``sway_amplitude_m`` in phase with the yaw, as a person leans toward where they look;
    and it nods by :data:`NOD_AMPLITUDE_RAD` twice per period.

    ``still``: the head holds its pose (facing ``head_yaw_rad``): a person at a keyboard
    or a gamepad looks at a screen, so the view frame their keys move in stays put.
    """

    def __init__(self, hmd: HmdConfig, *, still: bool = False) -> None:
        if still:
            hmd = replace(hmd, yaw_amplitude_rad=0.0, sway_amplitude_m=0.0)
        self.still = still
        self.hmd = hmd
        self._center_m = np.array(hmd.head_p_m, dtype=np.float64)
        yaw0 = hmd.head_yaw_rad
        self._lateral = np.array([-math.sin(yaw0), math.cos(yaw0), 0.0])  # head's +y, world
        self._omega_rad_s = 2.0 * math.pi / hmd.motion_period_s
        self._nod_omega_rad_s = self._omega_rad_s / NOD_PERIOD_FRACTION

    def pose(self, t_s: float) -> HeadPose:
        """True head pose at sim time ``t_s`` (s)."""
        s = math.sin(self._omega_rad_s * t_s)
        return HeadPose(
            p_m=self._center_m + self.hmd.sway_amplitude_m * s * self._lateral,
            yaw_rad=float(wrap_angle(self.hmd.head_yaw_rad + self.hmd.yaw_amplitude_rad * s)),
            pitch_rad=0.0
            if self.still
            else NOD_AMPLITUDE_RAD * math.sin(self._nod_omega_rad_s * t_s),
        )


class Tracker:
    """The HMD's tracking sensor: the true pose plus Gaussian noise, reproducibly.

    Position noise ``position_noise_m`` per axis; yaw and pitch noise ``yaw_noise_rad``
    (the config has one angular noise). The draws for a tick come from a generator keyed
    by (run seed, tick), so a sample depends only on the seed and the tick: the same seed
    gives the same measurements whether the service saw the run from tick 0, joined it
    late, or restarted it, and a new run needs no generator state to be reset.
    """

    def __init__(self, hmd: HmdConfig, seed: int) -> None:
        if hmd.position_noise_m < 0 or hmd.yaw_noise_rad < 0:
            raise ValueError("hmd.position_noise_m and hmd.yaw_noise_rad must be >= 0")
        if seed < 0:
            raise ValueError(f"seed must be >= 0, got {seed}")
        self.seed = seed
        self.std = measurement_std(hmd)

    def measure(self, pose: HeadPose, tick: int) -> HeadPose:
        """A noisy measurement of ``pose`` taken at plant tick ``tick`` (yaw wrapped)."""
        rng = np.random.default_rng([TRACKER_STREAM_ID, self.seed, tick])
        noisy = pose.as_vector() + self.std * rng.standard_normal(POSE_DIM)
        return HeadPose.from_vector(noisy)


def measurement_std(hmd: HmdConfig) -> np.ndarray:
    """(5,) standard deviations of a tracker sample: [pos x3 (m), yaw, pitch (rad)]."""
    return np.array([hmd.position_noise_m] * 3 + [hmd.yaw_noise_rad] * 2, dtype=np.float64)


def transition(dt_s: float) -> np.ndarray:
    """(10, 10) constant-velocity state transition over ``dt_s``: x' = x + dt * v."""
    f = np.eye(2 * POSE_DIM)
    f[:POSE_DIM, POSE_DIM:] = dt_s * np.eye(POSE_DIM)
    return f


def process_noise(dt_s: float, accel_std: np.ndarray) -> np.ndarray:
    """(10, 10) process noise of a white (piecewise constant) acceleration over ``dt_s``.

    Per coordinate with acceleration std ``a``: [[dt^4/4, dt^3/2], [dt^3/2, dt^2]] * a^2,
    laid out for the state [pose (5), rates (5)].
    """
    block = np.array([[dt_s**4 / 4.0, dt_s**3 / 2.0], [dt_s**3 / 2.0, dt_s**2]])
    return np.kron(block, np.diag(np.asarray(accel_std, dtype=np.float64) ** 2))


class HeadFilter:
    """Constant-velocity Kalman filter on [x, y, z, yaw, pitch] and their rates.

    Smooths the tracker's samples and predicts the pose ``horizon_s`` ahead (the
    motion-to-use latency) without touching the filter state. Yaw innovations are wrapped
    to [-pi, pi), and the yaw state is kept in [-pi, pi), so a head turning through +-pi
    is tracked without a 2 pi jump. The first sample initialises the pose (rates zero).
    """

    def __init__(
        self,
        period_s: float,
        measurement_std: np.ndarray,
        accel_std: np.ndarray | None = None,
    ) -> None:
        if period_s <= 0:
            raise ValueError(f"period_s must be > 0, got {period_s}")
        self.period_s = period_s
        if accel_std is None:
            accel_std = np.array(
                [HEAD_ACCEL_STD_M_S2] * 3 + [HEAD_ANGULAR_ACCEL_STD_RAD_S2] * 2, dtype=np.float64
            )
        self.accel_std = np.asarray(accel_std, dtype=np.float64)
        r_std = np.maximum(np.asarray(measurement_std, dtype=np.float64), MIN_MEASUREMENT_STD)
        self.kf = KalmanFilter(dim_x=2 * POSE_DIM, dim_z=POSE_DIM)
        self.kf.H = np.hstack([np.eye(POSE_DIM), np.zeros((POSE_DIM, POSE_DIM))])
        self.kf.R = np.diag(r_std**2)
        speed_std = [INITIAL_SPEED_STD_M_S] * 3 + [INITIAL_ANGULAR_SPEED_STD_RAD_S] * 2
        self._p0 = np.diag(np.concatenate([r_std**2, np.square(speed_std)]))
        self._models: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        self.initialized = False
        self.reset()

    @classmethod
    def from_config(cls, hmd: HmdConfig) -> HeadFilter:
        """A filter for the HMD's nominal sample period and the tracker's noise."""
        return cls(1.0 / hmd.rate_hz, measurement_std(hmd))

    def reset(self) -> None:
        """Forget everything: the next sample initialises the filter again."""
        self.kf.x = np.zeros((2 * POSE_DIM, 1))
        self.kf.P = self._p0.copy()
        self.initialized = False

    def _model(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(F, Q) for ``dt_s``; cached, since samples come at a few distinct intervals."""
        model = self._models.get(dt_s)
        if model is None:
            model = (transition(dt_s), process_noise(dt_s, self.accel_std))
            self._models[dt_s] = model
        return model

    def update(self, measured: HeadPose, dt_s: float | None = None) -> HeadPose:
        """Fold in one sample taken ``dt_s`` (s, default the nominal period) after the last.

        Returns the filtered pose at the sample's time.
        """
        z = measured.as_vector()
        if not self.initialized:
            self.kf.x = np.concatenate([z, np.zeros(POSE_DIM)]).reshape(-1, 1)
            self.kf.P = self._p0.copy()
            self.initialized = True
            return self.filtered()
        f, q = self._model(self.period_s if dt_s is None else dt_s)
        self.kf.predict(F=f, Q=q)
        # filterpy computes the innovation as z - Hx; shift the measured yaw by whole turns
        # so that difference is the wrapped one (the short way round).
        predicted_yaw = float(self.kf.x[YAW_INDEX, 0])
        z[YAW_INDEX] = predicted_yaw + float(wrap_angle(z[YAW_INDEX] - predicted_yaw))
        self.kf.update(z)
        self.kf.x[YAW_INDEX, 0] = float(wrap_angle(self.kf.x[YAW_INDEX, 0]))
        return self.filtered()

    def filtered(self) -> HeadPose:
        """The current filtered pose (at the time of the last sample)."""
        return HeadPose.from_vector(self.kf.x[:POSE_DIM, 0])

    def predict_ahead(self, horizon_s: float) -> HeadPose:
        """The pose ``horizon_s`` (s) after the last sample; the filter is left unchanged."""
        x = transition(horizon_s) @ self.kf.x[:, 0]
        return HeadPose.from_vector(x[:POSE_DIM])


@dataclass(frozen=True)
class HeadSample:
    """One HMD output: what the service publishes as a HEAD_POSE record."""

    tick: int  # plant tick of the sample
    t_s: float  # its sim time, s
    valid_from_tick: int  # first plant tick the prediction applies to
    truth: HeadPose  # the scripted pose at t_s (for error statistics, not published)
    measured: HeadPose  # what the tracker reported
    filtered: HeadPose  # the filter's estimate at t_s
    predicted: HeadPose  # the filter's prediction for valid_from_tick
    horizon_s: float  # valid_from_tick - tick, in s


class ErrorStats:
    """Running RMS of position (m, Euclidean) and yaw (rad, wrapped) errors vs a truth."""

    def __init__(self) -> None:
        self.count = 0
        self._sq_position_m2 = 0.0
        self._sq_yaw_rad2 = 0.0

    def add(self, estimate: HeadPose, truth: HeadPose) -> None:
        self.count += 1
        self._sq_position_m2 += float(np.sum((estimate.p_m - truth.p_m) ** 2))
        self._sq_yaw_rad2 += float(wrap_angle(estimate.yaw_rad - truth.yaw_rad)) ** 2

    @property
    def position_rms_m(self) -> float:
        return math.sqrt(self._sq_position_m2 / self.count) if self.count else math.nan

    @property
    def yaw_rms_rad(self) -> float:
        return math.sqrt(self._sq_yaw_rad2 / self.count) if self.count else math.nan

    def summary(self) -> dict[str, float | None]:
        """JSON-ready RMS values (None before the first sample)."""
        return {
            "position_rms_m": self.position_rms_m if self.count else None,
            "yaw_rms_rad": self.yaw_rms_rad if self.count else None,
        }


class HmdEmulator:
    """Motion + tracker + filter, driven by plant ticks; the whole HMD minus the bus.

    :meth:`on_tick` is called for every plant tick (in order, each once); on the HMD's
    sample ticks it returns a :class:`HeadSample`, otherwise None. Error statistics
    against the scripted truth accumulate for the summary: raw measurement and filter vs
    the pose at the sample, prediction and (for comparison) the un-predicted filtered pose
    vs the true pose at ``valid_from_tick``.
    """

    def __init__(self, config: Config) -> None:
        self.schedule = head_schedule(config)
        # A person's operator drives from a screen: no scripted head (run.operator).
        self.motion = HeadMotion(config.hmd, still=config.run.operator != SCRIPTED)
        self.tracker = Tracker(config.hmd, config.run.seed)
        self.filter = HeadFilter.from_config(config.hmd)
        self.reset()

    def reset(self) -> None:
        """Start a new run: forget the filter state and the statistics."""
        self.filter.reset()
        self._last_sample_tick: int | None = None
        self.measured_error = ErrorStats()
        self.filtered_error = ErrorStats()
        self.predicted_error = ErrorStats()
        self.unpredicted_error = ErrorStats()

    @property
    def samples(self) -> int:
        return self.measured_error.count

    def on_tick(self, tick: int) -> HeadSample | None:
        """Process plant tick ``tick``; a sample on the HMD's sample ticks, else None."""
        if not self.schedule.is_sample(tick):
            return None
        timestep_s = self.schedule.tick_s
        t_s = tick * timestep_s
        truth = self.motion.pose(t_s)
        measured = self.tracker.measure(truth, tick)
        dt_s = None
        if self._last_sample_tick is not None and tick > self._last_sample_tick:
            dt_s = (tick - self._last_sample_tick) * timestep_s
        self._last_sample_tick = tick
        filtered = self.filter.update(measured, dt_s)
        horizon_s = self.schedule.lead_s
        predicted = self.filter.predict_ahead(horizon_s)
        future = self.motion.pose(t_s + horizon_s)
        self.measured_error.add(measured, truth)
        self.filtered_error.add(filtered, truth)
        self.predicted_error.add(predicted, future)
        self.unpredicted_error.add(filtered, future)
        return HeadSample(
            tick=tick,
            t_s=t_s,
            valid_from_tick=tick + self.schedule.lead_ticks,
            truth=truth,
            measured=measured,
            filtered=filtered,
            predicted=predicted,
            horizon_s=horizon_s,
        )

    def summary(self) -> dict[str, object]:
        """Sample count and RMS errors (m, rad) of each stage against the truth."""
        return {
            "samples": self.samples,
            "horizon_s": self.schedule.lead_s,
            "measured_error": self.measured_error.summary(),
            "filtered_error": self.filtered_error.summary(),
            "predicted_error": self.predicted_error.summary(),
            "unpredicted_error": self.unpredicted_error.summary(),
        }


class HmdLoop:
    """The HMD clocked by plant ticks: the whole HMD service minus the bus.

    A clock tick ``m`` (from the plant's scene stream, :meth:`on_clock`) runs the
    emulator for every plant tick since the previous clock tick and returns the samples
    taken on the HMD's sample ticks among them: the records are identical to running on
    every plant tick. Every record must be out before the tick it applies to (else
    lockstep would wait for it), so ``lead_ticks`` must be at least the clock's period
    (``plant.scene_rate_hz``): a config error otherwise.

    A clock tick not newer than the last is a re-send (lockstep re-sends an unanswered
    state with the same tick) and is ignored; tick 0 after a later tick is a new run
    and resets the filter and statistics (the tracker noise is keyed by (seed, tick), so
    the same seed gives the same samples again). Not thread-safe: the service holds a
    lock around it.
    """

    def __init__(self, config: Config) -> None:
        scene_gap_ticks = scene_schedule(config).gap_ticks
        if head_schedule(config).lead_ticks < scene_gap_ticks:
            raise ConfigError(
                f"hmd.prediction_s ({config.hmd.prediction_s} s) must be at least one "
                f"scene period (1 / plant.scene_rate_hz: up to {scene_gap_ticks} ticks)"
            )
        self.emulator = HmdEmulator(config)
        self._last_tick = -1
        self.runs = 0
        self.resent_states = 0  # clock ticks seen before (re-sends)

    @property
    def last_tick(self) -> int:
        """The newest plant tick handled (-1: none in this run)."""
        return self._last_tick

    def on_clock(self, tick: int) -> list[HeadSample]:
        """Plant tick ``tick`` reached: the samples of every HMD sample tick up to it."""
        if tick == 0 and self._last_tick != 0:
            if self._last_tick > 0:  # a new run: start from a fresh filter
                self.emulator.reset()
            self.runs += 1
            self._last_tick = -1
        elif tick <= self._last_tick:
            self.resent_states += 1
            return []
        samples = []
        for k in range(self._last_tick + 1, tick + 1):
            sample = self.emulator.on_tick(k)
            if sample is not None:
                samples.append(sample)
        self._last_tick = tick
        return samples


def fill_head_pose(
    rec: np.ndarray, sample: HeadSample, seq: int, t_source_ns: int, timestep_ns: int
) -> None:
    """Write ``sample`` into a HEAD_POSE record (sim time from its tick, ``timestep_ns``)."""
    rec["seq"] = seq
    rec["t_source_ns"] = t_source_ns
    rec["sim_time_ns"] = sample.tick * timestep_ns
    rec["valid_from_tick"] = sample.valid_from_tick
    rec["measured_p_m"] = sample.measured.p_m
    rec["measured_yaw_rad"] = sample.measured.yaw_rad
    rec["filtered_p_m"] = sample.filtered.p_m
    rec["predicted_p_m"] = sample.predicted.p_m
    rec["predicted_yaw_rad"] = sample.predicted.yaw_rad
    rec["predicted_pitch_rad"] = sample.predicted.pitch_rad
    rec["horizon_s"] = sample.horizon_s
