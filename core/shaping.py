"""Discrete filter sections shared by every signal path, and command shaping against resonance.

The paper's modal analysis (§3.3.2, REFERENCE.md §1) puts the first natural frequency at 9.7559 Hz;
platform commands must not excite it. `CommandShaper` low-pass (default) or notch filters every pose
coordinate and refuses a design that attenuates less than `required_attenuation_db` over a band of
±`mode_band_fraction` around that mode (finite-element frequencies are uncertain).

The section primitives here are the one implementation of a second-order section (transposed direct
form II, the structure of `scipy.signal.lfilter`): batch paths run `lfilter` section by section,
populations run a compiled kernel (`section_step`) with one coefficient set per row; both give the same
numbers. Tustin (bilinear) discretisation maps each continuous section on its own, so a cascade
discretised section by section equals the discretised cascade.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, overload

import numba
import numpy as np

from core.errors import InvalidValueError

FIRST_MODE_HZ = 9.7559  # paper §3.3.2, first natural frequency
_FROM_REST: Any = object()  # `filter_sections` without a state argument: start from rest, return the output only


class ParameterError(InvalidValueError):
    """An invalid filter or model parameter; names the field, the value and the limit it broke."""


def require_finite(field_name: str, value: Any) -> None:
    array = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(array)):
        if array.size <= 6:
            raise ParameterError(field_name, array.tolist(), "must be a finite number (no NaN/inf)")
        index = tuple(int(i) for i in np.argwhere(~np.isfinite(array))[0])
        raise ParameterError(f"{field_name}{list(index)}", float(array[index]), "must be a finite number (no NaN/inf)")


def require_positive(field_name: str, value: Any) -> None:
    require_finite(field_name, value)
    if np.any(np.asarray(value, dtype=float) <= 0.0):
        raise ParameterError(field_name, np.asarray(value).tolist(), "must be > 0")


def require_sample_period(sample_period_s: float) -> None:
    require_positive("sample_period_s", sample_period_s)


# --- Tustin discretisation of first- and second-order sections ---------------------------------------


def tustin_second_order(numerator: np.ndarray, denominator: np.ndarray, sample_period_s: float) -> np.ndarray:
    """(b2 s² + b1 s + b0)/(a2 s² + a1 s + a0) as [..., (b2, b1, b0)] → sos rows [..., 6] with a0 = 1.

    Vectorised over leading axes so that a whole population of designs is one call."""
    k = 2.0 / sample_period_s
    num, den = np.asarray(numerator, dtype=float), np.asarray(denominator, dtype=float)

    def mapped(c: np.ndarray) -> np.ndarray:
        s2, s1, s0 = c[..., 0] * k * k, c[..., 1] * k, c[..., 2]
        return np.stack([s2 + s1 + s0, 2.0 * (s0 - s2), s2 - s1 + s0], axis=-1)

    b, a = mapped(num), mapped(den)
    return np.concatenate([b, a], axis=-1) / a[..., :1]


def tustin_first_order(numerator: np.ndarray, denominator: np.ndarray, sample_period_s: float) -> np.ndarray:
    """(b1 s + b0)/(a1 s + a0) → a first-order sos row [b0', b1', 0, 1, a1', 0].

    Mapped on its own rather than as a degenerate second-order section, which would add a cancelling
    pole/zero pair at z = −1 that rounding could leave undamped."""
    k = 2.0 / sample_period_s
    num, den = np.asarray(numerator, dtype=float), np.asarray(denominator, dtype=float)

    def mapped(c: np.ndarray) -> np.ndarray:
        s1, s0 = c[..., 0] * k, c[..., 1]
        return np.stack([s1 + s0, s0 - s1, np.zeros_like(s0)], axis=-1)

    b, a = mapped(num), mapped(den)
    return np.concatenate([b, a], axis=-1) / a[..., :1]


# --- Running sections ---------------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def section_step(sos_row: np.ndarray, state: np.ndarray, value: float) -> float:
    """One sample through one second-order section, transposed direct form II (as scipy's lfilter)."""
    output = state[0] + sos_row[0] * value
    state[0] = state[1] + value * sos_row[1] - output * sos_row[4]
    state[1] = value * sos_row[2] - output * sos_row[5]
    return output


@numba.njit(cache=True, parallel=True)
def _filter_rows(sos: np.ndarray, signals: np.ndarray, rows_per_design: int, out: np.ndarray) -> None:
    """signals (R, N), sos (R // rows_per_design, S, 6): each row filtered from rest by its own design."""
    for row in numba.prange(signals.shape[0]):
        design = sos[row // rows_per_design]
        state = np.zeros((design.shape[0], 2))
        for sample in range(signals.shape[1]):
            value = signals[row, sample]
            for section in range(design.shape[0]):
                value = section_step(design[section], state[section], value)
            out[row, sample] = value


@overload
def filter_sections(sos: np.ndarray, signals: np.ndarray) -> np.ndarray: ...
@overload
def filter_sections(
    sos: np.ndarray, signals: np.ndarray, state: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]: ...
def filter_sections(sos: np.ndarray, signals: np.ndarray, state: Any = _FROM_REST) -> Any:
    """Filter `signals` (..., N) along the last axis.

    `sos` (S, 6) is shared by every row and runs through `scipy.signal.lfilter` section by section;
    given `state` (S, ..., 2) (None = rest), returns (filtered, final state) so that a long signal can be
    filtered chunk by chunk. `sos` (P, S, 6) gives each of the P leading rows of `signals` (P, ..., N)
    its own design, from rest, and runs the compiled kernel over rows in parallel (populations)."""
    import scipy.signal  # here: the processes that only validate a prescription never load it

    sos = np.asarray(sos, dtype=float)
    if sos.ndim == 2:
        filtered = np.asarray(signals, dtype=float)
        initial = np.zeros((len(sos), *filtered.shape[:-1], 2)) if state is None or state is _FROM_REST else state
        final = np.empty_like(initial)
        for index, row in enumerate(sos):
            filtered, final[index] = scipy.signal.lfilter(row[:3], row[3:], filtered, axis=-1, zi=initial[index])
        return filtered if state is _FROM_REST else (filtered, final)
    if state is not _FROM_REST:
        raise ValueError("state: per-row designs always start from rest")
    signals = np.asarray(signals, dtype=float)
    if signals.shape[0] != sos.shape[0]:
        raise ValueError(f"signals: {signals.shape[0]} leading rows for {sos.shape[0]} designs")
    rows = np.ascontiguousarray(np.broadcast_to(signals, signals.shape).reshape(-1, signals.shape[-1]))
    out = np.empty_like(rows)
    _filter_rows(np.ascontiguousarray(sos), rows, rows.shape[0] // sos.shape[0], out)
    return out.reshape(signals.shape)


# --- Command shaping ------------------------------------------------------------------------------------

SHAPING_KINDS = ("lowpass", "notch")


@dataclass(frozen=True)
class ShapingParameters:
    """Filter on every platform pose coordinate. Default: 2nd-order Butterworth low-pass at 2.5 Hz,
    ≥ 21.8 dB down from 8.8 to 10.7 Hz (first mode ± 10 %), 90 ms group delay at low frequency."""

    enabled: bool = True
    kind: str = "lowpass"
    lowpass_cutoff_hz: float = 2.5
    lowpass_order: int = 2
    notch_frequency_hz: float = FIRST_MODE_HZ
    notch_quality: float = 0.4  # centre / −3 dB bandwidth; low Q keeps the notch wide around an uncertain mode
    first_mode_hz: float = FIRST_MODE_HZ
    mode_band_fraction: float = 0.1
    required_attenuation_db: float = 20.0

    def __post_init__(self) -> None:
        if not isinstance(self.enabled, bool):
            raise ParameterError("enabled", self.enabled, "must be true or false")
        if self.kind not in SHAPING_KINDS:
            raise ParameterError("kind", self.kind, f"must be one of {list(SHAPING_KINDS)}")
        for name in ("lowpass_cutoff_hz", "notch_frequency_hz", "notch_quality", "first_mode_hz"):
            require_positive(name, getattr(self, name))
        require_finite("required_attenuation_db", self.required_attenuation_db)
        require_finite("mode_band_fraction", self.mode_band_fraction)
        if not 0.0 <= self.mode_band_fraction < 1.0:
            raise ParameterError("mode_band_fraction", self.mode_band_fraction, "must be in [0, 1)")
        if not isinstance(self.lowpass_order, int) or not 1 <= self.lowpass_order <= 8:
            raise ParameterError("lowpass_order", self.lowpass_order, "must be an integer from 1 to 8")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ShapingParameters:
        unknown = set(data) - set(cls.__dataclass_fields__)
        if unknown:
            name = sorted(unknown)[0]
            raise ParameterError(name, data[name], "unknown shaping parameter")
        return cls(**data)


def shaping_sections(params: ShapingParameters, sample_period_s: float) -> np.ndarray:
    """The shaper's sos (S, 6) at this sample period; refuses a design that leaves the first mode exposed."""
    import scipy.signal

    require_sample_period(sample_period_s)
    nyquist_hz = 0.5 / sample_period_s
    if not params.enabled:
        return np.array([[1.0, 0.0, 0.0, 1.0, 0.0, 0.0]])
    design_hz = params.lowpass_cutoff_hz if params.kind == "lowpass" else params.notch_frequency_hz
    field_name = "lowpass_cutoff_hz" if params.kind == "lowpass" else "notch_frequency_hz"
    if design_hz >= nyquist_hz:
        raise ParameterError(field_name, design_hz, f"must be below the Nyquist frequency {nyquist_hz:g} Hz")
    fs = 1.0 / sample_period_s
    if params.kind == "lowpass":
        sos = scipy.signal.butter(params.lowpass_order, params.lowpass_cutoff_hz, fs=fs, output="sos")
    else:
        b, a = scipy.signal.iirnotch(params.notch_frequency_hz, params.notch_quality, fs=fs)
        sos = scipy.signal.tf2sos(b, a)
    worst_db = _worst_attenuation_db(sos, params, fs)
    if worst_db < params.required_attenuation_db:
        raise ParameterError(
            field_name,
            design_hz,
            f"attenuates the first mode ({params.first_mode_hz:g} Hz ± {params.mode_band_fraction:.0%}) by only "
            f"{worst_db:.1f} dB; required_attenuation_db is {params.required_attenuation_db:g}",
        )
    return np.asarray(sos, dtype=float)


def attenuation_db(sos: np.ndarray, frequencies_hz: np.ndarray, sample_period_s: float) -> np.ndarray:
    """Attenuation (dB, positive = quieter) of a sos filter at the given frequencies."""
    import scipy.signal

    _, response = scipy.signal.sosfreqz(sos, worN=np.asarray(frequencies_hz, dtype=float), fs=1.0 / sample_period_s)
    return -20.0 * np.log10(np.maximum(np.abs(response), 1e-300))


def _worst_attenuation_db(sos: np.ndarray, params: ShapingParameters, fs: float) -> float:
    band = params.first_mode_hz * (1.0 + params.mode_band_fraction * np.linspace(-1.0, 1.0, 201))
    band = band[band < 0.5 * fs]
    if band.size == 0:
        return math.inf  # the whole band lies above Nyquist: a sampled command cannot contain it
    return float(np.min(attenuation_db(sos, band, 1.0 / fs)))


class CommandShaper:
    """Shapes platform pose commands (relative to neutral, so rest is the zero state) over whole signals."""

    def __init__(self, params: ShapingParameters, sample_period_s: float) -> None:
        self.params = params
        self.sample_period_s = float(sample_period_s)
        self.sos = np.ascontiguousarray(shaping_sections(params, sample_period_s))

    def shape_batch(self, poses: np.ndarray) -> np.ndarray:
        """Shaped poses (N, 6) from rest."""
        poses = np.asarray(poses, dtype=float)
        if poses.ndim != 2 or poses.shape[1] != 6:
            raise ValueError(f"poses: shape {poses.shape}, expected (N, 6)")
        return np.ascontiguousarray(filter_sections(self.sos, poses.T).T)

    def attenuation_db(self, frequencies_hz: np.ndarray) -> np.ndarray:
        return attenuation_db(self.sos, frequencies_hz, self.sample_period_s)
