"""Bounded-jerk transitions in stance-pose space: soft start, stop to standstill, return to neutral.

All are polynomials in time, so position, velocity, acceleration and jerk are continuous inside a
transition and bounded. A transition starts from the current pose, velocity and acceleration, so
acceleration never jumps at its start (no jerk impulse).

- `to_standstill`: velocity goes from v0 (with slope a0) to 0 with zero final acceleration in T: a
  cubic Hermite in velocity, a quartic in position. Used by the emergency stop (IEC 60204-1 category 1:
  a controlled stop, then power removed) and by every controlled stop.
- `to_pose`: the quintic from (p0, v0, a0) to (p1, 0, 0) in T. Used to return to neutral.
- `smoothstep5`: the quintic 0 → 1 with zero slope and curvature at both ends: the soft-start gain.
"""

from __future__ import annotations

import math

import numpy as np

_ORDER = 6  # coefficients c0..c5


def start_velocity(
    velocity: np.ndarray, acceleration: np.ndarray, sample_period_s: float, out: np.ndarray
) -> np.ndarray:
    """The velocity at the latest sample from backward differences: (p_k − p_k−1)/T is the velocity half a
    period earlier, so add a·T/2. Starting a ramp from it keeps the third difference of the commanded
    poses (the jerk) continuous across the switch."""
    np.multiply(acceleration, 0.5 * sample_period_s, out=out)
    out += velocity
    return out


def smoothstep5(fraction: float) -> float:
    """10x³ − 15x⁴ + 6x⁵ on [0, 1], clamped outside: zero first and second derivative at both ends."""
    x = min(max(fraction, 0.0), 1.0)
    return x * x * x * (10.0 + x * (-15.0 + 6.0 * x))


class PoseRamp:
    """p(t) = Σ c_k t^k per axis for t in [0, duration]; holds the end state after it."""

    def __init__(self, axes: int = 6) -> None:
        self.coefficients = np.zeros((_ORDER, axes))
        self._velocity_coefficients = np.zeros((_ORDER - 1, axes))  # k·c_k for k = 1..5
        self._acceleration_coefficients = np.zeros((_ORDER - 2, axes))  # k·(k−1)·c_k for k = 2..5
        self.duration_s = 0.0
        self.position = np.zeros(axes)
        self.velocity = np.zeros(axes)
        self.acceleration = np.zeros(axes)

    def to_standstill(self, p0: np.ndarray, v0: np.ndarray, a0: np.ndarray, duration_s: float) -> None:
        """Stop from (p0, v0, a0) within `duration_s`; the stopping point follows from the motion."""
        t = duration_s
        c = self.coefficients
        c[0], c[1], c[2] = p0, v0, 0.5 * a0
        c[3] = -(2.0 * a0 * t + 3.0 * v0) / (3.0 * t * t)
        c[4] = (v0 + 0.5 * a0 * t) / (2.0 * t**3)
        c[5] = 0.0
        self._set_duration(t)

    def to_pose(self, p0: np.ndarray, v0: np.ndarray, a0: np.ndarray, p1: np.ndarray, duration_s: float) -> None:
        """Quintic from (p0, v0, a0) to (p1, 0, 0) in `duration_s`."""
        t = duration_s
        c = self.coefficients
        c[0], c[1], c[2] = p0, v0, 0.5 * a0
        h = p1 - p0
        c[3] = (20.0 * h - (12.0 * v0 + 3.0 * a0 * t) * t) / (2.0 * t**3)
        c[4] = (-30.0 * h + (16.0 * v0 + 3.0 * a0 * t) * t) / (2.0 * t**4)
        c[5] = (12.0 * h - (6.0 * v0 + a0 * t) * t) / (2.0 * t**5)
        self._set_duration(t)

    def hold(self, p0: np.ndarray) -> None:
        """Stay at `p0`."""
        self.coefficients[:] = 0.0
        self.coefficients[0] = p0
        self._set_duration(0.0)

    def _set_duration(self, duration_s: float) -> None:
        self.duration_s = duration_s
        orders = np.arange(_ORDER)[:, None]
        self._velocity_coefficients[:] = (orders * self.coefficients)[1:]
        self._acceleration_coefficients[:] = (orders * (orders - 1) * self.coefficients)[2:]

    def evaluate(self, time_s: float) -> bool:
        """Fill position, velocity, acceleration at `time_s`; True once the ramp is over."""
        t = min(max(time_s, 0.0), self.duration_s)
        _horner(self.coefficients, t, self.position)
        _horner(self._velocity_coefficients, t, self.velocity)
        _horner(self._acceleration_coefficients, t, self.acceleration)
        return time_s >= self.duration_s

    def peak_jerk(self) -> np.ndarray:
        """max |d³p/dt³| over the ramp per axis (jerk is a quadratic in t: check ends and vertex)."""
        c = self.coefficients
        t = np.linspace(0.0, self.duration_s, 257)[:, None]
        jerk = 6.0 * c[3] + 24.0 * c[4] * t + 60.0 * c[5] * t * t
        return np.max(np.abs(jerk), axis=0)


