"""Motion-fidelity metrics of a washout run (paper §4.2, Formulas 16–19).

Perception errors are platform-perceived minus commanded-perceived, each through the vestibular
models (Formulas 14–15). They are judged at the patient's head (`core.perception`, issue 14 §2): the
specific force there is Rᵀ·(a + g e_z) − g e_z plus the lever-arm terms ω̇ × r + ω × (ω × r) of the
platform's rotation, so both the gravity component the tilt adds and the head's swing during a tilt
onset count; the angular velocity is the body rate of the Euler-angle trajectory. `head_height_m = 0`
gives the paper's rotation-centre metrics. Platform motion is displacement and angular velocity.

Each quantity is reported per axis as RMS and peak. The paper normalises its two objectives because
their magnitudes differ (§4.2, ref. [16]) without saying how; here every RMS is divided by a scale
with the same unit, so the objectives are sums of dimensionless numbers:
- perception errors by the perception thresholds (Reid & Nahon), i.e. in "thresholds";
- displacement by `FidelityScales.displacement_m` (0.1 m: the travel budget of one cue);
- platform angular velocity by the angular-velocity perception thresholds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.perception import DEFAULT_HEAD_HEIGHT_M, STANDING, head_specific_force
from core.shaping import require_positive
from core.vestibular import VestibularModel
from core.washout import WashoutTrajectory, body_rates, rotate

OBJECTIVE_NAMES = ("perception_error", "platform_motion")


@dataclass(frozen=True)
class FidelityScales:
    displacement_m: float = 0.1

    def __post_init__(self) -> None:
        require_positive("displacement_m", self.displacement_m)


@dataclass(frozen=True)
class FidelityMetrics:
    """Per-axis RMS and peak (..., 3), and the two normalised objectives (...)."""

    specific_force_error_rms_m_s2: np.ndarray
    specific_force_error_peak_m_s2: np.ndarray
    angular_velocity_error_rms_rad_s: np.ndarray
    angular_velocity_error_peak_rad_s: np.ndarray
    displacement_rms_m: np.ndarray
    displacement_peak_m: np.ndarray
    angular_velocity_rms_rad_s: np.ndarray
    angular_velocity_peak_rad_s: np.ndarray
    perception_error: np.ndarray  # Σ RMS(perceived-force error)/threshold + Σ RMS(perceived-rate error)/threshold
    platform_motion: np.ndarray  # Σ RMS(displacement)/displacement_m + Σ RMS(angular velocity)/threshold

    def objectives(self) -> dict[str, float]:
        return {name: float(getattr(self, name)) for name in OBJECTIVE_NAMES}

    def to_dict(self) -> dict[str, object]:
        return {name: np.asarray(value).tolist() for name, value in vars(self).items()}


def platform_specific_force(pose: np.ndarray, acceleration: np.ndarray) -> np.ndarray:
    """Specific force at the rotation centre (no lever arm), relative to standing: (..., 3, N) time last."""
    return rotate(pose[..., 3:, :], acceleration[..., :3, :] + STANDING, inverse=True) - STANDING


def platform_angular_velocity(pose: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """Body angular velocity of the platform (..., 3, N) from its Euler angles and rates."""
    return body_rates(pose[..., 3:, :], velocity[..., 3:, :])


def _rms(signal: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(signal * signal, axis=-1))


def _peak(signal: np.ndarray) -> np.ndarray:
    return np.max(np.abs(signal), axis=-1)


def fidelity_of_signals(
    pose: np.ndarray,
    velocity: np.ndarray,
    acceleration: np.ndarray,
    specific_force: np.ndarray,
    angular_velocity: np.ndarray,
    vestibular: VestibularModel,
    scales: FidelityScales,
    head_height_m: float = DEFAULT_HEAD_HEIGHT_M,
) -> FidelityMetrics:
    """Metrics from time-last arrays: platform (..., 6, N), commands (..., 3, N); broadcasts over populations."""
    # The vestibular models are linear: perceived(platform) − perceived(command) = perceived(difference).
    delivered = head_specific_force(pose, velocity, acceleration, head_height_m)
    force_error = vestibular.perceive_specific_force_axes(delivered - specific_force)
    platform_rates = platform_angular_velocity(pose, velocity)
    rate_error = vestibular.perceive_angular_velocity_axes(platform_rates - angular_velocity)
    force_thresholds = vestibular.specific_force_thresholds_m_s2
    rate_thresholds = vestibular.angular_velocity_thresholds_rad_s
    force_error_rms, rate_error_rms = _rms(force_error), _rms(rate_error)
    displacement_rms, rates_rms = _rms(pose[..., :3, :]), _rms(platform_rates)
    return FidelityMetrics(
        specific_force_error_rms_m_s2=force_error_rms,
        specific_force_error_peak_m_s2=_peak(force_error),
        angular_velocity_error_rms_rad_s=rate_error_rms,
        angular_velocity_error_peak_rad_s=_peak(rate_error),
        displacement_rms_m=displacement_rms,
        displacement_peak_m=_peak(pose[..., :3, :]),
        angular_velocity_rms_rad_s=rates_rms,
        angular_velocity_peak_rad_s=_peak(platform_rates),
        perception_error=np.sum(force_error_rms / force_thresholds, axis=-1)
        + np.sum(rate_error_rms / rate_thresholds, axis=-1),
        platform_motion=np.sum(displacement_rms / scales.displacement_m, axis=-1)
        + np.sum(rates_rms / rate_thresholds, axis=-1),
    )


def fidelity(
    trajectory: WashoutTrajectory,
    specific_force_m_s2: np.ndarray,
    angular_velocity_rad_s: np.ndarray,
    vestibular: VestibularModel | None = None,
    scales: FidelityScales | None = None,
    head_height_m: float = DEFAULT_HEAD_HEIGHT_M,
) -> FidelityMetrics:
    """Metrics of one washout run against the commanded cue (N, 3) each, perceived at the head."""
    vestibular = vestibular or VestibularModel(sample_period_s=trajectory.sample_period_s)
    if abs(vestibular.sample_period_s - trajectory.sample_period_s) > 1e-12:
        raise ValueError(
            f"vestibular.sample_period_s = {vestibular.sample_period_s}: must equal the trajectory's "
            f"{trajectory.sample_period_s}"
        )
    return fidelity_of_signals(
        trajectory.pose.T,
        trajectory.velocity.T,
        trajectory.acceleration.T,
        np.asarray(specific_force_m_s2, dtype=float).T,
        np.asarray(angular_velocity_rad_s, dtype=float).T,
        vestibular,
        scales or FidelityScales(),
        head_height_m,
    )
