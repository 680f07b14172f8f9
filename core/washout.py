"""Six-degree-of-freedom classical washout (paper §4.1, Formulas 12–13; REFERENCE.md §3).

Input: the specific force f (m/s²) and angular velocity ω (rad/s) the patient should feel, head frame,
with f relative to standing still (zero at rest; the 1 g of standing is added here). Output: the
stance-frame platform pose, velocity and acceleration relative to neutral, (x, y, z, roll, pitch, yaw)
with R = Rx·Ry·Rz; velocity and acceleration are pose derivatives (Euler-angle rates).

1. Scale and limit f and ω (the limit is reported per sample, never silent).
2. Tilt coordination: corrected Formula 13, a LOW-pass ω_h²/(s² + 2ξω_h s + ω_h²) on f_x, f_y, then
   roll = asin(f_y/g), pitch = −asin(f_x/g) (gravity then appears along +y / +x of the head frame),
   then a tilt-rate limiter.
3. Rotational channel: body rates → Euler rates at the tilt attitude, high-pass s²/(s² + 2ξω_b s + ω_b²),
   integrated; the tilt angles are added.
4. Translational channel: a = R(β)·(f + g e_z) − g e_z (gravity removed in the inertial frame, with the
   platform attitude β), Formula 12 G1 = s²/(s² + 2ξω_a s + ω_a²) · s/(s + ω_a′), integrated twice.
   The integrations are folded into the filters (position = s/((s² + …)(s + ω_a′)) · a), so no pure
   integrator can drift.

Every filter is a first- or second-order section discretised by Tustin at construction. There is one
implementation, `run_washout`: `washout_batch` runs it over whole signals (`scipy.signal.lfilter`, in
cache-sized chunks that carry the filter states, so the result does not depend on the chunk size), and
populations run it over stacked designs. The real-time tick computes no washout: it plays the samples a
plan computed here and checked (`core.plan.motion`).

The tilt-rate limiter is the one sequential nonlinearity. Everything upstream of it is computed first
and vectorised; if no step of the commanded tilt exceeds the limit the limiter is the identity and the
path stays pure numpy; otherwise a compiled limiter runs over the two tilt signals only (a compiled
loop, exact, a few ms per hour of data).
The Euler-rate transform uses the tilt attitude, known before the rotational channel, rather than
the full attitude (which would feed the channel's own output back); the washed-out rotation is
small and transient, the tilt is the sustained part.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from typing import Any

import numba
import numpy as np

from core.errors import refuse_unknown_fields
from core.physics import GRAVITY_M_S2
from core.shaping import (
    ParameterError,
    filter_sections,
    require_finite,
    require_sample_period,
    tustin_first_order,
    tustin_second_order,
)

HEAD_HEIGHT_MAX_M = 2.5
BATCH_CHUNK_SAMPLES = 32_768


@dataclass(frozen=True)
class WashoutParameters:
    """Classical-washout parameters, SI units. Defaults are `baseline_parameters()`."""

    specific_force_gain: float = 1.0
    specific_force_limit_m_s2: float = 5.0  # paper §3.2: peak acceleration 5 m/s²
    translational_damping: float = 1.0  # ξ, Formula 12
    translational_break_rad_s: float = 2.0  # ω_a
    translational_first_order_break_rad_s: float = 0.5  # ω_a′
    tilt_damping: float = 1.0  # ξ, Formula 13 (corrected to a low-pass)
    tilt_break_rad_s: float = 0.4  # ω_h
    tilt_rate_limit_rad_s: float = math.radians(3.0)  # roll perception threshold (REFERENCE.md §4)
    angular_velocity_gain: float = 1.0
    angular_velocity_limit_rad_s: float = 1.0
    rotational_damping: float = 1.0
    rotational_break_rad_s: float = 1.0
    # Height of the patient's head above the foot plates. 0 (the paper): the cue is delivered at the rotation
    # centre. > 0: the translational channel also cancels the lever-arm terms of the platform's rotation
    # (ω̇ × r + ω × (ω × r), `core.perception`), so that the head feels the cue.
    head_height_m: float = 0.0

    def __post_init__(self) -> None:
        for item in fields(self):
            value = getattr(self, item.name)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ParameterError(item.name, value, "must be a number")
            if not math.isfinite(value):
                raise ParameterError(item.name, value, "must be a finite number (no NaN/inf)")
            if item.name.endswith("_gain"):
                if value < 0.0:
                    raise ParameterError(item.name, value, "must be >= 0 (0 switches the channel off)")
            elif item.name == "head_height_m":
                if not 0.0 <= value <= HEAD_HEIGHT_MAX_M:
                    raise ParameterError(
                        item.name, value, f"must be in [0, {HEAD_HEIGHT_MAX_M:g}] m (0: rotation centre)"
                    )
            elif value <= 0.0:
                raise ParameterError(item.name, value, "must be > 0")
        lowpass_peak = self.specific_force_limit_m_s2 * _lowpass_peak_factor(self.tilt_damping)
        if lowpass_peak >= 0.99 * GRAVITY_M_S2:
            raise ParameterError(
                "specific_force_limit_m_s2",
                self.specific_force_limit_m_s2,
                f"with tilt_damping {self.tilt_damping:g} the tilt low-pass can reach {lowpass_peak:.3g} m/s²; "
                f"it must stay below 0.99 g = {0.99 * GRAVITY_M_S2:.4g} m/s² for asin(f/g)",
            )

    def to_dict(self) -> dict[str, float]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> WashoutParameters:
        refuse_unknown_fields(cls, data, ParameterError, "washout parameter")
        return cls(**dict(data))


def _lowpass_peak_factor(damping: float) -> float:
    """‖h‖₁ of the tilt low-pass: the largest output per unit of bounded input, (1 + M)/(1 − M)."""
    if damping >= 1.0:
        return 1.0
    overshoot = math.exp(-math.pi * damping / math.sqrt(1.0 - damping * damping))
    if overshoot >= 1.0:  # damping so small that the exponential rounds to 1: the filter rings without bound
        return math.inf
    return (1.0 + overshoot) / (1.0 - overshoot)


def baseline_parameters() -> WashoutParameters:
    """The documented starting point for tuning (docs/washout.md): critically damped, ω_a = 2 rad/s,
    ω_a′ = 0.5 rad/s, ω_h = 0.4 rad/s (slow enough that the paper's square wave never asks the tilt for more
    than the 3 °/s roll threshold the rate limiter enforces)."""
    return WashoutParameters()


def paper_tilt_parameters() -> WashoutParameters:
    """Tilt channel that reproduces the paper's §5 run: ξ = 0.8, ω_h = 1.72 rad/s gives 0.201 rad within
    1.96 s (95 %) at a peak rate of 0.147 rad/s; the paper's tilt was bounded by its filter, so the
    rate limit (0.16 rad/s) sits just above that peak and does not act."""
    return WashoutParameters(
        translational_damping=1.0,
        translational_break_rad_s=2.5,
        translational_first_order_break_rad_s=0.5,
        tilt_damping=0.8,
        tilt_break_rad_s=1.72,
        tilt_rate_limit_rad_s=0.16,
    )


# --- Design -----------------------------------------------------------------------------------------

# Rows of the section bank: each stage is one Tustin section; position runs POSITION then LAG.
TILT_LOWPASS, ROTATION_ANGLE, ROTATION_RATE, HIGHPASS_SQUARED, LAG, POSITION = range(6)


@dataclass(frozen=True)
class WashoutDesign:
    """Coefficients of one parameter set, or of P sets stacked (population evaluation).

    `bank` is (6, 6) or (P, 6, 6); the scalars are floats or (P, 1, 1) arrays that broadcast against
    signals (P, 3, N)."""

    sample_period_s: float
    bank: np.ndarray
    specific_force_gain: Any
    specific_force_limit_m_s2: Any
    angular_velocity_gain: Any
    angular_velocity_limit_rad_s: Any
    tilt_rate_step_rad: Any  # rate limit × sample period
    first_order_break_rad_s: Any  # ω_a′: acceleration = s/(s + ω_a′)·u = u − ω_a′·(1/(s + ω_a′))·u
    head_height_m: Any = 0.0

    def sections(self, *rows: int) -> np.ndarray:
        return self.bank[..., list(rows), :]


def design(params: WashoutParameters | Sequence[WashoutParameters], sample_period_s: float) -> WashoutDesign:
    """Discretise one parameter set (or a sequence of them, stacked) at `sample_period_s`."""
    require_sample_period(sample_period_s)
    stacked = not isinstance(params, WashoutParameters)
    items = list(params) if stacked else [params]  # type: ignore[arg-type]
    values = {item.name: np.array([getattr(p, item.name) for p in items]) for item in fields(WashoutParameters)}
    nyquist_rad_s = math.pi / sample_period_s
    for name in (
        "translational_break_rad_s",
        "translational_first_order_break_rad_s",
        "tilt_break_rad_s",
        "rotational_break_rad_s",
    ):
        if np.any(values[name] >= 0.1 * nyquist_rad_s):
            raise ParameterError(
                name, float(np.max(values[name])), f"must be below a tenth of Nyquist, {0.1 * nyquist_rad_s:.4g} rad/s"
            )
    bank = _section_bank(values, sample_period_s)

    def scalar(name: str) -> Any:
        return values[name][:, None, None] if stacked else float(values[name][0])

    return WashoutDesign(
        sample_period_s=float(sample_period_s),
        bank=bank if stacked else bank[0],
        specific_force_gain=scalar("specific_force_gain"),
        specific_force_limit_m_s2=scalar("specific_force_limit_m_s2"),
        angular_velocity_gain=scalar("angular_velocity_gain"),
        angular_velocity_limit_rad_s=scalar("angular_velocity_limit_rad_s"),
        tilt_rate_step_rad=scalar("tilt_rate_limit_rad_s") * sample_period_s,
        first_order_break_rad_s=scalar("translational_first_order_break_rad_s"),
        head_height_m=scalar("head_height_m"),
    )


def _section_bank(values: Mapping[str, np.ndarray], sample_period_s: float) -> np.ndarray:
    """(P, 6, 6) sos rows for P parameter sets, one Tustin mapping per stage, vectorised over P."""
    zeros, ones = np.zeros_like(values["tilt_break_rad_s"]), np.ones_like(values["tilt_break_rad_s"])

    def quadratic(damping: np.ndarray, frequency: np.ndarray) -> np.ndarray:
        return np.stack([ones, 2.0 * damping * frequency, frequency * frequency], axis=-1)

    def second(numerator: tuple[np.ndarray, np.ndarray, np.ndarray], denominator: np.ndarray) -> np.ndarray:
        return tustin_second_order(np.stack(numerator, axis=-1), denominator, sample_period_s)

    def first(numerator: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        first_order = np.stack([ones, values["translational_first_order_break_rad_s"]], axis=-1)
        return tustin_first_order(np.stack(numerator, axis=-1), first_order, sample_period_s)

    tilt = quadratic(values["tilt_damping"], values["tilt_break_rad_s"])
    rotation = quadratic(values["rotational_damping"], values["rotational_break_rad_s"])
    translation = quadratic(values["translational_damping"], values["translational_break_rad_s"])
    rows = {
        TILT_LOWPASS: second((zeros, zeros, values["tilt_break_rad_s"] ** 2), tilt),  # Formula 13, low-pass
        ROTATION_ANGLE: second((zeros, ones, zeros), rotation),  # high-pass, integrated once
        ROTATION_RATE: second((ones, zeros, zeros), rotation),
        HIGHPASS_SQUARED: second((ones, zeros, zeros), translation),  # Formula 12, first factor
        LAG: first((zeros, ones)),  # 1/(s + ω_a′): Formula 12's second factor s/(s + ω_a′), integrated once
        POSITION: second((zeros, ones, zeros), translation),  # s/(s² + …): first factor integrated twice
    }
    return np.stack([rows[index] for index in range(len(rows))], axis=-2)


# --- Signal arithmetic -------------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _rate_limited(previous: float, command: float, max_step: float) -> float:
    change = command - previous
    if change > max_step:
        return previous + max_step
    if change < -max_step:
        return previous - max_step
    return command


@numba.njit(cache=True)
def _rate_limit_rows(commands: np.ndarray, max_steps: np.ndarray, initial: np.ndarray, out: np.ndarray) -> None:
    for row in range(commands.shape[0]):
        previous = initial[row]
        for sample in range(commands.shape[1]):
            previous = _rate_limited(previous, commands[row, sample], max_steps[row])
            out[row, sample] = previous


def rate_limit(commands: np.ndarray, max_step: Any, initial: Any = 0.0) -> np.ndarray:
    """Rate-limit signals (..., N) starting from `initial` (...,): each sample moves at most `max_step`.

    Vectorised identity when no step exceeds the limit; otherwise the compiled sequential limiter."""
    commands = np.asarray(commands, dtype=float)
    initial = np.broadcast_to(np.asarray(initial, dtype=float), commands.shape[:-1])
    steps = np.abs(np.diff(commands, axis=-1, prepend=initial[..., None]))
    max_step = np.asarray(max_step, dtype=float)
    if np.all(steps <= max_step):
        return commands
    rows = np.ascontiguousarray(commands.reshape(-1, commands.shape[-1]))
    row_steps = np.ascontiguousarray(np.broadcast_to(max_step, (*commands.shape[:-1], 1)).reshape(-1))
    out = np.empty_like(rows)
    _rate_limit_rows(rows, row_steps, np.ascontiguousarray(initial).reshape(-1), out)
    return out.reshape(commands.shape)


def backward_rate(signal: np.ndarray, sample_period_s: float, previous: Any = 0.0) -> np.ndarray:
    """(x_k − x_{k−1})/T along the last axis, with x_{−1} = `previous` (rest by default)."""
    previous = np.broadcast_to(np.asarray(previous, dtype=float), signal.shape[:-1])
    return np.diff(signal, axis=-1, prepend=previous[..., None]) / sample_period_s


def rotate(angles: np.ndarray, vectors: np.ndarray, *, inverse: bool = False) -> np.ndarray:
    """R(roll, pitch, yaw)·v (or Rᵀ·v), R = Rx·Ry·Rz; angles and vectors (..., 3, N), time last."""
    ca, cb, cc = np.cos(angles[..., 0, :]), np.cos(angles[..., 1, :]), np.cos(angles[..., 2, :])
    sa, sb, sc = np.sin(angles[..., 0, :]), np.sin(angles[..., 1, :]), np.sin(angles[..., 2, :])
    matrix = (
        (cb * cc, -cb * sc, sb),
        (ca * sc + sa * sb * cc, ca * cc - sa * sb * sc, -sa * cb),
        (sa * sc - ca * sb * cc, sa * cc + ca * sb * sc, ca * cb),
    )
    x, y, z = vectors[..., 0, :], vectors[..., 1, :], vectors[..., 2, :]
    if inverse:
        rows = [matrix[0][i] * x + matrix[1][i] * y + matrix[2][i] * z for i in range(3)]
    else:
        rows = [matrix[i][0] * x + matrix[i][1] * y + matrix[i][2] * z for i in range(3)]
    return np.stack(rows, axis=-2)


def body_rates(angles: np.ndarray, euler_rates: np.ndarray) -> np.ndarray:
    """Angular velocity in the moving (head) frame from Euler-angle rates, R = Rx·Ry·Rz; (..., 3, N)."""
    cb, cc = np.cos(angles[..., 1, :]), np.cos(angles[..., 2, :])
    sb, sc = np.sin(angles[..., 1, :]), np.sin(angles[..., 2, :])
    roll_rate, pitch_rate, yaw_rate = euler_rates[..., 0, :], euler_rates[..., 1, :], euler_rates[..., 2, :]
    return np.stack(
        [cb * cc * roll_rate + sc * pitch_rate, -cb * sc * roll_rate + cc * pitch_rate, sb * roll_rate + yaw_rate],
        axis=-2,
    )


def body_angular_acceleration(angles: np.ndarray, rates: np.ndarray, accelerations: np.ndarray) -> np.ndarray:
    """ω̇_b: the derivative of `body_rates` (R = Rx·Ry·Rz), time last (..., 3, N)."""
    pitch, yaw = angles[..., 1, :], angles[..., 2, :]
    cb, sb, cc, sc = np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    roll_rate, pitch_rate, yaw_rate = rates[..., 0, :], rates[..., 1, :], rates[..., 2, :]
    from_rates = np.stack(
        [
            (-sb * cc * pitch_rate - cb * sc * yaw_rate) * roll_rate + cc * yaw_rate * pitch_rate,
            (sb * sc * pitch_rate - cb * cc * yaw_rate) * roll_rate - sc * yaw_rate * pitch_rate,
            cb * pitch_rate * roll_rate,
        ],
        axis=-2,
    )
    return body_rates(angles, accelerations) + from_rates


def lever_arm_acceleration(
    angular_velocity: np.ndarray, angular_acceleration: np.ndarray, head_height_m: Any
) -> np.ndarray:
    """ω̇_b × r + ω_b × (ω_b × r) for r = (0, 0, h), head axes (..., 3, N)."""
    wx, wy, wz = angular_velocity[..., 0, :], angular_velocity[..., 1, :], angular_velocity[..., 2, :]
    ax, ay = angular_acceleration[..., 0, :], angular_acceleration[..., 1, :]
    unit = np.stack([ay + wx * wz, -ax + wy * wz, -(wx * wx + wy * wy)], axis=-2)
    return head_height_m * unit


# --- Batch ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class WashoutTrajectory:
    """Platform motion for N samples, stance frame, relative to neutral."""

    sample_period_s: float
    pose: np.ndarray  # (N, 6) m, rad
    velocity: np.ndarray  # (N, 6) m/s, rad/s (Euler-angle rates)
    acceleration: np.ndarray  # (N, 6) m/s², rad/s²
    input_limited: np.ndarray  # (N,) bool: the scaling limit clipped f or ω at this sample
    tilt_rate_limited: np.ndarray  # (N,) bool: the tilt-rate limiter changed the tilt at this sample

    @property
    def time_s(self) -> np.ndarray:
        return np.arange(len(self.pose)) * self.sample_period_s


@dataclass(frozen=True)
class WashoutSignals:
    """Pipeline output with time last: pose/velocity/acceleration (..., 6, N), tilt command (..., 2, N)."""

    pose: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    tilt_command: np.ndarray
    tilt: np.ndarray
    input_limited: np.ndarray  # (..., N)


class WashoutCarry:
    """What one chunk of `run_washout` leaves to the next: filter states and last samples.

    A fresh carry is rest. Only single designs carry state (populations run in one piece)."""

    def __init__(self) -> None:
        self._filter_states: dict[str, np.ndarray] = {}
        self._last: dict[str, np.ndarray] = {}

    def filter(self, key: str, sos: np.ndarray, signal: np.ndarray) -> np.ndarray:
        if sos.ndim == 3:
            return filter_sections(sos, signal)
        filtered, self._filter_states[key] = filter_sections(sos, signal, self._filter_states.get(key))
        return filtered

    def last(self, key: str) -> Any:
        return self._last.get(key, 0.0)

    def remember(self, key: str, signal: np.ndarray) -> np.ndarray:
        self._last[key] = signal[..., -1].copy()
        return signal

    def rate(self, key: str, signal: np.ndarray, sample_period_s: float) -> np.ndarray:
        rate = backward_rate(signal, sample_period_s, self.last(key))
        self.remember(key, signal)
        return rate


def _scaled(signal: np.ndarray, gain: Any, limit: Any) -> tuple[np.ndarray, np.ndarray]:
    scaled = gain * signal
    limited = np.abs(scaled) > limit
    return np.clip(scaled, -limit, limit), np.any(limited, axis=-2)


def run_washout(
    wd: WashoutDesign,
    specific_force: np.ndarray,
    angular_velocity: np.ndarray,
    carry: WashoutCarry | None = None,
) -> WashoutSignals:
    """The washout over signals (..., 3, N), time last; broadcasts over a stacked design. With `carry`,
    continues from where the previous chunk stopped (and updates it); without, starts from rest."""
    carry = carry or WashoutCarry()
    dt = wd.sample_period_s
    force, force_limited = _scaled(specific_force, wd.specific_force_gain, wd.specific_force_limit_m_s2)
    rates, rates_limited = _scaled(angular_velocity, wd.angular_velocity_gain, wd.angular_velocity_limit_rad_s)

    # Tilt coordination: low-pass (Formula 13 corrected), asin, rate limit.
    lowpass = carry.filter("tilt", wd.sections(TILT_LOWPASS), force[..., :2, :])
    tilt_command = np.stack(
        [np.arcsin(lowpass[..., 1, :] / GRAVITY_M_S2), -np.arcsin(lowpass[..., 0, :] / GRAVITY_M_S2)], axis=-2
    )
    tilt = rate_limit(tilt_command, wd.tilt_rate_step_rad, carry.last("tilt"))
    tilt_rate = carry.rate("tilt", tilt, dt)
    tilt_acceleration = carry.rate("tilt_rate", tilt_rate, dt)

    # Rotational channel: Euler rates at the tilt attitude (yaw 0), high-pass, integrated.
    pitch = tilt[..., 1, :]
    cos_pitch = np.cos(pitch)
    roll_rate = rates[..., 0, :] / cos_pitch
    euler_rates = np.stack([roll_rate, rates[..., 1, :], rates[..., 2, :] - np.sin(pitch) * roll_rate], axis=-2)
    angle = carry.filter("angle", wd.sections(ROTATION_ANGLE), euler_rates)
    angle_rate = carry.filter("angle_rate", wd.sections(ROTATION_RATE), euler_rates)
    angle_acceleration = carry.rate("angle_rate", angle_rate, dt)
    zero = np.zeros_like(pitch)
    attitude = angle + np.stack([tilt[..., 0, :], pitch, zero], axis=-2)
    tilt_rates = np.stack([tilt_rate[..., 0, :], tilt_rate[..., 1, :], zero], axis=-2)
    tilt_accelerations = np.stack([tilt_acceleration[..., 0, :], tilt_acceleration[..., 1, :], zero], axis=-2)
    attitude_rate = angle_rate + tilt_rates
    attitude_acceleration = angle_acceleration + tilt_accelerations
    if np.any(np.asarray(wd.head_height_m) != 0.0):
        # At the head: the platform origin must also cancel the head's swing about it.
        force = force - lever_arm_acceleration(
            body_rates(attitude, attitude_rate),
            body_angular_acceleration(attitude, attitude_rate, attitude_acceleration),
            wd.head_height_m,
        )

    # Translational channel: gravity removed in the inertial frame, Formula 12, integrated twice.
    standing = np.array([[0.0], [0.0], [GRAVITY_M_S2]])
    inertial = rotate(attitude, force + standing) - standing
    squared = carry.filter("squared", wd.sections(HIGHPASS_SQUARED), inertial)
    velocity = carry.filter("velocity", wd.sections(LAG), squared)
    acceleration = squared - wd.first_order_break_rad_s * velocity  # exact under Tustin too
    position = carry.filter("position", wd.sections(POSITION, LAG), inertial)

    return WashoutSignals(
        pose=np.concatenate([position, attitude], axis=-2),
        velocity=np.concatenate([velocity, attitude_rate], axis=-2),
        acceleration=np.concatenate([acceleration, attitude_acceleration], axis=-2),
        tilt_command=tilt_command,
        tilt=tilt,
        input_limited=force_limited | rates_limited,
    )


def _as_signal(name: str, value: np.ndarray) -> np.ndarray:
    array = np.asarray(value, dtype=float)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name}: shape {array.shape}, expected (N, 3)")
    require_finite(name, array)
    return array


def washout_batch(
    params: WashoutParameters,
    sample_period_s: float,
    specific_force_m_s2: np.ndarray,
    angular_velocity_rad_s: np.ndarray,
) -> WashoutTrajectory:
    """The washout over whole signals (N, 3) each, from rest; vectorised (see the module docstring)."""
    force = _as_signal("specific_force_m_s2", specific_force_m_s2)
    rates = _as_signal("angular_velocity_rad_s", angular_velocity_rad_s)
    if len(force) != len(rates):
        raise ValueError(f"angular_velocity_rad_s: {len(rates)} samples, specific_force_m_s2 has {len(force)}")
    wd = design(params, sample_period_s)
    count = len(force)
    # Time-last storage so that each chunk's rows are contiguous copies; the trajectory holds (N, 6) views.
    pose, velocity, acceleration = np.empty((6, count)), np.empty((6, count)), np.empty((6, count))
    input_limited, tilt_rate_limited = np.empty(count, dtype=bool), np.empty(count, dtype=bool)
    carry = WashoutCarry()
    # Chunks keep every temporary in cache; the state carried between them makes the result independent
    # of the chunk size. The loop is over chunks, each chunk is vectorised.
    for start in range(0, count, BATCH_CHUNK_SAMPLES):
        chunk = slice(start, start + BATCH_CHUNK_SAMPLES)
        signals = run_washout(wd, force[chunk].T, rates[chunk].T, carry)
        pose[:, chunk], velocity[:, chunk], acceleration[:, chunk] = (
            signals.pose,
            signals.velocity,
            signals.acceleration,
        )
        input_limited[chunk] = signals.input_limited
        tilt_rate_limited[chunk] = np.any(signals.tilt != signals.tilt_command, axis=0)
    return WashoutTrajectory(
        sample_period_s=float(sample_period_s),
        pose=pose.T,
        velocity=velocity.T,
        acceleration=acceleration.T,
        input_limited=input_limited,
        tilt_rate_limited=tilt_rate_limited,
    )