def _horner(coefficients: np.ndarray, t: float, out: np.ndarray) -> None:
    """out = Σ coefficients[k] · t^k, in place (Horner's rule, no temporaries)."""
    out[:] = coefficients[-1]
    for k in range(len(coefficients) - 2, -1, -1):
        out *= t
        out += coefficients[k]


def cue_gain(time_s: float, duration_s: float, soft_start_s: float, fade_out_s: float) -> float:
    """Soft start and fade out of a segment's cue: quintic 0 → 1 over `soft_start_s`, 1 until
    `duration_s`, quintic 1 → 0 over the following `fade_out_s`."""
    rising = smoothstep5(time_s / soft_start_s)
    falling = smoothstep5((duration_s + fade_out_s - time_s) / fade_out_s)
    return rising if rising < falling else falling


def cue_gains(times_s: np.ndarray, duration_s: float, soft_start_s: float, fade_out_s: float) -> np.ndarray:
    """`cue_gain` for many times, with the same arithmetic (so the same numbers)."""
    rising = np.clip(times_s / soft_start_s, 0.0, 1.0)
    falling = np.clip((duration_s + fade_out_s - times_s) / fade_out_s, 0.0, 1.0)
    rising = rising * rising * rising * (10.0 + rising * (-15.0 + 6.0 * rising))
    falling = falling * falling * falling * (10.0 + falling * (-15.0 + 6.0 * falling))
    return np.minimum(rising, falling)


def return_duration_s(
    position: np.ndarray,
    velocity: np.ndarray,
    *,
    minimum_s: float,
    speed_m_s: float,
    rate_rad_s: float,
    acceleration_m_s2: float,
    angular_acceleration_rad_s2: float,
) -> float:
    """How long a quintic return from (position, velocity) to neutral takes so that its peak speed and
    acceleration stay near the given bounds: a rest-to-rest quintic over distance d in T peaks at
    1.875·d/T in speed and 5.77·d/T² in acceleration; absorbing a start velocity v takes ~3·v/a."""
    linear = float(np.max(np.abs(position[:3])))
    angular = float(np.max(np.abs(position[3:])))
    linear_speed = float(np.max(np.abs(velocity[:3])))
    angular_speed = float(np.max(np.abs(velocity[3:])))
    return max(
        minimum_s,
        1.875 * linear / speed_m_s,
        1.875 * angular / rate_rad_s,
        math.sqrt(5.774 * linear / acceleration_m_s2),
        math.sqrt(5.774 * angular / angular_acceleration_rad_s2),
        3.0 * linear_speed / acceleration_m_s2,
        3.0 * angular_speed / angular_acceleration_rad_s2,
    )
