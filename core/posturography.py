"""Posturography metrics for one trial (issue 8; REFERENCE.md §5).

COP sway measures after Prieto et al. (1996), IEEE Trans Biomed Eng 43:956, on the COP referred to its
mean (definitions in docs/posturography.md): total excursions (path length), mean velocity (resultant, AP,
ML: excursions over the trial time), mean and RMS distance, AP/ML range, Prieto's 95 % confidence circle
and ellipse areas, sway area per second and mean frequency. Beside them the product's own 95 % ellipse,
π·χ²₀.₉₅(2)·√(λ₁λ₂) = π·5.991·√(λ₁λ₂) from the eigenvalues of the sample covariance: the *prediction*
ellipse (expected to hold 95 % of the COP samples), not the confidence ellipse of the mean COP (Schubert &
Kirchner 2014, Gait Posture 39:518); for a long trial Prieto's "confidence" ellipse is the same ellipse
(2·F₀.₉₅(2, ∞) = χ²₀.₉₅(2)).

Sensory Organization Test (NeuroCom): equilibrium score ES = 100·(12.5° − (θmax − θmin))/12.5° on the AP
sway angle of the centre of gravity (12.5° is the AP limit of stability, 8.5° forward + 4° back); a fall
scores 0. Composite = (C1 + C2 + 3·C3 + 3·C4 + 3·C5 + 3·C6)/14 with Ci the mean score of condition i;
ratios SOM = C2/C1, VIS = C4/C1, VEST = C5/C1, PREF = (C3 + C6)/(C2 + C5).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from core.patient import ParameterError, require_in_range
from core.sampling import on_uniform_grid

CHI2_2DOF_95 = 5.991  # χ² quantile, 2 degrees of freedom, p = 0.95
Z_95_ONE_SIDED = 1.645  # Prieto's z.05 for the 95 % confidence circle
SWAY_LIMIT_RAD = math.radians(12.5)
NEUROCOM_COG_HEIGHT_FRACTION = 0.5527  # COG height above the ankle used by NeuroCom, fraction of height
SOT_CONDITIONS = (1, 2, 3, 4, 5, 6)
# Path length and velocity measure noise as much as sway on raw 1 kHz plate COP: 1 mm of white sensor noise
# alone adds about 1 m/s. Prieto et al. (1996) low-pass filtered the COP at 5 Hz (4th-order Butterworth,
# zero phase) before computing their measures; `filtered_sway_metrics` does the same.
COP_LOWPASS_CUTOFF_HZ = 5.0
COP_LOWPASS_ORDER = 4


@dataclass(frozen=True)
class SwayMetrics:
    """Prieto (1996) sway measures of one COP trace; metres and seconds."""

    duration_s: float
    path_length_m: float  # total excursions
    mean_velocity_m_s: float
    mean_velocity_ap_m_s: float
    mean_velocity_ml_m_s: float
    mean_distance_m: float
    rms_distance_m: float
    rms_ap_m: float
    rms_ml_m: float
    range_ap_m: float
    range_ml_m: float
    ellipse_area_95_m2: float  # prediction ellipse
    confidence_circle_area_95_m2: float
    confidence_ellipse_area_95_m2: float
    sway_area_per_second_m2_s: float
    mean_frequency_hz: float

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


def _as_trace(time_s: np.ndarray, cop_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    time_s = np.asarray(time_s, dtype=float)
    cop_m = np.asarray(cop_m, dtype=float)
    if cop_m.ndim != 2 or cop_m.shape[1] != 2 or cop_m.shape[0] < 3:
        raise ParameterError("cop_m", cop_m.shape, "shape must be (N, 2) as (AP x, ML y) with N >= 3")
    if time_s.shape != (cop_m.shape[0],):
        raise ParameterError("time_s", time_s.shape, f"shape must be ({cop_m.shape[0]},) like cop_m")
    if not (np.all(np.isfinite(cop_m)) and np.all(np.isfinite(time_s))):
        raise ParameterError("cop_m/time_s", "non-finite", "every value must be finite")
    if not np.all(np.diff(time_s) > 0):
        raise ParameterError("time_s", "not increasing", "sample times must increase strictly")
    return time_s, cop_m


def sway_metrics(time_s: np.ndarray, cop_m: np.ndarray) -> SwayMetrics:
    """Sway measures of a COP trace (N, 2) in (AP, ML), over T = the trace's duration. Prieto's moments use
    1/N; the prediction ellipse uses the sample covariance (N − 1)."""
    from scipy.stats import f as f_distribution

    time_s, cop_m = _as_trace(time_s, cop_m)
    count = len(time_s)
    duration_s = float(time_s[-1] - time_s[0])
    steps = np.diff(cop_m, axis=0)
    path_length_m = float(np.sum(np.linalg.norm(steps, axis=1)))
    centred = cop_m - cop_m.mean(axis=0)
    distance = np.linalg.norm(centred, axis=1)
    mean_distance_m = float(np.mean(distance))
    rms_distance_m = float(np.sqrt(np.mean(distance**2)))
    eigenvalues = np.linalg.eigvalsh(np.cov(centred, rowvar=False))
    ap, ml = centred[:, 0], centred[:, 1]
    distance_sd = math.sqrt(max(rms_distance_m**2 - mean_distance_m**2, 0.0))
    moment_determinant = max(np.mean(ap**2) * np.mean(ml**2) - np.mean(ap * ml) ** 2, 0.0)
    f_95 = float(f_distribution.ppf(0.95, 2, count - 2))
    mean_velocity_m_s = path_length_m / duration_s
    return SwayMetrics(
        duration_s=duration_s,
        path_length_m=path_length_m,
        mean_velocity_m_s=mean_velocity_m_s,
        mean_velocity_ap_m_s=float(np.sum(np.abs(steps[:, 0]))) / duration_s,
        mean_velocity_ml_m_s=float(np.sum(np.abs(steps[:, 1]))) / duration_s,
        mean_distance_m=mean_distance_m,
        rms_distance_m=rms_distance_m,
        rms_ap_m=float(np.sqrt(np.mean(ap**2))),
        rms_ml_m=float(np.sqrt(np.mean(ml**2))),
        range_ap_m=float(np.ptp(cop_m[:, 0])),
        range_ml_m=float(np.ptp(cop_m[:, 1])),
        ellipse_area_95_m2=float(math.pi * CHI2_2DOF_95 * math.sqrt(max(eigenvalues[0], 0.0) * eigenvalues[1])),
        confidence_circle_area_95_m2=math.pi * (mean_distance_m + Z_95_ONE_SIDED * distance_sd) ** 2,
        confidence_ellipse_area_95_m2=2.0 * math.pi * f_95 * math.sqrt(moment_determinant),
        sway_area_per_second_m2_s=float(np.sum(np.abs(ap[1:] * ml[:-1] - ap[:-1] * ml[1:]))) / (2.0 * duration_s),
        mean_frequency_hz=mean_velocity_m_s / (2.0 * math.pi * mean_distance_m) if mean_distance_m > 0 else 0.0,
    )


def lowpass_cop(
    time_s: np.ndarray, cop_m: np.ndarray, cutoff_hz: float = COP_LOWPASS_CUTOFF_HZ
) -> tuple[np.ndarray, np.ndarray]:
    """The COP resampled onto a uniform grid at the median sample interval (a late tick or a lost sample must
    not bend the filter) and low-pass filtered, zero phase (4th-order Butterworth, scipy's sosfiltfilt)."""
    from scipy.signal import butter, sosfiltfilt

    time_s, cop_m = _as_trace(time_s, cop_m)
    uniform_s, period_s, resampled = on_uniform_grid(time_s, cop_m)
    nyquist_hz = 0.5 / period_s
    require_in_range("cutoff_hz", cutoff_hz, 0.0, nyquist_hz, low_open=True, high_open=True)
    sos = butter(COP_LOWPASS_ORDER, cutoff_hz / nyquist_hz, output="sos")
    if len(uniform_s) <= 3 * (2 * len(sos) + 1):  # too short for filtfilt's padding: nothing to filter
        return uniform_s, resampled
    return uniform_s, sosfiltfilt(sos, resampled, axis=0)


def filtered_sway_metrics(
    time_s: np.ndarray, cop_m: np.ndarray, cutoff_hz: float = COP_LOWPASS_CUTOFF_HZ
) -> SwayMetrics:
    """Prieto's measures on the low-pass-filtered COP (see `lowpass_cop`)."""
    return sway_metrics(*lowpass_cop(time_s, cop_m, cutoff_hz))


def net_cop(plate_force_z_n: np.ndarray, plate_cop_m: np.ndarray, foot_origins_m: np.ndarray) -> np.ndarray:
    """Both feet's COP (N, 2) in one frame: the load-weighted mean of each plate's COP (N, 2, 2) shifted
    by its foot-plate origin (2, 2) (right, left). Samples with no load on either plate are refused."""
    forces = np.asarray(plate_force_z_n, dtype=float)
    cops = np.asarray(plate_cop_m, dtype=float) + np.asarray(foot_origins_m, dtype=float)
    total = forces.sum(axis=1)
    if np.any(total <= 0.0):
        index = int(np.flatnonzero(total <= 0.0)[0])
        raise ParameterError(f"plate_force_z_n[{index}]", forces[index].tolist(), "total load must be > 0")
    return np.einsum("nf,nfk->nk", forces, cops) / total[:, None]


def sway_angle_from_cog(cog_ap_m: np.ndarray, height_m: float) -> np.ndarray:
    """AP sway angle of the COG from its AP offset over the ankles, as NeuroCom does (COG at 0.5527·H)."""
    require_in_range("height_m", height_m, 1.0, 2.3)
    ratio = np.asarray(cog_ap_m, dtype=float) / (NEUROCOM_COG_HEIGHT_FRACTION * height_m)
    if np.any(np.abs(ratio) > 1.0):
        raise ParameterError("cog_ap_m", float(np.max(np.abs(cog_ap_m))), "must be smaller than the COG height")
    return np.arcsin(ratio)


def equilibrium_score(sway_angle_rad: np.ndarray, *, fell: bool = False) -> float:
    """ES = 100·(12.5° − (θmax − θmin))/12.5° over the trial's AP sway angles; 0 for a fall.

    A sway range of 12.5° or more spans the whole AP limit of stability, which NeuroCom scores as a
    fall, so the score never goes below 0."""
    angles = np.asarray(sway_angle_rad, dtype=float)
    if angles.ndim != 1 or angles.size < 1 or not np.all(np.isfinite(angles)):
        raise ParameterError("sway_angle_rad", angles.shape, "a non-empty 1-D array of finite angles")
    if fell:
        return 0.0
    sway_range = float(np.ptp(angles))
    return max(0.0, 100.0 * (SWAY_LIMIT_RAD - sway_range) / SWAY_LIMIT_RAD)


def _condition_means(scores: Mapping[int, float | Sequence[float]]) -> dict[int, float]:
    means = {}
    for condition in SOT_CONDITIONS:
        if condition not in scores:
            raise ParameterError(f"scores[{condition}]", None, "every SOT condition 1–6 needs a score")
        trials = np.atleast_1d(np.asarray(scores[condition], dtype=float))
        if trials.size == 0 or np.any(~np.isfinite(trials)) or np.any((trials < 0) | (trials > 100)):
            raise ParameterError(f"scores[{condition}]", trials.tolist(), "scores must lie in [0, 100]")
        means[condition] = float(trials.mean())
    return means


def sot_composite(scores: Mapping[int, float | Sequence[float]]) -> float:
    """Composite equilibrium score from each condition's trial scores (or their mean)."""
    c = _condition_means(scores)
    return (c[1] + c[2] + 3 * c[3] + 3 * c[4] + 3 * c[5] + 3 * c[6]) / 14.0


def _ratio(numerator: float, denominator: float) -> float:
    return numerator / denominator if denominator > 0 else math.nan  # undefined when the reference fell


def sensory_ratios(scores: Mapping[int, float | Sequence[float]]) -> dict[str, float]:
    """SOM, VIS, VEST and PREF; NaN where the reference condition scored 0 (every trial a fall)."""
    c = _condition_means(scores)
    return {
        "somatosensory": _ratio(c[2], c[1]),
        "visual": _ratio(c[4], c[1]),
        "vestibular": _ratio(c[5], c[1]),
        "preference": _ratio(c[3] + c[6], c[2] + c[5]),
    }
