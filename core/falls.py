"""Fall detectors on the force plates and the harness load cell, and their evaluation (issue 8; REFERENCE.md §5).

Three detectors, each "a condition held for a minimum time":

- harness load above a fraction of body weight (default 30 % BW, the criterion widely cited after Yang &
  Pai 2011, J Biomech 44:2243, "Automatic recognition of falls in gait-slip training: harness load cell
  based criteria"; the minimum duration is ours, to reject rope snatches);
- centre of pressure outside the foot's footprint shrunk by a margin, on a loaded plate (COP means
  nothing on an unloaded plate);
- loss of load on a foot plate (Fz below a fraction of body weight: a step, a lifted foot or hanging
  in the harness, all of which clinical protocols count as falls).

A detector fires once when its condition has held for `min_duration_s` (rounded up to whole samples) and
re-arms when the condition clears. The event carries the onset (first sample of the run), the detection
time, the detector's name and the values that tripped it. The streaming (`FallMonitor.step`, per tick,
no allocation unless an event fires) and the batch (`detect_falls`) forms share the conditions and give
the same events.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

import numba
import numpy as np

from core.patient import GRAVITY_M_S2, FootGeometry, ParameterError, require_in_range

HARNESS_LOAD = "harness_load"
COP_OUTSIDE_BASE = "cop_outside_base"
FOOT_UNLOADED = "foot_unloaded"
FUSED = "fused"
DETECTOR_NAMES = (HARNESS_LOAD, COP_OUTSIDE_BASE, FOOT_UNLOADED, FUSED)
FEET = ("right", "left")


# --- configuration ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class HarnessLoadConfig:
    enabled: bool = True
    threshold_fraction_bw: float = 0.30  # Yang & Pai 2011
    min_duration_s: float = 0.05

    def __post_init__(self) -> None:
        require_in_range("harness.threshold_fraction_bw", self.threshold_fraction_bw, 0.0, 2.0, low_open=True)
        require_in_range("harness.min_duration_s", self.min_duration_s, 0.0, 10.0)


@dataclass(frozen=True)
class CopOutsideBaseConfig:
    """Footprint rectangle in the foot-plate frame (origin under the ankle, x anterior, y left), metres."""

    enabled: bool = True
    x_min_m: float = -0.065
    x_max_m: float = 0.196
    y_min_m: float = -0.047
    y_max_m: float = 0.047
    margin_m: float = 0.01  # inward: the COP must stay this far inside the edge
    min_duration_s: float = 0.1
    min_load_fraction_bw: float = 0.1  # below this the plate's COP is not trusted

    def __post_init__(self) -> None:
        for name in ("x_min_m", "x_max_m", "y_min_m", "y_max_m"):
            require_in_range(f"cop.{name}", getattr(self, name), -0.5, 0.5)
        if not self.x_min_m < self.x_max_m:
            raise ParameterError("cop.x_max_m", self.x_max_m, f"must be > cop.x_min_m = {self.x_min_m}")
        if not self.y_min_m < self.y_max_m:
            raise ParameterError("cop.y_max_m", self.y_max_m, f"must be > cop.y_min_m = {self.y_min_m}")
        half_span = 0.5 * min(self.x_max_m - self.x_min_m, self.y_max_m - self.y_min_m)
        require_in_range("cop.margin_m", self.margin_m, -0.1, half_span, high_open=True)
        require_in_range("cop.min_duration_s", self.min_duration_s, 0.0, 10.0)
        require_in_range("cop.min_load_fraction_bw", self.min_load_fraction_bw, 0.0, 1.0)

    @classmethod
    def for_foot(cls, foot: FootGeometry, **overrides: Any) -> CopOutsideBaseConfig:
        return cls(
            x_min_m=-foot.heel_m,
            x_max_m=foot.toe_m,
            y_min_m=-foot.half_breadth_m,
            y_max_m=foot.half_breadth_m,
            **overrides,
        )


@dataclass(frozen=True)
class FootUnloadedConfig:
    enabled: bool = True
    threshold_fraction_bw: float = 0.05
    min_duration_s: float = 0.2

    def __post_init__(self) -> None:
        require_in_range("unload.threshold_fraction_bw", self.threshold_fraction_bw, 0.0, 0.5, low_open=True)
        require_in_range("unload.min_duration_s", self.min_duration_s, 0.0, 10.0)


@dataclass(frozen=True)
class FusedConfig:
    """The fused detector: four kinds of evidence, each normalised to 1 at its reference, weighted and summed.

    - harness: load / (`harness_reference_fraction_bw` · BW);
    - COP at the edge of support: the share of the last ~0.1 s (a first-order average) that a loaded plate's
      COP spent within `edge_margin_m` of its footprint's edge (the footprint comes from `cop`);
    - body drop: the body's vertical sag estimated from the plates and the harness, the leaky double integral
      of (measured load − standing load)/mass, the support's own heave taken out; / `drop_reference_m`;
    - unloading: the share of the standing load the plates lost (a grab, a foot off the plate, hanging in
      the harness) / `unload_reference_fraction`, and one foot's loss of its half of the load (a step).

    The standing load is a slow average of the measured load (`reference_time_constant_s`), so a body mass
    entered a few kilograms wrong neither drifts the drop estimate nor reads as unloading. The detector
    fires when the weighted sum has been ≥ `threshold` for `min_duration_s`. The weights and references
    are tuned on a simulated cohort (`ssp-rehab tune-falls`); the defaults are that tuning's result
    (docs/falls.md)."""

    enabled: bool = True
    harness_reference_fraction_bw: float = 0.3
    edge_margin_m: float = 0.01
    drop_reference_m: float = 0.07
    unload_reference_fraction: float = 0.3
    weight_harness: float = 1.0
    weight_edge: float = 0.25
    weight_drop: float = 1.0
    weight_unload: float = 1.0
    weight_foot: float = 0.5
    threshold: float = 1.0
    min_duration_s: float = 0.03
    reference_time_constant_s: float = 3.0
    drop_leak_time_constant_s: float = 0.5
    edge_time_constant_s: float = 0.1

    def __post_init__(self) -> None:
        require_in_range(
            "fused.harness_reference_fraction_bw", self.harness_reference_fraction_bw, 0.0, 2.0, low_open=True
        )
        require_in_range("fused.edge_margin_m", self.edge_margin_m, 0.0, 0.1)
        require_in_range("fused.drop_reference_m", self.drop_reference_m, 0.0, 1.0, low_open=True)
        require_in_range("fused.unload_reference_fraction", self.unload_reference_fraction, 0.0, 1.0, low_open=True)
        for name in ("weight_harness", "weight_edge", "weight_drop", "weight_unload", "weight_foot"):
            require_in_range(f"fused.{name}", getattr(self, name), 0.0, 10.0)
        require_in_range("fused.threshold", self.threshold, 0.0, 50.0, low_open=True)
        require_in_range("fused.min_duration_s", self.min_duration_s, 0.0, 10.0)
        require_in_range("fused.reference_time_constant_s", self.reference_time_constant_s, 0.1, 600.0)
        require_in_range("fused.drop_leak_time_constant_s", self.drop_leak_time_constant_s, 0.05, 60.0)
        require_in_range("fused.edge_time_constant_s", self.edge_time_constant_s, 0.001, 10.0)


@dataclass(frozen=True)
class FallDetectorConfig:
    """The detectors for one patient (body weight scales the thresholds)."""

    body_mass_kg: float
    harness: HarnessLoadConfig = field(default_factory=HarnessLoadConfig)
    cop: CopOutsideBaseConfig = field(default_factory=CopOutsideBaseConfig)
    unload: FootUnloadedConfig = field(default_factory=FootUnloadedConfig)
    fused: FusedConfig = field(default_factory=lambda: FusedConfig(enabled=False))

    def __post_init__(self) -> None:
        require_in_range("body_mass_kg", self.body_mass_kg, 20.0, 250.0)

    @classmethod
    def for_patient(cls, body_mass_kg: float, height_m: float) -> FallDetectorConfig:
        """What the supervisor runs: the fused detector and the harness criterion, with the footprint sized from
        the patient's height (Winter's foot proportions). The COP and the foot-unloaded detectors alone fire
        on hard recoveries and on weight shifts; they stay available (enable them) for evaluation."""
        require_in_range("height_m", height_m, 1.0, 2.3)
        return cls(
            body_mass_kg=body_mass_kg,
            cop=CopOutsideBaseConfig.for_foot(FootGeometry.from_height(height_m), enabled=False),
            unload=FootUnloadedConfig(enabled=False),
            fused=FusedConfig(),
        )

    @property
    def body_weight_n(self) -> float:
        return self.body_mass_kg * GRAVITY_M_S2

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FallDetectorConfig:
        sections: dict[str, Any] = {
            "harness": HarnessLoadConfig,
            "cop": CopOutsideBaseConfig,
            "unload": FootUnloadedConfig,
            "fused": FusedConfig,
        }
        unknown = sorted(set(data) - {"body_mass_kg", *sections})
        if unknown:
            raise ParameterError(unknown[0], data[unknown[0]], "unknown fall-detector setting")
        built: dict[str, Any] = {}
        for name, section_cls in sections.items():
            section = dict(data.get(name, {}))
            known = {f.name for f in fields(section_cls)}
            extra = sorted(set(section) - known)
            if extra:
                raise ParameterError(f"{name}.{extra[0]}", section[extra[0]], "unknown fall-detector setting")
            built[name] = section_cls(**section)
        if "body_mass_kg" not in data:
            raise ParameterError("body_mass_kg", None, "required")
        return cls(body_mass_kg=data["body_mass_kg"], **built)


def samples_for(duration_s: float, sample_period_s: float) -> int:
    """Whole samples a condition must hold to last `duration_s` (at least one)."""
    return max(1, math.ceil(duration_s / sample_period_s - 1e-9))


# --- events --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FallEvent:
    detector: str
    onset_s: float  # first sample of the run that tripped the detector
    detected_s: float  # the sample at which the minimum duration was reached
    tick: int  # sample index of the detection
    values: dict[str, Any]

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": "fall",
            "detector": self.detector,
            "tick": self.tick,
            "onset_s": self.onset_s,
            "detected_s": self.detected_s,
            "details": dict(self.values),
        }


# --- the detectors: one condition, a scalar (per tick) and a vector (batch) form --------------------


class _Detector:
    """A condition held for a number of samples. Subclasses give the condition and the event values."""

    name = ""

    def __init__(self, config: FallDetectorConfig, min_duration_s: float, sample_period_s: float) -> None:
        self.config = config
        self.required_samples = samples_for(min_duration_s, sample_period_s)
        self.body_weight_n = config.body_weight_n
        self.reset()

    def reset(self) -> None:
        self.run_length = 0
        self.run_onset_s = 0.0

    def update(
        self, tick: int, time_s: float, fz: np.ndarray, cop: np.ndarray, load: float, support_az: float = 0.0
    ) -> FallEvent | None:
        return self._advance(self.condition(fz, cop, load), tick, time_s, fz, cop, load)

    def _advance(
        self, held: bool, tick: int, time_s: float, fz: np.ndarray, cop: np.ndarray, load: float
    ) -> FallEvent | None:
        if not held:
            self.run_length = 0
            return None
        if self.run_length == 0:
            self.run_onset_s = time_s
        self.run_length += 1
        if self.run_length != self.required_samples:
            return None
        return FallEvent(self.name, self.run_onset_s, time_s, tick, self.values(fz, cop, load))

    def detect(
        self,
        time_s: np.ndarray,
        fz: np.ndarray,
        cop: np.ndarray,
        load: np.ndarray,
        support_az: np.ndarray | None = None,
    ) -> list[FallEvent]:
        """Batch: the runs of the condition at least `required_samples` long, vectorised."""
        held = self.conditions(fz, cop, load)
        return self._events(time_s, held, lambda tick: self.values(fz[tick], cop[tick], load[tick]))

    def _events(
        self, time_s: np.ndarray, held: np.ndarray, values_at: Callable[[int], dict[str, Any]]
    ) -> list[FallEvent]:
        """An event where each run of `held` reaches `required_samples`, with `values_at(tick)`."""
        return [
            FallEvent(self.name, float(time_s[start]), float(time_s[tick]), tick, values_at(tick))
            for start, tick in held_runs(held, self.required_samples)
        ]

    def condition(self, fz: np.ndarray, cop: np.ndarray, load: float) -> bool:
        raise NotImplementedError

    def conditions(self, fz: np.ndarray, cop: np.ndarray, load: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def values(self, fz: np.ndarray, cop: np.ndarray, load: float) -> dict[str, Any]:
        raise NotImplementedError


class HarnessLoadDetector(_Detector):
    name = HARNESS_LOAD

    def __init__(self, config: FallDetectorConfig, sample_period_s: float) -> None:
        super().__init__(config, config.harness.min_duration_s, sample_period_s)
        self.threshold_n = config.harness.threshold_fraction_bw * config.body_weight_n

    def condition(self, fz: np.ndarray, cop: np.ndarray, load: float) -> bool:
        return load > self.threshold_n

    def conditions(self, fz: np.ndarray, cop: np.ndarray, load: np.ndarray) -> np.ndarray:
        return load > self.threshold_n

    def values(self, fz: np.ndarray, cop: np.ndarray, load: float) -> dict[str, Any]:
        return {
            "harness_load_n": float(load),
            "threshold_n": self.threshold_n,
            "threshold_fraction_bw": self.config.harness.threshold_fraction_bw,
            "min_duration_s": self.config.harness.min_duration_s,
        }


class CopOutsideBaseDetector(_Detector):
    name = COP_OUTSIDE_BASE

    def __init__(self, config: FallDetectorConfig, sample_period_s: float) -> None:
        super().__init__(config, config.cop.min_duration_s, sample_period_s)
        cop = config.cop
        self.x_low, self.x_high = cop.x_min_m + cop.margin_m, cop.x_max_m - cop.margin_m
        self.y_low, self.y_high = cop.y_min_m + cop.margin_m, cop.y_max_m - cop.margin_m
        self.min_load_n = cop.min_load_fraction_bw * config.body_weight_n

    def _foot_outside(self, fz: float, x: float, y: float) -> bool:
        return fz >= self.min_load_n and not (self.x_low <= x <= self.x_high and self.y_low <= y <= self.y_high)

    def condition(self, fz: np.ndarray, cop: np.ndarray, load: float) -> bool:
        return self._foot_outside(fz[0], cop[0, 0], cop[0, 1]) or self._foot_outside(fz[1], cop[1, 0], cop[1, 1])

    def conditions(self, fz: np.ndarray, cop: np.ndarray, load: np.ndarray) -> np.ndarray:
        x, y = cop[..., 0], cop[..., 1]
        inside = (self.x_low <= x) & (x <= self.x_high) & (self.y_low <= y) & (y <= self.y_high)
        return np.any((fz >= self.min_load_n) & ~inside, axis=1)

    def values(self, fz: np.ndarray, cop: np.ndarray, load: float) -> dict[str, Any]:
        return {
            "feet": [foot for index, foot in enumerate(FEET) if self._foot_outside(fz[index], *cop[index])],
            "plate_cop_m": np.asarray(cop).tolist(),
            "plate_force_z_n": np.asarray(fz).tolist(),
            "base_x_m": [self.x_low, self.x_high],
            "base_y_m": [self.y_low, self.y_high],
            "margin_m": self.config.cop.margin_m,
            "min_duration_s": self.config.cop.min_duration_s,
        }


class FootUnloadedDetector(_Detector):
    name = FOOT_UNLOADED

    def __init__(self, config: FallDetectorConfig, sample_period_s: float) -> None:
        super().__init__(config, config.unload.min_duration_s, sample_period_s)
        self.threshold_n = config.unload.threshold_fraction_bw * config.body_weight_n

    def condition(self, fz: np.ndarray, cop: np.ndarray, load: float) -> bool:
        return fz[0] < self.threshold_n or fz[1] < self.threshold_n

    def conditions(self, fz: np.ndarray, cop: np.ndarray, load: np.ndarray) -> np.ndarray:
        return np.any(fz < self.threshold_n, axis=1)

    def values(self, fz: np.ndarray, cop: np.ndarray, load: float) -> dict[str, Any]:
        return {
            "feet": [foot for index, foot in enumerate(FEET) if fz[index] < self.threshold_n],
            "plate_force_z_n": np.asarray(fz).tolist(),
            "threshold_n": self.threshold_n,
            "threshold_fraction_bw": self.config.unload.threshold_fraction_bw,
            "min_duration_s": self.config.unload.min_duration_s,
        }


def held_runs(held: np.ndarray, required_samples: int) -> list[tuple[int, int]]:
    """(first sample, detection sample) of every run of `held` at least `required_samples` long."""
    edges = np.diff(np.concatenate([[0], held.astype(np.int8), [0]]))
    starts = np.flatnonzero(edges == 1)
    ends = np.flatnonzero(edges == -1)
    long_enough = (ends - starts) >= required_samples
    return [(int(start), int(start) + required_samples - 1) for start in starts[long_enough]]


# Fused-detector evidence, in the order of `FUSED_FEATURES` and of the kernel's output columns.
FUSED_FEATURES = ("harness", "edge", "drop", "unload", "foot")
(
    F_BODY_WEIGHT,
    F_HARNESS_REF,
    F_DROP_REF,
    F_UNLOAD_REF,
    F_W_HARNESS,
    F_W_EDGE,
    F_W_DROP,
    F_W_UNLOAD,
    F_W_FOOT,
    F_ALPHA_REF,
    F_LEAK,
    F_ALPHA_EDGE,
    F_DT,
    F_X_LOW,
    F_X_HIGH,
    F_Y_LOW,
    F_Y_HIGH,
    F_MIN_LOAD,
    F_SIZE,
) = range(19)
# state: standing load (N), drop velocity and height (m/s, m, up +), edge average, initialised flag
FS_REFERENCE, FS_VELOCITY, FS_HEIGHT, FS_EDGE, FS_READY, FS_SIZE = range(6)
FOOT_UNLOADED_SHARE = 0.1  # the lighter foot carries nothing (evidence 1) .. this share of the load (0)


@numba.njit(cache=True)
def _fused_kernel(
    p: np.ndarray,
    state: np.ndarray,
    fz: np.ndarray,
    cop: np.ndarray,
    load: np.ndarray,
    support_az: np.ndarray,
    scores: np.ndarray,
    features: np.ndarray,
) -> None:
    """Score samples in order, carrying `state` across calls (one call per tick or one per log)."""
    dt = p[F_DT]
    for n in range(fz.shape[0]):
        plates = fz[n, 0] + fz[n, 1]
        measured = plates + load[n]  # the rope hangs near vertical: its pull is lift
        if state[FS_READY] == 0.0:
            state[FS_REFERENCE] = p[F_BODY_WEIGHT]
            state[FS_READY] = 1.0
        if math.isnan(measured) or math.isnan(support_az[n]):
            scores[n] = 0.0  # a reading lost: no evidence, and the filters keep their state
            features[n, :] = 0.0
            continue
        reference = state[FS_REFERENCE]
        reference += p[F_ALPHA_REF] * (measured - reference)
        state[FS_REFERENCE] = reference
        mass = reference / GRAVITY_M_S2
        expected = reference * (1.0 + support_az[n] / GRAVITY_M_S2)  # the support's heave loads the plates
        acceleration = (measured - expected) / mass
        leak = p[F_LEAK]
        state[FS_VELOCITY] += (acceleration - leak * state[FS_VELOCITY]) * dt
        state[FS_HEIGHT] += (state[FS_VELOCITY] - leak * state[FS_HEIGHT]) * dt
        at_edge = 0.0
        for foot in range(2):
            x, y = cop[n, foot, 0], cop[n, foot, 1]
            inside = p[F_X_LOW] <= x <= p[F_X_HIGH] and p[F_Y_LOW] <= y <= p[F_Y_HIGH]
            if fz[n, foot] >= p[F_MIN_LOAD] and not inside:
                at_edge = 1.0
        state[FS_EDGE] += p[F_ALPHA_EDGE] * (at_edge - state[FS_EDGE])
        lighter = min(fz[n, 0], fz[n, 1])
        harness = load[n] / p[F_HARNESS_REF]
        drop = max(-state[FS_HEIGHT], 0.0) / p[F_DROP_REF]
        expected = max(expected, 1e-9 * reference)
        unload = max(expected - plates, 0.0) / (expected * p[F_UNLOAD_REF])
        foot = min(max(1.0 - lighter / (FOOT_UNLOADED_SHARE * expected), 0.0), 1.0)
        features[n, 0], features[n, 1], features[n, 2] = harness, state[FS_EDGE], drop
        features[n, 3], features[n, 4] = unload, foot
        scores[n] = (
            p[F_W_HARNESS] * harness
            + p[F_W_EDGE] * state[FS_EDGE]
            + p[F_W_DROP] * drop
            + p[F_W_UNLOAD] * unload
            + p[F_W_FOOT] * foot
        )


class FusedDetector(_Detector):
    """Harness load, COP at the edge of support, body drop and unloading, weighted into one score."""

    name = FUSED

    def __init__(self, config: FallDetectorConfig, sample_period_s: float) -> None:
        fused, cop = config.fused, config.cop
        margin = fused.edge_margin_m
        vector = np.zeros(F_SIZE)
        vector[F_BODY_WEIGHT] = config.body_weight_n
        vector[F_HARNESS_REF] = fused.harness_reference_fraction_bw * config.body_weight_n
        vector[F_DROP_REF] = fused.drop_reference_m
        vector[F_UNLOAD_REF] = fused.unload_reference_fraction
        vector[F_W_HARNESS], vector[F_W_EDGE], vector[F_W_DROP] = (
            fused.weight_harness,
            fused.weight_edge,
            fused.weight_drop,
        )
        vector[F_W_UNLOAD], vector[F_W_FOOT] = fused.weight_unload, fused.weight_foot
        vector[F_ALPHA_REF] = min(1.0, sample_period_s / fused.reference_time_constant_s)
        vector[F_LEAK] = 1.0 / fused.drop_leak_time_constant_s
        vector[F_ALPHA_EDGE] = min(1.0, sample_period_s / fused.edge_time_constant_s)
        vector[F_DT] = sample_period_s
        vector[F_X_LOW], vector[F_X_HIGH] = cop.x_min_m + margin, cop.x_max_m - margin
        vector[F_Y_LOW], vector[F_Y_HIGH] = cop.y_min_m + margin, cop.y_max_m - margin
        vector[F_MIN_LOAD] = cop.min_load_fraction_bw * config.body_weight_n
        self.parameters = vector
        self.threshold = fused.threshold
        # One-sample buffers for the streaming form: a tick copies into them and allocates nothing.
        self._fz, self._cop, self._load = np.zeros((1, 2)), np.zeros((1, 2, 2)), np.zeros(1)
        self._az, self._score, self._features = np.zeros(1), np.zeros(1), np.zeros((1, len(FUSED_FEATURES)))
        super().__init__(config, fused.min_duration_s, sample_period_s)

    def reset(self) -> None:
        super().reset()
        self.state = np.zeros(FS_SIZE)

    def update(
        self, tick: int, time_s: float, fz: np.ndarray, cop: np.ndarray, load: float, support_az: float = 0.0
    ) -> FallEvent | None:
        self._fz[0], self._cop[0], self._load[0], self._az[0] = fz, cop, load, support_az
        _fused_kernel(
            self.parameters, self.state, self._fz, self._cop, self._load, self._az, self._score, self._features
        )
        return self._advance(bool(self._score[0] >= self.threshold), tick, time_s, fz, cop, load)

    def scores(
        self, fz: np.ndarray, cop: np.ndarray, load: np.ndarray, support_az: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The score (N,) and the evidence (N, 5) of a whole log, from a fresh state."""
        count = fz.shape[0]
        scores, features = np.empty(count), np.empty((count, len(FUSED_FEATURES)))
        az = np.zeros(count) if support_az is None else np.ascontiguousarray(support_az, dtype=float)
        _fused_kernel(
            self.parameters,
            np.zeros(FS_SIZE),
            np.ascontiguousarray(fz, dtype=float),
            np.ascontiguousarray(cop, dtype=float),
            np.ascontiguousarray(load, dtype=float),
            az,
            scores,
            features,
        )
        return scores, features

    def detect(
        self,
        time_s: np.ndarray,
        fz: np.ndarray,
        cop: np.ndarray,
        load: np.ndarray,
        support_az: np.ndarray | None = None,
    ) -> list[FallEvent]:
        scores, features = self.scores(fz, cop, load, support_az)
        held = scores >= self.threshold
        return self._events(time_s, held, lambda tick: self._evidence(float(scores[tick]), features[tick]))

    def values(self, fz: np.ndarray, cop: np.ndarray, load: float) -> dict[str, Any]:
        return self._evidence(float(self._score[0]), self._features[0])

    def _evidence(self, score: float, features: np.ndarray) -> dict[str, Any]:
        return {
            "score": float(score),
            "threshold": self.threshold,
            "evidence": {name: round(float(value), 4) for name, value in zip(FUSED_FEATURES, features, strict=True)},
            "min_duration_s": self.config.fused.min_duration_s,
        }


