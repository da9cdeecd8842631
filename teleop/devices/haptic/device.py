"""The haptic device: its driver interface, a Falcon-like emulator, and stale-feedback fading.

Frames and units. Everything here is in the *device frame*: x forward (away from the
operator), y left, z up, origin at the centre of the workspace; positions in m,
velocities in m/s, forces in N acting on the handle.

Why an emulator with its own dynamics: the operator's hand and the rendered feedback
force both act on a handle with mass and damping, so feedback is *felt as motion* (the
handle gives way), exactly as on a real device, and a controller that renders a force
from the handle position closes a real mechanical loop whose stability can be checked.

Stability (Colgate and Schenkel, "Passivity of a class of sampled-data systems", 1997):
a virtual wall of stiffness K rendered with a zero-order hold at sample period T on a
device with physical viscous damping b is passive iff ``b > K T / 2 + |B|`` (B: virtual
damping). So the stiffest spring any feedback law may render is ``K_max = 2 b / T``;
with the defaults (b = 3 N s/m, T = 1 ms) that is 6000 N/m, twice the ~3000 N/m a real
Falcon renders and 20x the 300 N/m workspace spring of the teleop config. Each extra
sample of loop delay adds T to the hold, roughly ``K_max = 2 b / ((1 + 2 d) T)``.
The operator's hand adds damping, but the bound must hold without it (a released handle).
"""

from __future__ import annotations

import abc
import collections
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from teleop.bus.messages import Button
from teleop.core.config import HapticConfig

N_AXES = 3  # a Falcon-like device: three translational degrees of freedom
NS_PER_S = 1_000_000_000
# Variance of a uniform quantisation error of step q is q^2 / 12.
UNIFORM_QUANTISATION_VARIANCE_FACTOR = 1.0 / 12.0


def max_stable_stiffness_n_per_m(config: HapticConfig, period_s: float) -> float:
    """Largest stiffness (N/m) a feedback law may render passively: ``K_max = 2 b / T``.

    From Colgate's condition ``b > K T / 2`` with b = ``config.damping_n_s_per_m`` (the
    device's own viscous damping, N s/m) and T = ``period_s`` (the force update period, s).
    Defaults: 2 * 3 / 0.001 = 6000 N/m.
    """
    if period_s <= 0:
        raise ValueError(f"period_s must be > 0, got {period_s}")
    return 2.0 * config.damping_n_s_per_m / period_s


def saturate_force(force_n: np.ndarray, peak_n: float) -> np.ndarray:
    """``force_n`` (3,) scaled down to norm ``peak_n`` if above it (direction kept)."""
    return np.array(saturated_xyz(np.asarray(force_n, dtype=np.float64).tolist(), peak_n))


def saturated_xyz(force_n: list[float], peak_n: float) -> list[float]:
    """:func:`saturate_force` on Python floats (the servo period's own form)."""
    norm = math.hypot(*force_n)  # np.linalg.norm costs several times more
    if norm > peak_n:
        scale = peak_n / norm
        return [f * scale for f in force_n]
    return list(force_n)


@dataclass(frozen=True)
class DeviceSample:
    """One reading of the device, device frame.

    ``p_m`` (3,): encoder position, m (quantised); ``v_m_s`` (3,): velocity estimate, m/s;
    ``f_n`` (3,): force the motors rendered during the last period, N (after saturation);
    ``buttons``: the handle's buttons.
    """

    p_m: np.ndarray
    v_m_s: np.ndarray
    f_n: np.ndarray
    buttons: Button


@dataclass(frozen=True)
class HandInput:
    """What the operator's hand does during one servo period, device frame.

    ``target_p_m`` (3,), m: where the hand pulls the handle; ``buttons``: what it holds
    pressed. Only a device that simulates the hand uses it (see HapticDevice.next_sample).
    """

    target_p_m: np.ndarray
    buttons: Button = Button.NONE


