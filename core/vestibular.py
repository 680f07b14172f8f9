"""Vestibular perception models (paper §4.2, Formulas 14–15, Tables 2–3; REFERENCE.md §4).

Otolith (specific force → perceived specific force):   G_oto(s) = K(τ_a s + 1)/((τ_L s + 1)(τ_s s + 1)).
Semicircular canal (angular velocity → perceived):     G_scc(s) = T_L T_a s²/((T_L s + 1)(T_s s + 1)(T_a s + 1)).

The paper's Table 3 labels the canal constants Ta = 6.1, Tl = 0.1, Ts = 30; against Formula 15 the
labels are shuffled: T_L = 6.1 s (roll; 5.3 s pitch, 10.2 s yaw in the literature), T_s = 0.1 s and
the adaptation constant T_a = 30 s. Each axis is built as a continuous python-control transfer
function and discretised (Tustin) at construction. Perception thresholds default to Reid & Nahon
(1985) as quoted by secondary sources, so they are configuration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any

import numpy as np

from core.shaping import ParameterError, filter_sections, require_finite, require_positive, require_sample_period

if TYPE_CHECKING:
    import control

AXES = ("x", "y", "z")
ROTATION_AXES = ("roll", "pitch", "yaw")


@dataclass(frozen=True)
class OtolithParameters:
    """Formula 14, Table 2."""

    gain: float = 0.4  # K
    lead_time_constant_s: float = 13.2  # τ_a
    long_time_constant_s: float = 5.33  # τ_L
    short_time_constant_s: float = 0.66  # τ_s


@dataclass(frozen=True)
class CanalParameters:
    """Formula 15, Table 3 with its labels put back in the formula's order."""

    long_time_constant_s: float = 6.1  # T_L
    short_time_constant_s: float = 0.1  # T_s
    adaptation_time_constant_s: float = 30.0  # T_a


@dataclass(frozen=True)
class PerceptionThresholds:
    """Reid & Nahon (1985): 0.17 m/s² surge/sway, 0.28 m/s² heave; 3.0, 3.6, 2.6 °/s roll, pitch, yaw."""

    specific_force_m_s2: tuple[float, float, float] = (0.17, 0.17, 0.28)
    angular_velocity_rad_s: tuple[float, float, float] = (math.radians(3.0), math.radians(3.6), math.radians(2.6))


def _default_canals() -> tuple[CanalParameters, CanalParameters, CanalParameters]:
    return (
        CanalParameters(long_time_constant_s=6.1),
        CanalParameters(long_time_constant_s=5.3),
        CanalParameters(long_time_constant_s=10.2),
    )


@dataclass(frozen=True)
class VestibularParameters:
    """One otolith and one canal model per axis (x, y, z / roll, pitch, yaw) and the thresholds."""

    otoliths: tuple[OtolithParameters, OtolithParameters, OtolithParameters] = (
        OtolithParameters(),
        OtolithParameters(),
        OtolithParameters(),
    )
    canals: tuple[CanalParameters, CanalParameters, CanalParameters] = field(default_factory=_default_canals)
    thresholds: PerceptionThresholds = field(default_factory=PerceptionThresholds)

    def __post_init__(self) -> None:
        if len(self.otoliths) != 3 or len(self.canals) != 3:
            raise ParameterError("otoliths/canals", (len(self.otoliths), len(self.canals)), "one per axis (3 each)")
        for axis, otolith in zip(AXES, self.otoliths, strict=True):
            for item in fields(otolith):
                require_positive(f"otoliths.{axis}.{item.name}", getattr(otolith, item.name))
        for axis, canal in zip(ROTATION_AXES, self.canals, strict=True):
            for item in fields(canal):
                require_positive(f"canals.{axis}.{item.name}", getattr(canal, item.name))
        for name in ("specific_force_m_s2", "angular_velocity_rad_s"):
            values = getattr(self.thresholds, name)
            if len(values) != 3:
                raise ParameterError(f"thresholds.{name}", values, "three values (one per axis)")
            require_positive(f"thresholds.{name}", values)

    def to_dict(self) -> dict[str, Any]:
        return {
            "otoliths": [vars(o).copy() for o in self.otoliths],
            "canals": [vars(c).copy() for c in self.canals],
            "thresholds": {
                "specific_force_m_s2": list(self.thresholds.specific_force_m_s2),
                "angular_velocity_rad_s": list(self.thresholds.angular_velocity_rad_s),
            },
        }


