"""Motion-cue generators for prescriptions: what the patient should feel, sample by sample.

Each generator yields the washout's inputs (paper §4, Figure 12): the specific force f (m/s², head
frame, x forward, y left, z up) and the angular velocity ω (rad/s, roll/pitch/yaw rates). The paper's
own signals are here: the acceleration square wave used for tuning (§4.2: period 2 s, 2 m/s²) and
the steps of §3.2 (5 → 0.5 m/s² at 0.1 s) and §4.3 (0.2 g held 10 s). Also sinusoids and multi-sines
per axis, gait-like periodic cues, seeded random perturbation pulses and the replay of an uploaded CSV.

A cue is the deviation from standing still: gravity is not included (a patient at rest feels f = 0).

Every kind is a pure function of the tick index, evaluated vectorised by `_fill`. `step()` serves
samples from a preallocated chunk that `_fill` refills, and `generate()` calls the same `_fill` over
the whole range, so streaming and batch give bit-identical numbers.
"""

from __future__ import annotations

import abc
import csv
import io
import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from core.errors import InvalidValueError

TRANSLATION_AXES = ("x", "y", "z")
ROTATION_AXES = ("roll", "pitch", "yaw")
CUE_KINDS = ("square_wave", "step", "sine", "multisine", "gait", "perturbations", "csv_replay")

# Bounds on what a prescription may ask for; the robot's own limits are checked later, offline.
SPECIFIC_FORCE_MAX_M_S2 = 10.0
ANGULAR_VELOCITY_MAX_RAD_S = 2.0
FREQUENCY_MAX_HZ = 5.0  # well under the first natural frequency, 9.76 Hz (REFERENCE.md §1)
CUE_TIME_MAX_S = 3600.0
CSV_ROWS_MAX = 2_000_000
CADENCE_RANGE_STEPS_PER_MIN = (30.0, 150.0)
CHUNK_SAMPLES = 256


class CueSpecError(InvalidValueError):
    """An invalid cue specification; names the field, the value and the limit it broke."""


# --- Field validation -----------------------------------------------------------------------------


def _number(spec: Mapping[str, Any], name: str, low: float, high: float, default: float | None = None) -> float:
    if name not in spec:
        if default is None:
            raise CueSpecError(name, None, "required")
        return default
    value = spec[name]
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise CueSpecError(name, value, "must be a finite number")
    if not low <= value <= high:
        raise CueSpecError(name, value, f"must be in [{low:g}, {high:g}]")
    return float(value)


def _positive(spec: Mapping[str, Any], name: str, high: float, default: float | None = None) -> float:
    value = _number(spec, name, 0.0, high, default)
    if value <= 0.0:
        raise CueSpecError(name, value, "must be > 0")
    return value


def _axis_amplitude(spec: Mapping[str, Any], prefix: str = "") -> tuple[int, bool, float]:
    """(index within its vector, is_rotation, amplitude) for an axis field and its matching amplitude.

    Translational axes take `amplitude_m_s2`, rotational ones `amplitude_rad_s`: the unit is in the name.
    """
    axis = spec.get("axis")
    if axis in TRANSLATION_AXES:
        unit_name, bound = "amplitude_m_s2", SPECIFIC_FORCE_MAX_M_S2
    elif axis in ROTATION_AXES:
        unit_name, bound = "amplitude_rad_s", ANGULAR_VELOCITY_MAX_RAD_S
    else:
        raise CueSpecError(f"{prefix}axis", axis, f"must be one of {TRANSLATION_AXES + ROTATION_AXES}")
    wrong = "amplitude_rad_s" if unit_name == "amplitude_m_s2" else "amplitude_m_s2"
    if wrong in spec:
        raise CueSpecError(f"{prefix}{wrong}", spec[wrong], f"axis {axis!r} takes {unit_name}")
    try:
        amplitude = _number(spec, unit_name, -bound, bound)
    except CueSpecError as error:
        raise CueSpecError(prefix + error.field, error.value, error.limit) from None
    rotation = axis in ROTATION_AXES
    index = (ROTATION_AXES if rotation else TRANSLATION_AXES).index(axis)
    return index, rotation, amplitude


def _allowed_fields(spec: Mapping[str, Any], allowed: set[str], prefix: str = "") -> None:
    unknown = sorted(set(spec) - allowed - {"kind"})
    if unknown:
        raise CueSpecError(f"{prefix}{unknown[0]}", spec[unknown[0]], f"unknown field; allowed: {sorted(allowed)}")