class HapticDevice(abc.ABC):
    """The one interface of a haptic device: the emulator and a real driver alike.

    Everything the haptic service calls is here, so any implementation takes the
    emulator's place unchanged. Lifecycle: :meth:`connect`, then once per servo period
    ``period_s`` :meth:`next_sample` (the force sent by :meth:`send_force`, at any time,
    acts from then on), then :meth:`disconnect`; usable as a context manager.
    :meth:`reset` marks a new run. Not thread-safe: the caller serialises the calls.
    """

    period_s: float  # the servo period, s

    def __enter__(self) -> HapticDevice:
        self.connect()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.disconnect()

    @abc.abstractmethod
    def connect(self) -> None:
        """Open the device (a driver: its link, motors enabled at zero force)."""

    @abc.abstractmethod
    def disconnect(self) -> None:
        """Zero the force and release the device; safe to call twice."""

    @abc.abstractmethod
    def read(self) -> DeviceSample:
        """The latest sample: position (m), velocity (m/s), rendered force (N), buttons."""

    @abc.abstractmethod
    def send_force(self, force_n: np.ndarray) -> None:
        """Apply ``force_n`` (3,), N, device frame, from now on; the device saturates it
        at its peak force."""

    @abc.abstractmethod
    def next_sample(self, hand: HandInput | None) -> DeviceSample:
        """Advance one servo period and return the sample taken at its end.

        ``hand`` is what the operator's hand does meanwhile (None: nobody holds the
        handle). An emulator integrates its handle under that hand and the sent force; a
        device whose handle a real hand holds ignores it and returns its newest hardware
        sample (waiting for one if none came this period).
        """

    @abc.abstractmethod
    def reset(self) -> None:
        """A new run starts: forget the force and per-run state (an emulator also puts its
        handle back at the centre, at rest; a real handle stays where the hand holds it)."""


def steady_state_gains(
    resolution_m: float, accel_noise_m_s2: float, dt_s: float
) -> tuple[float, float]:
    """The gains ``(g, h)`` the constant-velocity Kalman filter of
    :class:`KalmanVelocityEstimator` converges to: ``g`` on the position, ``h`` on the
    velocity times ``dt_s`` (an alpha-beta filter's alpha and beta).

    The model: per axis, state ``[p, v]`` driven by white acceleration of standard deviation
    ``accel_noise_m_s2`` held over each period (filterpy's ``Q_discrete_white_noise``), the
    encoder position measured with quantisation noise of standard deviation
    ``q / sqrt(12)``. Its steady state is known in closed form through the tracking index
    ``lambda = sigma_a T^2 / sigma_w`` (Kalata, "The tracking index", IEEE Trans. AES 20(2),
    1984; Bar-Shalom, Li and Kirubarajan, "Estimation with Applications to Tracking and
    Navigation", 6.5)::

        g = -(lambda^2 + 8 lambda - (lambda + 4) sqrt(lambda^2 + 8 lambda)) / 8
        h = (lambda^2 + 4 lambda - lambda sqrt(lambda^2 + 8 lambda)) / 4

    tests/unit/test_haptics.py checks them against filterpy's ``KalmanFilter`` run to
    convergence on the same model.
    """
    if resolution_m <= 0 or accel_noise_m_s2 <= 0 or dt_s <= 0:
        raise ValueError("resolution_m, accel_noise_m_s2 and dt_s must be > 0")
    sigma_w = resolution_m * math.sqrt(UNIFORM_QUANTISATION_VARIANCE_FACTOR)
    lam = accel_noise_m_s2 * dt_s * dt_s / sigma_w
    root = math.sqrt(lam * lam + 8.0 * lam)
    g = -(lam * lam + 8.0 * lam - (lam + 4.0) * root) / 8.0
    h = (lam * lam + 4.0 * lam - lam * root) / 4.0
    return g, h