def otolith_transfer_function(params: OtolithParameters) -> control.TransferFunction:
    """Formula 14 as a continuous transfer function."""
    import control  # here: python-control loads matplotlib and scipy.signal (1.3 s of CPU in each process)

    numerator = [params.gain * params.lead_time_constant_s, params.gain]
    denominator = np.polymul([params.long_time_constant_s, 1.0], [params.short_time_constant_s, 1.0])
    return control.tf(numerator, denominator)


def canal_transfer_function(params: CanalParameters) -> control.TransferFunction:
    """Formula 15 as a continuous transfer function (T_s multiplies s: the `1/Tl*Ts` bug is Ts/Tl)."""
    import control

    long_s, short_s, adaptation_s = (
        params.long_time_constant_s,
        params.short_time_constant_s,
        params.adaptation_time_constant_s,
    )
    denominator = np.polymul(np.polymul([long_s, 1.0], [short_s, 1.0]), [adaptation_s, 1.0])
    return control.tf([long_s * adaptation_s, 0.0, 0.0], denominator)


def _discrete_sections(system: control.TransferFunction, sample_period_s: float) -> np.ndarray:
    import control
    import scipy.signal

    discrete = control.sample_system(system, sample_period_s, method="tustin")
    numerator = np.asarray(discrete.num[0][0], dtype=float)
    denominator = np.asarray(discrete.den[0][0], dtype=float)
    return np.asarray(scipy.signal.tf2sos(numerator, denominator), dtype=float)


class VestibularModel:
    """Both organs for all three axes at one sample period; perceives whole signals (N, 3)."""

    def __init__(self, params: VestibularParameters | None = None, sample_period_s: float = 0.001) -> None:
        require_sample_period(sample_period_s)
        self.params = params or VestibularParameters()
        self.sample_period_s = float(sample_period_s)
        self.otolith_systems = [otolith_transfer_function(p) for p in self.params.otoliths]
        self.canal_systems = [canal_transfer_function(p) for p in self.params.canals]
        self.otolith_sos = [_discrete_sections(s, sample_period_s) for s in self.otolith_systems]
        self.canal_sos = [_discrete_sections(s, sample_period_s) for s in self.canal_systems]

    @property
    def specific_force_thresholds_m_s2(self) -> np.ndarray:
        return np.asarray(self.params.thresholds.specific_force_m_s2, dtype=float)

    @property
    def angular_velocity_thresholds_rad_s(self) -> np.ndarray:
        return np.asarray(self.params.thresholds.angular_velocity_rad_s, dtype=float)

    def perceive_specific_force_axes(self, signals: np.ndarray) -> np.ndarray:
        """Perceived specific force for signals (..., 3, N), time last."""
        return _perceive(self.otolith_sos, signals)

    def perceive_angular_velocity_axes(self, signals: np.ndarray) -> np.ndarray:
        """Perceived angular velocity for signals (..., 3, N), time last."""
        return _perceive(self.canal_sos, signals)

    def perceive_specific_force(self, specific_force_m_s2: np.ndarray) -> np.ndarray:
        """(N, 3) m/s² → perceived (N, 3)."""
        return self.perceive_specific_force_axes(_time_last(specific_force_m_s2, "specific_force_m_s2")).T

    def perceive_angular_velocity(self, angular_velocity_rad_s: np.ndarray) -> np.ndarray:
        """(N, 3) rad/s → perceived (N, 3)."""
        return self.perceive_angular_velocity_axes(_time_last(angular_velocity_rad_s, "angular_velocity_rad_s")).T


def _time_last(signal: np.ndarray, name: str) -> np.ndarray:
    signal = np.asarray(signal, dtype=float)
    if signal.ndim != 2 or signal.shape[1] != 3:
        raise ValueError(f"{name}: shape {signal.shape}, expected (N, 3)")
    require_finite(name, signal)
    return signal.T


def _perceive(sections: list[np.ndarray], signals: np.ndarray) -> np.ndarray:
    signals = np.asarray(signals, dtype=float)
    return np.stack([filter_sections(sections[axis], signals[..., axis, :]) for axis in range(3)], axis=-2)
