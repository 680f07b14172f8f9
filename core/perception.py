"""What the patient's vestibular organs receive: specific force and angular velocity at the head
(issue 14 §2, REFERENCE.md §7), and whether the platform's tilt rate stays below perception.

The head sits at r = (0, 0, h) in the foot-plate (stance) frame, h above the plates. For a stance pose
p = (x, y, z, roll, pitch, yaw), R = Rx·Ry·Rz, body angular velocity ω_b and its derivative ω̇_b:

    a_head = p̈ + R (ω̇_b × r + ω_b × (ω_b × r))            (inertial frame)
    f_head = Rᵀ (p̈ + g e_z) + ω̇_b × r + ω_b × (ω_b × r) − g e_z      (head axes, relative to standing)

(the inertial angular acceleration is R ω̇_b, because Ṙ ω_b = R [ω_b]× ω_b = 0). The angular velocity
felt is ω_b. With h = 0 this is the rotation-centre formula the paper uses. A tilt onset of 0.6 rad/s²
with h = 1.6 m moves the head by ~1 m/s² against the cue: that is why perception is judged here.

The head height comes from the patient's stature (ear level, `HEAD_HEIGHT_FRACTION` of it) or a default.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.physics import GRAVITY_M_S2
from core.shaping import ParameterError, require_finite
from core.vestibular import ROTATION_AXES, PerceptionThresholds
from core.washout import body_angular_acceleration, body_rates, lever_arm_acceleration, rotate

DEFAULT_HEAD_HEIGHT_M = 1.6  # REFERENCE.md §7: a head about 1.6 m above the feet
# Ear (vestibular) height as a fraction of stature: eye height is 0.936 H and the ear is within ~2 cm of it
# (Drillis & Contini 1966 segment proportions).
HEAD_HEIGHT_FRACTION = 0.93
HEIGHT_RANGE_M = (0.5, 2.5)
STANDING = np.array([[0.0], [0.0], [GRAVITY_M_S2]])


def head_height_m(body_height_m: float | None) -> float:
    """Height of the vestibular organs above the foot plates for a patient of this stature (None: default)."""
    if body_height_m is None:
        return DEFAULT_HEAD_HEIGHT_M
    low, high = HEIGHT_RANGE_M
    if isinstance(body_height_m, bool) or not math.isfinite(body_height_m) or not low <= body_height_m <= high:
        raise ParameterError("height_m", body_height_m, f"must be a stature in [{low:g}, {high:g}] m")
    return HEAD_HEIGHT_FRACTION * float(body_height_m)


def head_specific_force(
    pose: np.ndarray, velocity: np.ndarray, acceleration: np.ndarray, head_height_m: float
) -> np.ndarray:
    """Specific force at the head, head axes, relative to standing, for stance motion (..., 6, N) time last
    (velocity and acceleration are pose derivatives: Euler-angle rates)."""
    require_finite("head_height_m", head_height_m)
    angles = pose[..., 3:, :]
    centre = rotate(angles, acceleration[..., :3, :] + STANDING, inverse=True) - STANDING
    if head_height_m == 0.0:
        return centre
    rates = body_rates(angles, velocity[..., 3:, :])
    return centre + lever_arm_acceleration(
        rates, body_angular_acceleration(angles, velocity[..., 3:, :], acceleration[..., 3:, :]), head_height_m
    )


def head_angular_velocity(pose: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """Angular velocity felt at the head: the body rate of the rigid stance frame (..., 3, N)."""
    return body_rates(pose[..., 3:, :], velocity[..., 3:, :])


@dataclass(frozen=True)
class TiltRateCheck:
    """The platform's peak roll/pitch rate (body axes) against the canal perception thresholds."""

    peak_rate_rad_s: float  # the larger of roll and pitch, relative to its threshold
    axis: str  # "roll" or "pitch"
    threshold_rad_s: float  # that axis's threshold
    above_threshold: bool
    first_time_s: float | None  # first sample above its axis's threshold

    def to_dict(self) -> dict[str, object]:
        return dict(vars(self))


def tilt_rate_check(
    pose: np.ndarray,
    velocity: np.ndarray,
    sample_period_s: float,
    thresholds: PerceptionThresholds | None = None,
) -> TiltRateCheck:
    """Roll and pitch rates of a stance trajectory (N, 6) against the thresholds (default Reid & Nahon)."""
    limits = np.asarray((thresholds or PerceptionThresholds()).angular_velocity_rad_s[:2], dtype=float)
    rates = np.abs(head_angular_velocity(np.asarray(pose, float).T, np.asarray(velocity, float).T)[:2])
    peaks = rates.max(axis=1) if rates.shape[1] else np.zeros(2)
    axis = int(np.argmax(peaks / limits))
    above = rates > limits[:, None] * (1.0 + 1e-9)
    rows = np.flatnonzero(above.any(axis=0))
    return TiltRateCheck(
        peak_rate_rad_s=float(peaks[axis]),
        axis=ROTATION_AXES[axis],
        threshold_rad_s=float(limits[axis]),
        above_threshold=bool(rows.size),
        first_time_s=float(rows[0] * sample_period_s) if rows.size else None,
    )