class KalmanVelocityEstimator:
    """Velocity from quantised encoder positions: a constant-velocity Kalman filter at its
    steady state (:func:`steady_state_gains`), one per axis.

    Finite differences of quantised positions jump by q / T (20 mm/s at 20 um, 1 ms)
    whenever a count changes; the filter averages those steps over its bandwidth instead.
    The tuning trades lag for noise through ``accel_noise_m_s2`` alone: with q = 20 um and
    T = 1 ms, 3 m/s^2 gives a velocity noise about 5x below finite differences and settles in
    about 15 ms; 30 m/s^2 trusts the encoder so much that it is *noisier* than finite
    differences (std 12.7 vs 9.7 mm/s for a slow constant motion).

    Why the steady state from the start, and not filterpy's ``KalmanFilter`` converging
    to it: the model is time invariant, so the gain settles within about 100 updates
    (0.1 s) of a reset, where the handle is at rest; and importing filterpy (its
    ``kalman`` package brings scipy.stats) took half a second of the device's start-up,
    which a restarted device spends with the robot braked. The update runs in Python
    floats: a few microseconds at the 1 kHz servo rate.
    """

    def __init__(self, resolution_m: float, accel_noise_m_s2: float, dt_s: float) -> None:
        self.resolution_m = resolution_m
        self.accel_noise_m_s2 = accel_noise_m_s2
        self._dt_s = 0.0
        self._g = self._h = 0.0
        self._set_dt(dt_s)
        self._p_m = [0.0] * N_AXES
        self._v_m_s = [0.0] * N_AXES
        self.reset(np.zeros(N_AXES))

    def _set_dt(self, dt_s: float) -> None:
        """The gains for a period of ``dt_s`` (only when it changes)."""
        if dt_s != self._dt_s:
            self._g, self._h = steady_state_gains(self.resolution_m, self.accel_noise_m_s2, dt_s)
            self._dt_s = dt_s

    def reset(self, p_m: np.ndarray) -> None:
        """Restart at position ``p_m`` (3,), m, at rest."""
        self._p_m = [float(x) for x in p_m]
        self._v_m_s = [0.0] * N_AXES

    def update(self, p_measured_m: Sequence[float], dt_s: float) -> np.ndarray:
        """Predict over ``dt_s`` (s), correct with the encoder position (3 floats or an
        array), m; velocity (3,)."""
        self._set_dt(dt_s)
        g, h_per_s = self._g, self._h / dt_s
        p, v = self._p_m, self._v_m_s
        for axis, z in enumerate(map(float, p_measured_m)):
            predicted = p[axis] + v[axis] * dt_s
            residual = z - predicted
            p[axis] = predicted + g * residual
            v[axis] += h_per_s * residual
        return self.velocity_m_s

    @property
    def velocity_m_s(self) -> np.ndarray:
        """Current velocity estimate (3,), m/s (a copy)."""
        return np.array(self._v_m_s, dtype=np.float64)