# --- Generators -----------------------------------------------------------------------------------


class CueGenerator(abc.ABC):
    """A cue sampled every `sample_period_s`: `step()` streams it, `generate()` gives it as arrays."""

    def __init__(self, sample_period_s: float) -> None:
        if not (isinstance(sample_period_s, float | int) and 0.0 < sample_period_s <= 0.1):
            raise CueSpecError("sample_period_s", sample_period_s, "must be in (0, 0.1] s")
        self.sample_period_s = float(sample_period_s)
        self._force_chunk = np.zeros((CHUNK_SAMPLES, 3))
        self._angular_chunk = np.zeros((CHUNK_SAMPLES, 3))
        self._chunk_offsets = np.arange(CHUNK_SAMPLES)
        self.tick = 0
        self._chunk_start = -CHUNK_SAMPLES

    def reset(self) -> None:
        """Back to t = 0."""
        self.tick = 0
        self._chunk_start = -CHUNK_SAMPLES

    def step(self) -> tuple[np.ndarray, np.ndarray]:
        """The next sample: (specific force (3,) m/s², angular velocity (3,) rad/s).

        Both are views of an internal buffer, valid until the next call; copy them to keep them.
        """
        row = self.tick - self._chunk_start
        if not 0 <= row < CHUNK_SAMPLES:
            self._chunk_start, row = self.tick, 0
            self._fill(self._chunk_offsets + self.tick, self._force_chunk, self._angular_chunk)
        self.tick += 1
        return self._force_chunk[row], self._angular_chunk[row]

    def generate(self, duration_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The cue from t = 0 for `duration_s`: specific force (N, 3) and angular velocity (N, 3)."""
        if not (math.isfinite(duration_s) and 0.0 < duration_s <= CUE_TIME_MAX_S):
            raise CueSpecError("duration_s", duration_s, f"must be in (0, {CUE_TIME_MAX_S:g}] s")
        count = round(duration_s / self.sample_period_s)
        force, angular = np.zeros((count, 3)), np.zeros((count, 3))
        self._fill(np.arange(count), force, angular)
        return force, angular

    def _times_s(self, ticks: np.ndarray) -> np.ndarray:
        return ticks * self.sample_period_s

    @abc.abstractmethod
    def _fill(self, ticks: np.ndarray, force_out: np.ndarray, angular_out: np.ndarray) -> None:
        """Write the samples of `ticks` (M,) into `force_out` (M, 3) and `angular_out` (M, 3)."""


class _SingleAxisCue(CueGenerator):
    """A scalar waveform on one axis; subclasses give the waveform of time."""

    def __init__(self, sample_period_s: float, axis_index: int, rotation: bool) -> None:
        super().__init__(sample_period_s)
        self.axis_index = axis_index
        self.rotation = rotation

    def _fill(self, ticks: np.ndarray, force_out: np.ndarray, angular_out: np.ndarray) -> None:
        force_out[:] = 0.0
        angular_out[:] = 0.0
        target = angular_out if self.rotation else force_out
        target[:, self.axis_index] = self._waveform(self._times_s(ticks))

    @abc.abstractmethod
    def _waveform(self, times_s: np.ndarray) -> np.ndarray: ...


class SquareWaveCue(_SingleAxisCue):
    """±amplitude with the given period and duty cycle, from `start_s` (paper §4.2 tuning input)."""

    def __init__(
        self,
        sample_period_s: float,
        axis_index: int,
        rotation: bool,
        amplitude: float,
        period_s: float,
        duty: float,
        start_s: float,
    ) -> None:
        super().__init__(sample_period_s, axis_index, rotation)
        self.amplitude, self.period_s, self.duty, self.start_s = amplitude, period_s, duty, start_s

    def _waveform(self, times_s: np.ndarray) -> np.ndarray:
        since_start = times_s - self.start_s
        phase = np.mod(since_start / self.period_s, 1.0)
        wave = np.where(phase < self.duty, self.amplitude, -self.amplitude)
        return np.where(since_start >= 0.0, wave, 0.0)


class StepCue(_SingleAxisCue):
    """`initial` until `step_time_s`, then `final`; back to `initial` at `end_time_s` if given (§3.2, §4.3)."""

    def __init__(
        self,
        sample_period_s: float,
        axis_index: int,
        rotation: bool,
        initial: float,
        final: float,
        step_time_s: float,
        end_time_s: float,
    ) -> None:
        super().__init__(sample_period_s, axis_index, rotation)
        self.initial, self.final, self.step_time_s, self.end_time_s = initial, final, step_time_s, end_time_s

    def _waveform(self, times_s: np.ndarray) -> np.ndarray:
        stepped = (times_s >= self.step_time_s) & (times_s < self.end_time_s)
        return np.where(stepped, self.final, self.initial)


class SumOfSinesCue(CueGenerator):
    """Σ amplitude_k · sin(2π f_k t + φ_k) on each component's axis: sines, multi-sines and gait cues."""

    def __init__(
        self,
        sample_period_s: float,
        axis_indices: np.ndarray,  # (K,) 0..5: x, y, z, roll, pitch, yaw
        amplitudes: np.ndarray,
        frequencies_hz: np.ndarray,
        phases_rad: np.ndarray,
    ) -> None:
        super().__init__(sample_period_s)
        self.axis_indices = np.asarray(axis_indices, dtype=int)
        self.amplitudes = np.asarray(amplitudes, dtype=float)
        self.angular_frequencies = 2.0 * math.pi * np.asarray(frequencies_hz, dtype=float)
        self.phases_rad = np.asarray(phases_rad, dtype=float)

    def _fill(self, ticks: np.ndarray, force_out: np.ndarray, angular_out: np.ndarray) -> None:
        times = self._times_s(ticks)
        components = self.amplitudes * np.sin(times[:, None] * self.angular_frequencies + self.phases_rad)
        six = np.zeros((len(ticks), 6))
        np.add.at(six.T, self.axis_indices, components.T)
        force_out[:] = six[:, :3]
        angular_out[:] = six[:, 3:]


class PerturbationCue(CueGenerator):
    """Seeded random pulses for balance training (translation and/or tilt).

    Onsets are separated by intervals drawn uniformly from [interval_min_s, interval_max_s]; each pulse
    has a uniformly random horizontal direction. A translation pulse is one period of a sine in
    specific force (net velocity zero: the support moves and stops). A tilt pulse is one period of a
    sine in angular velocity about a random horizontal axis (tilt out and back).
    """

    def __init__(
        self,
        sample_period_s: float,
        seed: int,
        translation_m_s2: float,
        tilt_rate_rad_s: float,
        pulse_duration_s: float,
        interval_min_s: float,
        interval_max_s: float,
        first_onset_s: float,
    ) -> None:
        super().__init__(sample_period_s)
        self.translation_m_s2, self.tilt_rate_rad_s = translation_m_s2, tilt_rate_rad_s
        self.pulse_duration_s = pulse_duration_s
        self.interval_min_s, self.interval_max_s = interval_min_s, interval_max_s
        self._rng = np.random.default_rng(seed)
        kinds = [k for k, magnitude in ((0, translation_m_s2), (1, tilt_rate_rad_s)) if magnitude > 0.0]
        self._kinds = np.array(kinds)
        # The schedule only ever grows, in draw order, so every caller sees the same pulses.
        self.onsets_s = np.array([first_onset_s])
        self.pulse_kinds = self._rng.choice(self._kinds, size=1)
        self.directions_rad = self._rng.uniform(0.0, 2.0 * math.pi, size=1)

    def _extend_schedule(self, until_s: float) -> None:
        while self.onsets_s[-1] <= until_s:
            count = 64
            gaps = self._rng.uniform(self.interval_min_s, self.interval_max_s, size=count)
            self.onsets_s = np.concatenate([self.onsets_s, self.onsets_s[-1] + np.cumsum(gaps)])
            self.pulse_kinds = np.concatenate([self.pulse_kinds, self._rng.choice(self._kinds, size=count)])
            self.directions_rad = np.concatenate(
                [self.directions_rad, self._rng.uniform(0.0, 2.0 * math.pi, size=count)]
            )

    def _fill(self, ticks: np.ndarray, force_out: np.ndarray, angular_out: np.ndarray) -> None:
        times = self._times_s(ticks)
        self._extend_schedule(float(times[-1]))
        # Intervals are at least as long as a pulse, so at most one pulse is active at any time.
        latest = np.searchsorted(self.onsets_s, times, side="right") - 1
        active = latest >= 0
        index = np.where(active, latest, 0)
        since_onset = times - self.onsets_s[index]
        active &= since_onset < self.pulse_duration_s
        shape = np.where(active, np.sin(2.0 * math.pi * since_onset / self.pulse_duration_s), 0.0)
        direction = self.directions_rad[index]
        is_tilt = self.pulse_kinds[index] == 1
        translation = np.where(is_tilt, 0.0, self.translation_m_s2 * shape)
        tilt = np.where(is_tilt, self.tilt_rate_rad_s * shape, 0.0)
        force_out[:] = 0.0
        angular_out[:] = 0.0
        force_out[:, 0] = translation * np.cos(direction)
        force_out[:, 1] = translation * np.sin(direction)
        angular_out[:, 0] = tilt * np.cos(direction)
        angular_out[:, 1] = tilt * np.sin(direction)


class CsvReplayCue(CueGenerator):
    """Replay of recorded samples (time_s, specific force, optional angular velocity), linearly
    interpolated onto the control period; zero after the last row."""

    def __init__(self, sample_period_s: float, times_s: np.ndarray, force: np.ndarray, angular: np.ndarray) -> None:
        super().__init__(sample_period_s)
        self.times_s, self.force, self.angular = times_s, force, angular

    def _fill(self, ticks: np.ndarray, force_out: np.ndarray, angular_out: np.ndarray) -> None:
        times = self._times_s(ticks)
        for column in range(3):
            force_out[:, column] = np.interp(times, self.times_s, self.force[:, column], right=0.0)
            angular_out[:, column] = np.interp(times, self.times_s, self.angular[:, column], right=0.0)


# --- Spec parsing ---------------------------------------------------------------------------------

CSV_FORCE_COLUMNS = ("specific_force_x_m_s2", "specific_force_y_m_s2", "specific_force_z_m_s2")
CSV_ANGULAR_COLUMNS = ("angular_velocity_x_rad_s", "angular_velocity_y_rad_s", "angular_velocity_z_rad_s")


def parse_cue_csv(text: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate an uploaded CSV: a header with `time_s` and the three specific-force columns (the
    angular-velocity columns are optional), finite values within bounds, strictly increasing time
    starting at or after 0. Returns times (N,), force (N, 3), angular velocity (N, 3)."""
    if not isinstance(text, str) or not text.strip():
        raise CueSpecError("csv", text if not isinstance(text, str) else "", "must be non-empty CSV text")
    reader = csv.reader(io.StringIO(text))
    header = [name.strip() for name in next(reader)]
    missing = [name for name in ("time_s", *CSV_FORCE_COLUMNS) if name not in header]
    if missing:
        raise CueSpecError("csv.header", header, f"missing column {missing[0]!r}")
    extra = sorted(set(header) - {"time_s", *CSV_FORCE_COLUMNS, *CSV_ANGULAR_COLUMNS})
    if extra:
        raise CueSpecError("csv.header", header, f"unknown column {extra[0]!r}")
    rows = list(reader)
    if not 2 <= len(rows) <= CSV_ROWS_MAX:
        raise CueSpecError("csv.rows", len(rows), f"must have 2 to {CSV_ROWS_MAX} data rows")
    try:
        table = np.array([[float(cell) for cell in row] for row in rows])
    except ValueError as error:
        raise CueSpecError("csv", str(error), "every cell must be a number") from None
    if table.ndim != 2 or table.shape[1] != len(header):
        raise CueSpecError("csv.rows", len(rows), f"every row must have {len(header)} cells")
    for column, name in enumerate(header):
        values = table[:, column]
        if not np.all(np.isfinite(values)):
            row = int(np.argmax(~np.isfinite(values)))
            raise CueSpecError(f"csv[{row + 1}].{name}", float(values[row]), "must be finite")
        bound = (
            CUE_TIME_MAX_S
            if name == "time_s"
            else (SPECIFIC_FORCE_MAX_M_S2 if name in CSV_FORCE_COLUMNS else ANGULAR_VELOCITY_MAX_RAD_S)
        )
        low = 0.0 if name == "time_s" else -bound
        outside = (values < low) | (values > bound)
        if np.any(outside):
            row = int(np.argmax(outside))
            raise CueSpecError(f"csv[{row + 1}].{name}", float(values[row]), f"must be in [{low:g}, {bound:g}]")
    times = table[:, header.index("time_s")]
    steps = np.diff(times)
    if np.any(steps <= 0.0):
        row = int(np.argmax(steps <= 0.0)) + 2
        raise CueSpecError(f"csv[{row}].time_s", float(times[row - 1]), "time must increase strictly")
    force = np.stack([table[:, header.index(name)] for name in CSV_FORCE_COLUMNS], axis=1)
    angular = np.zeros_like(force)
    for axis, name in enumerate(CSV_ANGULAR_COLUMNS):
        if name in header:
            angular[:, axis] = table[:, header.index(name)]
    return times, force, angular


def _square_wave(spec: Mapping[str, Any], period: float, seed: int) -> CueGenerator:
    _allowed_fields(spec, {"axis", "amplitude_m_s2", "amplitude_rad_s", "period_s", "duty", "start_s"})
    index, rotation, amplitude = _axis_amplitude(spec)
    period_s = _number(spec, "period_s", 2.0 / FREQUENCY_MAX_HZ, CUE_TIME_MAX_S)
    duty = _number(spec, "duty", 0.05, 0.95, default=0.5)
    start_s = _number(spec, "start_s", 0.0, CUE_TIME_MAX_S, default=0.0)
    return SquareWaveCue(period, index, rotation, amplitude, period_s, duty, start_s)


def _step(spec: Mapping[str, Any], period: float, seed: int) -> CueGenerator:
    allowed = {"axis", "step_time_s", "end_time_s"}
    axis = spec.get("axis")
    unit = "m_s2" if axis in TRANSLATION_AXES else "rad_s"
    allowed |= {f"initial_{unit}", f"final_{unit}"}
    _allowed_fields(spec, allowed)
    index, rotation, _ = _axis_amplitude({"axis": axis, f"amplitude_{unit}": 0.0})
    bound = SPECIFIC_FORCE_MAX_M_S2 if unit == "m_s2" else ANGULAR_VELOCITY_MAX_RAD_S
    initial = _number(spec, f"initial_{unit}", -bound, bound, default=0.0)
    final = _number(spec, f"final_{unit}", -bound, bound)
    step_time_s = _number(spec, "step_time_s", 0.0, CUE_TIME_MAX_S, default=0.0)
    end_time_s = _number(spec, "end_time_s", 0.0, CUE_TIME_MAX_S) if "end_time_s" in spec else math.inf
    if end_time_s <= step_time_s:
        raise CueSpecError("end_time_s", end_time_s, f"must be after step_time_s = {step_time_s:g} s")
    return StepCue(period, index, rotation, initial, final, step_time_s, end_time_s)


def _sine_component(spec: Mapping[str, Any], prefix: str = "") -> tuple[int, float, float, float]:
    _allowed_fields(spec, {"axis", "amplitude_m_s2", "amplitude_rad_s", "frequency_hz", "phase_rad"}, prefix)
    index, rotation, amplitude = _axis_amplitude(spec, prefix)
    try:
        frequency = _positive(spec, "frequency_hz", FREQUENCY_MAX_HZ)
        phase = _number(spec, "phase_rad", -2.0 * math.pi, 2.0 * math.pi, default=0.0)
    except CueSpecError as error:
        raise CueSpecError(prefix + error.field, error.value, error.limit) from None
    return index + 3 * rotation, amplitude, frequency, phase


def _sine(spec: Mapping[str, Any], period: float, seed: int) -> CueGenerator:
    axis, amplitude, frequency, phase = _sine_component(spec)
    return SumOfSinesCue(period, np.array([axis]), np.array([amplitude]), np.array([frequency]), np.array([phase]))


def _multisine(spec: Mapping[str, Any], period: float, seed: int) -> CueGenerator:
    _allowed_fields(spec, {"components"})
    components = spec.get("components")
    if not isinstance(components, list) or not 1 <= len(components) <= 32:
        raise CueSpecError("components", components, "must be a list of 1 to 32 sine components")
    parsed = []
    for number, component in enumerate(components):
        if not isinstance(component, Mapping):
            raise CueSpecError(f"components[{number}]", component, "must be an object")
        parsed.append(_sine_component(component, f"components[{number}]."))
    axes, amplitudes, frequencies, phases = (np.array(column) for column in zip(*parsed, strict=True))
    return SumOfSinesCue(period, axes, amplitudes, frequencies, phases)


def _gait(spec: Mapping[str, Any], period: float, seed: int) -> CueGenerator:
    """Walking-like cue: vertical and fore-aft at the step frequency, lateral (and roll) at the stride
    frequency, half of it, since the weight shifts from one foot to the other once per stride."""
    _allowed_fields(
        spec,
        {
            "cadence_steps_per_min",
            "vertical_amplitude_m_s2",
            "forward_amplitude_m_s2",
            "lateral_amplitude_m_s2",
            "roll_amplitude_rad_s",
        },
    )
    low, high = CADENCE_RANGE_STEPS_PER_MIN
    step_hz = _number(spec, "cadence_steps_per_min", low, high) / 60.0
    vertical = _number(spec, "vertical_amplitude_m_s2", 0.0, SPECIFIC_FORCE_MAX_M_S2, default=0.0)
    forward = _number(spec, "forward_amplitude_m_s2", 0.0, SPECIFIC_FORCE_MAX_M_S2, default=0.0)
    lateral = _number(spec, "lateral_amplitude_m_s2", 0.0, SPECIFIC_FORCE_MAX_M_S2, default=0.0)
    roll = _number(spec, "roll_amplitude_rad_s", 0.0, ANGULAR_VELOCITY_MAX_RAD_S, default=0.0)
    if vertical == forward == lateral == roll == 0.0:
        raise CueSpecError("vertical_amplitude_m_s2", 0.0, "at least one gait amplitude must be > 0")
    stride_hz = step_hz / 2.0
    return SumOfSinesCue(
        period,
        axis_indices=np.array([2, 0, 1, 3]),
        amplitudes=np.array([vertical, forward, lateral, roll]),
        frequencies_hz=np.array([step_hz, step_hz, stride_hz, stride_hz]),
        phases_rad=np.array([0.0, math.pi / 2.0, 0.0, math.pi / 2.0]),
    )


def _perturbations(spec: Mapping[str, Any], period: float, seed: int) -> CueGenerator:
    _allowed_fields(
        spec,
        {
            "translation_m_s2",
            "tilt_rate_rad_s",
            "pulse_duration_s",
            "interval_min_s",
            "interval_max_s",
            "first_onset_s",
        },
    )
    translation = _number(spec, "translation_m_s2", 0.0, SPECIFIC_FORCE_MAX_M_S2, default=0.0)
    tilt = _number(spec, "tilt_rate_rad_s", 0.0, ANGULAR_VELOCITY_MAX_RAD_S, default=0.0)
    if translation == 0.0 and tilt == 0.0:
        raise CueSpecError("translation_m_s2", 0.0, "translation_m_s2 or tilt_rate_rad_s must be > 0")
    pulse = _number(spec, "pulse_duration_s", 1.0 / FREQUENCY_MAX_HZ, 10.0, default=0.5)
    interval_min = _number(spec, "interval_min_s", pulse, CUE_TIME_MAX_S, default=max(pulse, 3.0))
    interval_max = _number(spec, "interval_max_s", interval_min, CUE_TIME_MAX_S, default=max(interval_min, 8.0))
    first_onset = _number(spec, "first_onset_s", 0.0, CUE_TIME_MAX_S, default=interval_min)
    return PerturbationCue(period, seed, translation, tilt, pulse, interval_min, interval_max, first_onset)


def _csv_replay(spec: Mapping[str, Any], period: float, seed: int) -> CueGenerator:
    _allowed_fields(spec, {"csv"})
    return CsvReplayCue(period, *parse_cue_csv(spec.get("csv")))  # type: ignore[arg-type]


_BUILDERS: dict[str, Callable[[Mapping[str, Any], float, int], CueGenerator]] = {
    "square_wave": _square_wave,
    "step": _step,
    "sine": _sine,
    "multisine": _multisine,
    "gait": _gait,
    "perturbations": _perturbations,
    "csv_replay": _csv_replay,
}


def cue_from_spec(spec: Mapping[str, Any], sample_period_s: float, seed: int = 0) -> CueGenerator:
    """Build the generator a JSON-able spec describes; refuses an invalid spec with `CueSpecError`."""
    if not isinstance(spec, Mapping):
        raise CueSpecError("cue", spec, "must be an object with a 'kind'")
    kind = spec.get("kind")
    if kind not in _BUILDERS:
        raise CueSpecError("kind", kind, f"must be one of {list(CUE_KINDS)}")
    return _BUILDERS[kind](spec, sample_period_s, seed)


def validate_cue_spec(spec: Mapping[str, Any]) -> None:
    """Raise `CueSpecError` (field, value, limit) if `spec` is not a valid cue."""
    cue_from_spec(spec, 0.001, seed=0)
