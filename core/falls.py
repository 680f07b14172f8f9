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
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np

from core.patient import GRAVITY_M_S2, FootGeometry, ParameterError, require_in_range

HARNESS_LOAD = "harness_load"
COP_OUTSIDE_BASE = "cop_outside_base"
FOOT_UNLOADED = "foot_unloaded"
DETECTOR_NAMES = (HARNESS_LOAD, COP_OUTSIDE_BASE, FOOT_UNLOADED)
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
class FallDetectorConfig:
    """All three detectors for one patient (body weight scales the thresholds)."""

    body_mass_kg: float
    harness: HarnessLoadConfig = field(default_factory=HarnessLoadConfig)
    cop: CopOutsideBaseConfig = field(default_factory=CopOutsideBaseConfig)
    unload: FootUnloadedConfig = field(default_factory=FootUnloadedConfig)

    def __post_init__(self) -> None:
        require_in_range("body_mass_kg", self.body_mass_kg, 20.0, 250.0)

    @classmethod
    def for_patient(cls, body_mass_kg: float, height_m: float) -> FallDetectorConfig:
        """Defaults with the footprint sized from the patient's height (Winter's foot proportions)."""
        require_in_range("height_m", height_m, 1.0, 2.3)
        return cls(body_mass_kg=body_mass_kg, cop=CopOutsideBaseConfig.for_foot(FootGeometry.from_height(height_m)))

    @property
    def body_weight_n(self) -> float:
        return self.body_mass_kg * GRAVITY_M_S2

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FallDetectorConfig:
        sections = {"harness": HarnessLoadConfig, "cop": CopOutsideBaseConfig, "unload": FootUnloadedConfig}
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

    def update(self, tick: int, time_s: float, fz: np.ndarray, cop: np.ndarray, load: float) -> FallEvent | None:
        if not self.condition(fz, cop, load):
            self.run_length = 0
            return None
        if self.run_length == 0:
            self.run_onset_s = time_s
        self.run_length += 1
        if self.run_length != self.required_samples:
            return None
        return FallEvent(self.name, self.run_onset_s, time_s, tick, self.values(fz, cop, load))

    def detect(self, time_s: np.ndarray, fz: np.ndarray, cop: np.ndarray, load: np.ndarray) -> list[FallEvent]:
        """Batch: the runs of the condition at least `required_samples` long, vectorised."""
        held = self.conditions(fz, cop, load).astype(np.int8)
        edges = np.diff(np.concatenate([[0], held, [0]]))
        starts = np.flatnonzero(edges == 1)
        ends = np.flatnonzero(edges == -1)
        long_enough = (ends - starts) >= self.required_samples
        ticks = starts[long_enough] + self.required_samples - 1
        return [
            FallEvent(
                self.name,
                float(time_s[start]),
                float(time_s[tick]),
                int(tick),
                self.values(fz[tick], cop[tick], load[tick]),
            )
            for start, tick in zip(starts[long_enough], ticks, strict=True)
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


def _build_detectors(config: FallDetectorConfig, sample_period_s: float) -> list[_Detector]:
    require_in_range("sample_period_s", sample_period_s, 0.0, 1.0, low_open=True)
    detectors: list[_Detector] = []
    if config.harness.enabled:
        detectors.append(HarnessLoadDetector(config, sample_period_s))
    if config.cop.enabled:
        detectors.append(CopOutsideBaseDetector(config, sample_period_s))
    if config.unload.enabled:
        detectors.append(FootUnloadedDetector(config, sample_period_s))
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
        self, time_s: float, plate_force_z_n: np.ndarray, plate_cop_m: np.ndarray, harness_load_n: float
    ) -> tuple[FallEvent, ...]:
        fired: tuple[FallEvent, ...] = _NO_EVENTS
        for detector in self.detectors:
            event = detector.update(self.tick, time_s, plate_force_z_n, plate_cop_m, harness_load_n)
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
) -> list[FallEvent]:
    """Batch form of `FallMonitor` over a whole log: every detector's events, ordered by detection tick.

    A NaN reading never satisfies a condition (comparisons with NaN are false), as in the streaming form."""
    time_s, fz, cop, load = _as_signals(time_s, plate_force_z_n, plate_cop_m, harness_load_n)
    events = [
        event
        for detector in _build_detectors(config, sample_period_s)
        for event in detector.detect(time_s, fz, cop, load)
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