class EmulatedDevice(HapticDevice):
    """A Falcon-like handle: mass, viscous damping, end stops, encoders, force saturation.

    Forces on the handle (device frame, N): the operator's hand, a spring-damper
    ``K_h (target - p) - B_h v`` toward the hand's target, and the rendered feedback force
    (saturated to ``peak_force_n`` in norm); plus the device's own damping ``-b v``. With the
    defaults (m = 0.15 kg, K_h = 200 N/m, B_h + b = 11 N s/m) the held handle is a
    critically damped (zeta = 1.0) second-order system with omega_n = 36.5 rad/s, and a
    steady feedback force F moves it by F / K_h (8 N peak: 40 mm, inside the 50 mm stops).

    Integration, per period dt: the damping is taken implicitly and the springs
    semi-implicitly (new velocity first, then position with the new velocity)::

        v' = (v + dt / m * (K_h (target - p) + F_fb)) / (1 + dt (b + B_h) / m)
        p' = p + dt v'

    Semi-implicit (symplectic) Euler keeps a spring's energy bounded where explicit Euler
    would inject energy every step, which would fake (or hide) exactly the instability the
    Colgate bound is about; it is stable for omega_n dt < 2 (here 0.037). The implicit
    damping is dissipative for any dt. End stops at +-``workspace_half_m`` per axis are
    inelastic: the position is clamped and the velocity component into the stop zeroed.
    """

    def __init__(self, config: HapticConfig, period_s: float) -> None:
        if period_s <= 0:
            raise ValueError(f"period_s must be > 0, got {period_s}")
        self.config = config
        self.period_s = period_s
        self._estimator = KalmanVelocityEstimator(
            config.encoder_resolution_m, config.kf_accel_noise_m_s2, period_s
        )
        self.connected = False
        self.reset()

    def reset(self) -> None:
        """Handle at the centre, at rest, no force, no buttons; velocity filter restarted."""
        # The state as Python floats, one per axis: the servo period runs a few dozen
        # operations on 3-vectors, each cheaper on floats than a numpy call (and the
        # same IEEE operations in the same order: the same results). numpy at the
        # interface only (send_force, read).
        self._p_m = [0.0] * N_AXES
        self._v_m_s = [0.0] * N_AXES
        self._f_command_n = [0.0] * N_AXES
        self._f_rendered_n = [0.0] * N_AXES
        self._p_encoder_m = [0.0] * N_AXES
        self._v_estimate_m_s = np.zeros(N_AXES)
        self._buttons = Button.NONE
        self._estimator.reset(np.zeros(N_AXES))

    # -- HapticDevice ------------------------------------------------------------------
    def connect(self) -> None:
        """Nothing to open in an emulator."""
        self.connected = True

    def disconnect(self) -> None:
        """Nothing to release in an emulator; zero the force as a driver would."""
        self._f_command_n = [0.0] * N_AXES
        self.connected = False

    def send_force(self, force_n: np.ndarray) -> None:
        """Set the force for the next :meth:`step`, saturated to ``peak_force_n`` in norm."""
        self._f_command_n = saturated_xyz(force_n.tolist(), self.config.peak_force_n)

    def read(self) -> DeviceSample:
        """Encoder position (quantised), Kalman velocity, last rendered force, buttons."""
        return DeviceSample(
            p_m=np.array(self._p_encoder_m),
            v_m_s=self._v_estimate_m_s.copy(),
            f_n=np.array(self._f_rendered_n),
            buttons=self._buttons,
        )

    def next_sample(self, hand: HandInput | None) -> DeviceSample:
        """One :meth:`step` of ``period_s`` under ``hand``, then :meth:`read`."""
        if hand is None:
            self.step(self.period_s, None, Button.NONE)
        else:
            self.step(self.period_s, hand.target_p_m, hand.buttons)
        return self.read()

    # -- the emulation -----------------------------------------------------------------
    def step(
        self,
        dt_s: float,
        hand_target_p_m: np.ndarray | None,
        buttons: Button = Button.NONE,
    ) -> None:
        """Integrate one period ``dt_s`` (s) under the hand and the rendered force.

        ``hand_target_p_m`` (3,), m, device frame: where the hand pulls the handle; None
        means no hand force at all (nobody holds the handle: it only feels the feedback
        force and its own damping). ``buttons``: what the hand holds pressed.
        """
        c = self.config
        force = self._f_command_n
        damping = c.damping_n_s_per_m
        if hand_target_p_m is not None:
            k = c.hand_stiffness_n_per_m
            targets = hand_target_p_m.tolist()
            force = [f + k * (t - x) for f, t, x in zip(force, targets, self._p_m, strict=True)]
            damping += c.hand_damping_n_s_per_m
        m = c.handle_mass_kg
        gain, divisor = dt_s / m, 1.0 + dt_s * damping / m
        half, q = c.workspace_half_m, c.encoder_resolution_m
        p_new, v_new, encoder = [], [], []
        for p, v, f in zip(self._p_m, self._v_m_s, force, strict=True):
            v = (v + gain * f) / divisor
            p = p + dt_s * v
            if p > half:
                p, v = half, min(v, 0.0)  # the end stop: no speed into it
            elif p < -half:
                p, v = -half, max(v, 0.0)
            p_new.append(p)
            v_new.append(v)
            encoder.append(q * round(p / q))
        self._p_m, self._v_m_s = p_new, v_new
        self._f_rendered_n = self._f_command_n
        self._buttons = Button(buttons)
        self._p_encoder_m = encoder
        self._v_estimate_m_s = self._estimator.update(encoder, dt_s)

    @property
    def true_p_m(self) -> np.ndarray:
        """Exact handle position (3,), m (emulator only: tests and diagnostics)."""
        return np.array(self._p_m)

    @property
    def true_v_m_s(self) -> np.ndarray:
        """Exact handle velocity (3,), m/s (emulator only)."""
        return np.array(self._v_m_s)