def _build_detectors(config: FallDetectorConfig, sample_period_s: float) -> list[_Detector]:
    require_in_range("sample_period_s", sample_period_s, 0.0, 1.0, low_open=True)
    detectors: list[_Detector] = []
    if config.harness.enabled:
        detectors.append(HarnessLoadDetector(config, sample_period_s))
    if config.cop.enabled:
        detectors.append(CopOutsideBaseDetector(config, sample_period_s))
    if config.unload.enabled:
        detectors.append(FootUnloadedDetector(config, sample_period_s))
    if config.fused.enabled:
        detectors.append(FusedDetector(config, sample_period_s))
    return detectors


_NO_EVENTS: tuple[FallEvent, ...] = ()


class FallMonitor:
    """All enabled detectors, stepped once per control tick by the real-time worker.

    `step` returns the events that fired on this tick (an empty tuple, not a new object, on quiet
    ticks). `fallen` latches on the first event until `reset()`; the supervisor pauses the motion and
    washes the platform out to neutral when it turns true.
    """

    def __init__(self, config: FallDetectorConfig, sample_period_s: float) -> None:
        self.config = config
        self.sample_period_s = sample_period_s
        self.detectors = _build_detectors(config, sample_period_s)
        self.reset()

    def reset(self) -> None:
        for detector in self.detectors:
            detector.reset()
        self.tick = 0
        self.fallen = False
        self.events: list[FallEvent] = []

    def step(
        self,
        time_s: float,
        plate_force_z_n: np.ndarray,
        plate_cop_m: np.ndarray,
        harness_load_n: float,
        support_acceleration_z_m_s2: float = 0.0,
    ) -> tuple[FallEvent, ...]:
        """`time_s` is the session clock; the support's vertical acceleration (gravity excluded) keeps a
        heave cue from reading as a body drop."""
        fired: tuple[FallEvent, ...] = _NO_EVENTS
        for detector in self.detectors:
            event = detector.update(
                self.tick, time_s, plate_force_z_n, plate_cop_m, harness_load_n, support_acceleration_z_m_s2
            )
            if event is not None:
                fired = (*fired, event)
        if fired:
            self.fallen = True
            self.events.extend(fired)
        self.tick += 1
        return fired