@dataclass(frozen=True)
class LocalContactModel:
    """What the handle feels between two feedback records (device frame, SI).

    The controller computes the feedback once per bus period, at the handle position it
    last received; the device renders at its own servo rate (``haptic.render_period_s``)
    ``force_n + k_n_per_m (p - p_ref_m)`` at the handle's position ``p`` now: the
    feedback's force held, plus how it changes with the handle about where it was
    computed (the workspace spring's Jacobian: model-mediated teleoperation, the
    "intermediate representation" of haptic rendering). ``k_n_per_m`` (3, 3): dF/dp,
    N/m, negative definite for a spring that pushes back.
    """

    force_n: np.ndarray  # (3,) N at p_ref_m
    p_ref_m: np.ndarray  # (3,) m
    k_n_per_m: np.ndarray  # (3, 3) N/m

    @classmethod
    def constant(cls, force_n: np.ndarray) -> LocalContactModel:
        """A force that does not change with the handle's position."""
        force = np.array(force_n, dtype=np.float64)
        return cls(force, np.zeros(N_AXES), np.zeros((N_AXES, N_AXES)))

    def force_at(self, p_m: np.ndarray) -> np.ndarray:
        """The force (3,), N, at handle position ``p_m`` (3,), m."""
        return self.force_n + self.k_n_per_m @ (np.asarray(p_m, dtype=np.float64) - self.p_ref_m)

    def scaled(self, factor: float) -> LocalContactModel:
        """The same model with force and stiffness times ``factor`` (a fade)."""
        return LocalContactModel(self.force_n * factor, self.p_ref_m, self.k_n_per_m * factor)


ZERO_MODEL = LocalContactModel.constant(np.zeros(N_AXES))


class ForceSlew:
    """The rendered force's rate limit: a new local model (or a fade) never jumps the
    force on the handle faster than ``max_rate_n_per_s``.

    A feedback record comes once per bus period; rendered as it comes, each one would
    be a step of up to the device's peak force, which the hand feels as a knock at the
    bus rate (and which puts energy into a stiff contact, the chatter a passivity
    controller then has to take out). Limited to ``max_rate_n_per_s`` the force ramps
    over a few servo periods instead; the default (haptic.max_force_rate_n_per_s) lets
    the peak force come within one 4 ms bus period.
    """

    def __init__(self, max_rate_n_per_s: float, period_s: float) -> None:
        if max_rate_n_per_s <= 0 or period_s <= 0:
            raise ValueError("max_rate_n_per_s and period_s must be > 0")
        self.max_step_n = max_rate_n_per_s * period_s
        self._last_n = [0.0] * N_AXES  # Python floats: cheaper than numpy at this size
        self.limited_steps = 0  # servo periods whose force change was cut

    def reset(self) -> None:
        self._last_n = [0.0] * N_AXES

    def limit(self, force_n: np.ndarray) -> np.ndarray:
        """``force_n`` (3,), N, moved from the last one by at most the step (direction of
        the change kept)."""
        last = self._last_n
        change = [f - x for f, x in zip(force_n.tolist(), last, strict=True)]
        size = math.hypot(*change)
        if size > self.max_step_n:
            scale = self.max_step_n / size
            change = [d * scale for d in change]
            self.limited_steps += 1
        self._last_n = [x + d for x, d in zip(last, change, strict=True)]
        return np.array(self._last_n)


# Local models FeedbackHold keeps by arrival time: the device's renders of one bus period
# look up the newest received before each render (a few arrive per period at most).
MODEL_HISTORY = 8


class FeedbackHold:
    """The received local contact models by arrival time, the newest one faded out when
    it gets old; never held stale.

    A model older than ``stale_after_s`` no longer describes the robot (the controller
    stalled or the link dropped): holding it would push the operator's hand with a force
    nothing produces any more, and an abrupt cut to zero would kick the handle. So it
    fades linearly to zero over ``fade_s``, then stays zero until fresh feedback arrives.
    Times are integer ns of one clock: monotonic arrival time in realtime, sim time in
    lockstep. A device that renders a bus period's servo periods in one go (the emulator)
    asks for each render's time and gets the model that had arrived by then, as a 1 kHz
    servo thread would have. Not thread-safe: the service holds its own lock around it.
    """

    def __init__(self, stale_after_s: float, fade_s: float) -> None:
        if stale_after_s <= 0 or fade_s <= 0:
            raise ValueError("stale_after_s and fade_s must be > 0")
        self.stale_after_ns = round(stale_after_s * NS_PER_S)
        self.fade_ns = round(fade_s * NS_PER_S)
        self._models: collections.deque[tuple[int, LocalContactModel]] = collections.deque(
            maxlen=MODEL_HISTORY
        )
        # What was rendered before the oldest model kept came: (received at, model).
        self._before: tuple[int | None, LocalContactModel] = (None, ZERO_MODEL)
        self._stale = False
        self.stale_events = 0  # fresh -> stale transitions

    def receive(self, model: LocalContactModel, t_ns: int) -> None:
        """Store a fresh model, received at ``t_ns`` (not before the last one's)."""
        if self._models and t_ns < self._models[-1][0]:
            t_ns = self._models[-1][0]
        if len(self._models) == self._models.maxlen:
            self._before = self._models[0]
        self._models.append((t_ns, model))
        self._stale = False

    def clear(self) -> None:
        """Forget the models held (a new run); counters are kept."""
        self._models.clear()
        self._before = (None, ZERO_MODEL)
        self._stale = False

    def model_at(self, t_ns: int) -> tuple[LocalContactModel, bool, int | None]:
        """(model to render at ``t_ns``, stale, when it was received): the newest received
        by ``t_ns``; a zero force before the first.

        ``stale`` is True once the model is older than ``stale_after_s`` (fading, or faded
        out to zero); its first occurrence after a receive counts one stale event.
        """
        received_ns, model = self._before
        for at_ns, candidate in self._models:
            if at_ns > t_ns:
                break
            received_ns, model = at_ns, candidate
        if received_ns is None:
            return model, False, None
        overdue_ns = t_ns - received_ns - self.stale_after_ns
        if overdue_ns <= 0:
            return model, False, received_ns
        if not self._stale and received_ns == self._models[-1][0]:
            self._stale = True
            self.stale_events += 1
        return model.scaled(max(0.0, 1.0 - overdue_ns / self.fade_ns)), True, received_ns


# A force from the robot's feedback below this is not felt (N): the handle's own friction
# and the encoder's quantisation are larger.
FELT_FORCE_N = 0.01
# Stale spells StaleSpells keeps in full (the count goes on beyond them).
MAX_SPELLS_KEPT = 32


@dataclass
class StaleSpell:
    """One spell of stale feedback (times on the device's feedback clock, integer ns)."""

    received_ns: int  # the last fresh model's receipt: the spell's start
    last_stale_ns: int  # the last render it was still stale
    felt_until_ns: int  # the last render the handle still felt a force from it

    def summary(self) -> dict[str, float]:
        return {
            "missing_ms": (self.last_stale_ns - self.received_ns) / 1e6,
            "felt_ms": max(0, self.felt_until_ns - self.received_ns) / 1e6,
        }


class StaleSpells:
    """What the handle felt while its feedback was stale (the link or the controller
    silent): per spell, how long the feedback was missing and how long after the last
    fresh model the handle still felt a force from it (a stale force held would be felt
    for the whole spell; :class:`FeedbackHold` fades it out after ``stale_after_s``).
    The first :data:`MAX_SPELLS_KEPT` spells are kept; :attr:`felt_max_ms` covers all."""

    def __init__(self) -> None:
        self.spells: list[StaleSpell] = []
        self.count = 0
        self.felt_max_ms = 0.0
        self._open: StaleSpell | None = None

    @property
    def open(self) -> bool:
        """Whether a spell is under way (the next render may close it)."""
        return self._open is not None

    def render(self, t_ns: int, stale: bool, received_ns: int | None, force_n: float) -> None:
        """One render at ``t_ns``: whether its model was stale, when that model was
        received, and the size of the force from it (N)."""
        if not stale or received_ns is None:
            self._open = None
            return
        spell = self._open
        if spell is None or spell.received_ns != received_ns:
            spell = self._open = StaleSpell(received_ns, t_ns, received_ns)
            self.count += 1
            if len(self.spells) < MAX_SPELLS_KEPT:
                self.spells.append(spell)
        spell.last_stale_ns = t_ns
        if force_n > FELT_FORCE_N:
            spell.felt_until_ns = t_ns
            self.felt_max_ms = max(self.felt_max_ms, (t_ns - received_ns) / 1e6)

    def summary(self) -> dict[str, object]:
        return {
            "count": self.count,
            "felt_max_ms": self.felt_max_ms,
            "spells": [spell.summary() for spell in self.spells],
        }