def _as_signals(
    time_s: np.ndarray, plate_force_z_n: np.ndarray, plate_cop_m: np.ndarray, harness_load_n: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    time_s = np.asarray(time_s, dtype=float)
    count = time_s.shape[0] if time_s.ndim == 1 else -1
    shapes = {
        "time_s": (time_s, (count,)),
        "plate_force_z_n": (np.asarray(plate_force_z_n, dtype=float), (count, 2)),
        "plate_cop_m": (np.asarray(plate_cop_m, dtype=float), (count, 2, 2)),
        "harness_load_n": (np.asarray(harness_load_n, dtype=float), (count,)),
    }
    for name, (array, shape) in shapes.items():
        if array.shape != shape:
            raise ParameterError(name, array.shape, f"shape must be {shape} (N = len(time_s))")
    if count > 1 and not np.all(np.diff(time_s) > 0):
        raise ParameterError("time_s", "not increasing", "sample times must increase strictly")
    return time_s, shapes["plate_force_z_n"][0], shapes["plate_cop_m"][0], shapes["harness_load_n"][0]


def detect_falls(
    config: FallDetectorConfig,
    sample_period_s: float,
    time_s: np.ndarray,
    plate_force_z_n: np.ndarray,
    plate_cop_m: np.ndarray,
    harness_load_n: np.ndarray,
    support_acceleration_z_m_s2: np.ndarray | None = None,
) -> list[FallEvent]:
    """Batch form of `FallMonitor` over a whole log: every detector's events, ordered by detection tick.

    A NaN reading never satisfies a condition (comparisons with NaN are false), as in the streaming form."""
    time_s, fz, cop, load = _as_signals(time_s, plate_force_z_n, plate_cop_m, harness_load_n)
    if support_acceleration_z_m_s2 is not None and np.shape(support_acceleration_z_m_s2) != time_s.shape:
        raise ParameterError(
            "support_acceleration_z_m_s2", np.shape(support_acceleration_z_m_s2), f"shape must be {time_s.shape}"
        )
    events = [
        event
        for detector in _build_detectors(config, sample_period_s)
        for event in detector.detect(time_s, fz, cop, load, support_acceleration_z_m_s2)
    ]
    order = {name: index for index, name in enumerate(DETECTOR_NAMES)}
    return sorted(events, key=lambda event: (event.tick, order[event.detector]))


# --- evaluation against labelled falls ----------------------------------------------------------------


@dataclass(frozen=True)
class MatchingWindow:
    """A detection counts for a fall if it comes between `before_s` before and `after_s` after the onset.

    Detections may precede the labelled onset: the COP reaches the edge of the foot before the COM's
    projection leaves it. Later detections inside the same window are duplicates, not false alarms, and
    so are those up to `post_fall_ignore_s` after the onset; detections anywhere else are false alarms."""

    before_s: float = 1.0
    after_s: float = 2.0
    # After a fall the supervisor has paused and the patient is being set upright again: detections up
    # to this long after the onset are the same fall (rope rebounds), neither hits nor false alarms.
    post_fall_ignore_s: float = 10.0

    def __post_init__(self) -> None:
        require_in_range("window.before_s", self.before_s, 0.0, 60.0)
        require_in_range("window.after_s", self.after_s, 0.0, 60.0, low_open=True)
        require_in_range("window.post_fall_ignore_s", self.post_fall_ignore_s, self.after_s, 600.0)


@dataclass(frozen=True)
class SessionDetections:
    """One session: its length, its labelled fall onsets and the detections to score."""

    name: str
    duration_s: float
    fall_onsets_s: tuple[float, ...]
    events: tuple[FallEvent, ...]


@dataclass(frozen=True)
class DetectorScore:
    detector: str
    falls: int
    detected: int
    false_alarms: int
    duration_h: float
    latencies_s: tuple[float, ...]

    @property
    def sensitivity(self) -> float:
        return self.detected / self.falls if self.falls else math.nan

    @property
    def false_alarms_per_hour(self) -> float:
        return self.false_alarms / self.duration_h if self.duration_h > 0 else math.nan

    def latency_percentile_s(self, percentile: float) -> float:
        return float(np.percentile(self.latencies_s, percentile)) if self.latencies_s else math.nan

    def to_dict(self) -> dict[str, Any]:
        return {
            "detector": self.detector,
            "falls": self.falls,
            "detected": self.detected,
            "sensitivity": self.sensitivity,
            "false_alarms": self.false_alarms,
            "false_alarms_per_hour": self.false_alarms_per_hour,
            "latency_median_s": self.latency_percentile_s(50),
            "latency_p95_s": self.latency_percentile_s(95),
        }


ANY_DETECTOR = "any"  # the monitor as the supervisor sees it: the first event of any detector


def score_detector(
    sessions: list[SessionDetections], detector: str, window: MatchingWindow | None = None
) -> DetectorScore:
    """Latency, sensitivity and false alarms of one detector (or `ANY_DETECTOR`) over sessions."""
    window = window or MatchingWindow()
    falls = detected = false_alarms = 0
    latencies: list[float] = []
    duration_s = 0.0
    for session in sessions:
        duration_s += session.duration_s
        times = np.array(
            sorted(e.detected_s for e in session.events if detector in (ANY_DETECTOR, e.detector)), dtype=float
        )
        onsets = np.asarray(session.fall_onsets_s, dtype=float)
        falls += len(onsets)
        # in_window[i, j]: detection j lies in fall i's window.
        in_window = (times[None, :] >= onsets[:, None] - window.before_s) & (
            times[None, :] <= onsets[:, None] + window.after_s
        )
        after_fall = (times[None, :] >= onsets[:, None]) & (
            times[None, :] <= onsets[:, None] + window.post_fall_ignore_s
        )
        false_alarms += int(np.sum(~np.any(in_window | after_fall, axis=0)))
        caught = np.any(in_window, axis=1)
        detected += int(np.sum(caught))
        if times.size:
            first = np.argmax(in_window, axis=1)  # times are sorted: the earliest detection in the window
            latencies.extend((times[first[caught]] - onsets[caught]).tolist())
    return DetectorScore(detector, falls, detected, false_alarms, duration_s / 3600.0, tuple(latencies))


# --- ROC curves and tuning on labelled logs -------------------------------------------------------------


@dataclass(frozen=True)
class LabelledLog:
    """One session's detector inputs, its configuration and its labelled fall onsets."""

    name: str
    config: FallDetectorConfig
    sample_period_s: float
    time_s: np.ndarray
    plate_force_z_n: np.ndarray
    plate_cop_m: np.ndarray
    harness_load_n: np.ndarray
    support_acceleration_z_m_s2: np.ndarray | None
    fall_onsets_s: tuple[float, ...]

    @property
    def duration_s(self) -> float:
        return float(self.time_s[-1] - self.time_s[0] + self.sample_period_s)


@dataclass(frozen=True)
class RocPoint:
    """One threshold of a detector and how it scores: sensitivity against false alarms per hour."""

    threshold: float
    sensitivity: float
    false_alarms_per_hour: float
    latency_median_s: float

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


# What each detector's ROC sweeps: (section, field) of its configuration; the fused detector sweeps its
# score threshold. A larger COP margin makes that detector more sensitive, as a lower threshold does the others.
ROC_PARAMETERS = {
    HARNESS_LOAD: ("harness", "threshold_fraction_bw"),
    COP_OUTSIDE_BASE: ("cop", "margin_m"),
    FOOT_UNLOADED: ("unload", "threshold_fraction_bw"),
    FUSED: ("fused", "threshold"),
}
ROC_THRESHOLDS = {
    HARNESS_LOAD: tuple(np.round(np.linspace(0.05, 0.6, 12), 3)),
    COP_OUTSIDE_BASE: tuple(np.round(np.linspace(-0.004, 0.03, 12), 4)),
    FOOT_UNLOADED: tuple(np.round(np.linspace(0.01, 0.4, 12), 3)),
    FUSED: tuple(np.round(np.linspace(0.4, 2.6, 23), 2)),
}


def _with(config: FallDetectorConfig, section: str, **values: Any) -> FallDetectorConfig:
    """`config` with only the detector of `section` enabled and `values` set in it."""
    data = config.to_dict()
    for name in ("harness", "cop", "unload", "fused"):
        data[name]["enabled"] = name == section
    data[section].update(values)
    return FallDetectorConfig.from_dict(data)


def _fused_events(log: LabelledLog, scores: np.ndarray, threshold: float, required: int) -> tuple[FallEvent, ...]:
    return tuple(
        FallEvent(FUSED, float(log.time_s[start]), float(log.time_s[tick]), tick, {})
        for start, tick in held_runs(scores >= threshold, required)
    )


def _point(threshold: float, sessions: list[SessionDetections], detector: str, window: MatchingWindow) -> RocPoint:
    score = score_detector(sessions, detector, window)
    return RocPoint(float(threshold), score.sensitivity, score.false_alarms_per_hour, score.latency_percentile_s(50))


def roc_curve(
    logs: list[LabelledLog],
    detector: str,
    thresholds: tuple[float, ...] | None = None,
    window: MatchingWindow | None = None,
) -> list[RocPoint]:
    """Sensitivity and false alarms per hour of one detector at each threshold of its `ROC_PARAMETERS`."""
    if detector not in ROC_PARAMETERS:
        raise ParameterError("detector", detector, f"must be one of {sorted(ROC_PARAMETERS)}")
    window = window or MatchingWindow()
    thresholds = thresholds or ROC_THRESHOLDS[detector]
    section, parameter = ROC_PARAMETERS[detector]
    if detector == FUSED:
        scored = []
        for log in logs:
            fused = FusedDetector(_with(log.config, "fused"), log.sample_period_s)
            scores, _ = fused.scores(
                log.plate_force_z_n, log.plate_cop_m, log.harness_load_n, log.support_acceleration_z_m_s2
            )
            scored.append((log, scores, fused.required_samples))
        return [
            _point(
                threshold,
                [
                    SessionDetections(
                        log.name, log.duration_s, log.fall_onsets_s, _fused_events(log, scores, threshold, required)
                    )
                    for log, scores, required in scored
                ],
                FUSED,
                window,
            )
            for threshold in thresholds
        ]
    points = []
    for threshold in thresholds:
        sessions = []
        for log in logs:
            config = _with(log.config, section, **{parameter: float(threshold)})
            events = detect_falls(
                config, log.sample_period_s, log.time_s, log.plate_force_z_n, log.plate_cop_m, log.harness_load_n
            )
            sessions.append(SessionDetections(log.name, log.duration_s, log.fall_onsets_s, tuple(events)))
        points.append(_point(threshold, sessions, detector, window))
    return points


# The tuning grid of the fused detector: every combination is scored over the training logs at every
# threshold of ROC_THRESHOLDS[FUSED].
TUNING_GRID: dict[str, tuple[float, ...]] = {
    "weight_edge": (0.0, 0.25, 0.5),
    "weight_foot": (0.25, 0.5, 1.0),
    "drop_reference_m": (0.04, 0.07, 0.1),
    "unload_reference_fraction": (0.2, 0.3, 0.4),
}


@dataclass(frozen=True)
class TuningResult:
    settings: dict[str, float]  # the `fused` section to use (threshold included)
    training: RocPoint
    combinations: int


def tune_fused(
    logs: list[LabelledLog],
    *,
    max_false_alarms_per_hour: float = 1.0,
    window: MatchingWindow | None = None,
    grid: dict[str, tuple[float, ...]] | None = None,
    advance: Any = None,
) -> TuningResult:
    """The fused settings with the highest training sensitivity at ≤ `max_false_alarms_per_hour`; ties go to
    fewer false alarms, then to the higher threshold (more margin against alarms on new patients)."""
    require_in_range("max_false_alarms_per_hour", max_false_alarms_per_hour, 0.0, 1000.0)
    grid = grid or TUNING_GRID
    names = sorted(grid)
    best: tuple[tuple[float, float, float], dict[str, float], RocPoint] | None = None
    combinations = 0
    for values in np.array(np.meshgrid(*(grid[name] for name in names))).T.reshape(-1, len(names)):
        settings = {name: float(value) for name, value in zip(names, values, strict=True)}
        tuned = [replace(log, config=_with(log.config, "fused", **settings)) for log in logs]
        points = roc_curve(tuned, FUSED, window=window)
        feasible = [point for point in points if point.false_alarms_per_hour <= max_false_alarms_per_hour]
        combinations += 1
        if advance is not None:
            advance(1)
        if not feasible:
            continue
        top = max((point.sensitivity, -point.false_alarms_per_hour) for point in feasible)
        band = [point for point in feasible if (point.sensitivity, -point.false_alarms_per_hour) == top]
        middle = math.sqrt(band[0].threshold * band[-1].threshold)
        chosen = min(band, key=lambda point: abs(math.log(point.threshold / middle)))
        key = (*top, band[-1].threshold / band[0].threshold)
        if best is None or key > best[0]:
            best = (key, {**settings, "threshold": chosen.threshold}, chosen)
    if best is None:
        raise ParameterError(
            "max_false_alarms_per_hour", max_false_alarms_per_hour, "no setting of the grid stays within it"
        )
    return TuningResult(best[1], best[2], combinations)
