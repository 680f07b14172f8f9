"""One session run's recording, validated, and its flattening into named scalar channels (issue 6 §5).

A `SessionLog` holds the worker's telemetry columns under their telemetry field names (SI units,
arrays of shape (N,) or (N, ...)), the run's events and a JSON-able metadata dict. Every export format
is built from the same scalar channels: `slider_position_m` (N, 12) becomes `slider_position_right_1`
… `slider_position_left_6`, each with its unit, so that CSV, Parquet and C3D all name a channel alike.
"""

from __future__ import annotations

import datetime as dt
import json
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from itertools import product
from typing import Any, Protocol

import numpy as np

from core.errors import InvalidValueError
from server.hal.base import AXIS_COUNT, FEET
from server.realtime.loop import LATE_THRESHOLD_NS

SLIDER_LABELS = tuple(f"{foot}_{slider}" for foot in FEET for slider in range(1, AXIS_COUNT // len(FEET) + 1))
POSE_LABELS = ("x", "y", "z", "roll", "pitch", "yaw")
POSE_UNITS = ("m", "m", "m", "rad", "rad", "rad")
XYZ = ("x", "y", "z")


@dataclass(frozen=True)
class FieldLayout:
    """The component shape of one telemetry field, its label along each axis, and per-component units."""

    shape: tuple[int, ...]
    labels: tuple[tuple[str, ...], ...]
    units: tuple[str, ...] | None = None  # overrides the unit read from the field name, one per component


# The worker's telemetry fields (`TELEMETRY_DTYPE`, server/realtime/telemetry.py) that need names for
# their components; any other field gets numbered components. Per-foot axes are right then left, as
# the HAL's axis order.
TELEMETRY_LAYOUTS: dict[str, FieldLayout] = {
    "tick": FieldLayout((), ()),
    "time_s": FieldLayout((), ()),
    "state": FieldLayout((), ()),
    "cue_specific_force_m_s2": FieldLayout((3,), (XYZ,)),
    "cue_angular_velocity_rad_s": FieldLayout((3,), (XYZ,)),
    "stance_pose": FieldLayout((6,), (POSE_LABELS,), POSE_UNITS),
    "measured_stance_pose": FieldLayout((6,), (POSE_LABELS,), POSE_UNITS),
    "slider_command_m": FieldLayout((AXIS_COUNT,), (SLIDER_LABELS,)),
    "slider_position_m": FieldLayout((AXIS_COUNT,), (SLIDER_LABELS,)),
    "slider_velocity_m_s": FieldLayout((AXIS_COUNT,), (SLIDER_LABELS,)),
    "predicted_force_n": FieldLayout((AXIS_COUNT,), (SLIDER_LABELS,)),
    "drive_force_n": FieldLayout((AXIS_COUNT,), (SLIDER_LABELS,)),
    "drive_state": FieldLayout((AXIS_COUNT,), (SLIDER_LABELS,)),
    "plate_force_z_n": FieldLayout((2,), (FEET,)),
    "plate_cop_m": FieldLayout((2, 2), (FEET, ("x", "y"))),
    "harness_load_n": FieldLayout((), ()),
    "tick_compute_us": FieldLayout((), ()),
    "lateness_us": FieldLayout((), ()),
    "late": FieldLayout((), ()),
    "tick_gap": FieldLayout((), ()),
}

# Issue 6 §5: cues, platform pose, slider positions and forces, plate Fz and COP per foot, harness load.
REQUIRED_COLUMNS = (
    "tick",
    "time_s",
    "cue_specific_force_m_s2",
    "cue_angular_velocity_rad_s",
    "stance_pose",
    "slider_position_m",
    "drive_force_n",
    "plate_force_z_n",
    "plate_cop_m",
    "harness_load_n",
)
REQUIRED_METADATA = ("session_id", "sample_rate_hz")
RESERVED_METADATA = ("recording",)  # written by the exporters into the sidecar
REQUIRED_EVENT_FIELDS = ("kind", "tick", "tick_time_s", "utc")

# Unit suffixes of field names (ARCHITECTURE.md: units in names), longest first so `_m_s2` wins over `_s`.
NAME_SUFFIX_UNITS = (
    ("_m_s2", "m/s^2"),
    ("_rad_s2", "rad/s^2"),
    ("_m_s", "m/s"),
    ("_rad_s", "rad/s"),
    ("_rad", "rad"),
    ("_us", "us"),
    ("_kg", "kg"),
    ("_hz", "Hz"),
    ("_m", "m"),
    ("_n", "N"),
    ("_s", "s"),
)
# Per-sample timing flags the exporters add (docs/exports.md "Time per sample"): a late or skipped tick is
# flagged, never a reason to refuse an export. `late` uses the worker's own threshold.
LATE_THRESHOLD_US = LATE_THRESHOLD_NS / 1000
TIMING_FLAGS = ("late", "tick_gap")


class SessionLogError(InvalidValueError):
    """A session log or export request refused; names the field (column), the value and the limit."""


@dataclass(frozen=True)
class Channel:
    """One scalar channel of the flattened log: `values` has shape (N,)."""

    name: str
    unit: str
    field: str
    values: np.ndarray

    @property
    def header(self) -> str:
        """The CSV header, unit in brackets: `slider_position_right_1 [m]`."""
        return f"{self.name} [{self.unit}]" if self.unit else self.name


def split_unit(field_name: str) -> tuple[str, str]:
    """(`stem`, `unit`) from a field name's unit suffix: `drive_force_n` -> (`drive_force`, `N`)."""
    for suffix, unit in NAME_SUFFIX_UNITS:
        if field_name.endswith(suffix) and len(field_name) > len(suffix):
            return field_name[: -len(suffix)], unit
    return field_name, ""


def field_layout(field_name: str, component_shape: tuple[int, ...]) -> FieldLayout:
    """The known layout of a telemetry field, or numbered components (1, 2, …) for any other field."""
    layout = TELEMETRY_LAYOUTS.get(field_name)
    if layout is not None:
        return layout
    return FieldLayout(component_shape, tuple(tuple(str(i) for i in range(1, n + 1)) for n in component_shape))


def channel_names(field_name: str, component_shape: tuple[int, ...]) -> list[tuple[str, str]]:
    """(name, unit) of each scalar channel of one field, in C (row-major) order of its components."""
    stem, unit = split_unit(field_name)
    layout = field_layout(field_name, component_shape)
    if not layout.labels:
        return [(stem, layout.units[0] if layout.units else unit)]
    names = ["_".join((stem, *labels)) for labels in product(*layout.labels)]
    units = layout.units or (unit,) * len(names)
    return list(zip(names, units, strict=True))


@dataclass
class SessionLog:
    """A session run's telemetry `columns` (field name -> (N,) or (N, ...) array), `events` and `metadata`.

    `metadata` needs `session_id` and `sample_rate_hz`; `server.exports.metadata.session_metadata`
    builds the rest (pseudonymised patient, prescription version, geometry, washout, software version).
    Each event is `{"kind", "tick", "tick_time_s", "utc", "detector"?, "details"?}`.
    """

    columns: dict[str, np.ndarray]
    events: list[dict[str, Any]] = field(default_factory=list)
    metadata: dict[str, Any] = field(default_factory=dict)
    previous_tick: int | None = None  # for one batch of a longer run: the tick of the sample before it

    def __post_init__(self) -> None:
        self.columns = {name: np.asarray(values) for name, values in self.columns.items()}
        self.events = [normalised_event(index, event) for index, event in enumerate(self.events)]
        self.metadata = dict(self.metadata)
        validate_columns(self.columns)
        validate_metadata(self.metadata)
        for name, values in timing_flags(self.columns, self.previous_tick).items():
            self.columns.setdefault(name, values)

    @property
    def sample_count(self) -> int:
        return len(self.columns["time_s"])

    @property
    def head(self) -> SessionLog:
        """A log with every column, to read the layout from (`RecordedLog`): itself."""
        return self

    @property
    def first_tick(self) -> int:
        return int(self.columns["tick"][0])

    @property
    def duration_s(self) -> float:
        return float(self.columns["time_s"][-1] - self.columns["time_s"][0])

    def batches(self) -> Iterator[SessionLog]:
        """The telemetry in batches (`RecordedLog`): one, itself."""
        yield self

    def column_batches(self, name: str) -> Iterator[np.ndarray]:
        """One field's values in batches (`RecordedLog`): one, the column."""
        yield self.columns[name]

    def whole(self) -> SessionLog:
        return self

    @property
    def sample_rate_hz(self) -> float:
        return float(self.metadata["sample_rate_hz"])

    @property
    def session_id(self) -> str:
        return str(self.metadata["session_id"])

    @classmethod
    def from_telemetry(
        cls, telemetry: np.ndarray, events: list[dict[str, Any]], metadata: dict[str, Any]
    ) -> SessionLog:
        """A log from the worker's drained telemetry records (`TELEMETRY_DTYPE`): one column per field."""
        if telemetry.dtype.names is None:
            raise SessionLogError("telemetry", str(telemetry.dtype), "a structured array (TELEMETRY_DTYPE)")
        return cls(columns={name: telemetry[name] for name in telemetry.dtype.names}, events=events, metadata=metadata)

    def field_order(self) -> list[str]:
        """Time first, then the fields in the order of the columns (the telemetry dtype's order)."""
        return ["time_s", *(name for name in self.columns if name != "time_s")]

    def channel_units(self) -> dict[str, dict[str, str]]:
        """Every scalar channel's unit and source field, in export order (no data copied)."""
        return {
            name: {"unit": unit, "field": field_name}
            for field_name in self.field_order()
            for name, unit in channel_names(field_name, self.columns[field_name].shape[1:])
        }

    def channels(self) -> Iterator[Channel]:
        """Every scalar channel with its values, in export order."""
        for field_name in self.field_order():
            values = self.columns[field_name]
            flat = values.reshape(len(values), -1)
            for index, (name, unit) in enumerate(channel_names(field_name, values.shape[1:])):
                yield Channel(name, unit, field_name, np.ascontiguousarray(flat[:, index]))


class RecordedLog(Protocol):
    """What the exporters write from: a `SessionLog` in memory, or a run read in batches
    (`server.exports.stream.LogStream`) so that no export holds a whole run."""

    metadata: dict[str, Any]
    events: list[dict[str, Any]]

    @property
    def head(self) -> SessionLog: ...
    @property
    def session_id(self) -> str: ...
    @property
    def sample_rate_hz(self) -> float: ...
    @property
    def sample_count(self) -> int: ...
    @property
    def first_tick(self) -> int: ...
    @property
    def duration_s(self) -> float: ...
    def batches(self) -> Iterator[SessionLog]: ...
    def column_batches(self, name: str) -> Iterator[np.ndarray]: ...
    def whole(self) -> SessionLog: ...


def validate_columns(columns: Mapping[str, np.ndarray]) -> None:
    """Refuse a log whose columns are missing, of unequal length, misshapen or not numbers, naming the column."""
    for name in REQUIRED_COLUMNS:
        if name not in columns:
            raise SessionLogError(name, None, f"required column missing (required: {', '.join(REQUIRED_COLUMNS)})")
    sample_count = len(columns["time_s"]) if columns["time_s"].ndim else 0
    if sample_count == 0:
        raise SessionLogError("time_s", columns["time_s"].shape, "at least one sample")
    for name, values in columns.items():
        if values.ndim == 0 or len(values) != sample_count:
            length = len(values) if values.ndim else "scalar"
            raise SessionLogError(name, length, f"must have {sample_count} samples, like time_s")
        layout = TELEMETRY_LAYOUTS.get(name)
        if layout is not None and values.shape[1:] != layout.shape:
            raise SessionLogError(name, list(values.shape[1:]), f"components per sample must be {list(layout.shape)}")
        numeric = np.issubdtype(values.dtype, np.number) or values.dtype == np.bool_
        text = values.dtype.kind in "US" and values.ndim == 1
        if not (numeric or text):
            raise SessionLogError(name, str(values.dtype), "numbers (or text for a one-component column)")
    _validate_clock(columns["time_s"], columns["tick"])


def _validate_clock(time_s: np.ndarray, tick: np.ndarray) -> None:
    if not np.issubdtype(time_s.dtype, np.floating) or not np.all(np.isfinite(time_s)):
        raise SessionLogError("time_s", str(time_s.dtype), "finite floating-point seconds")
    if not np.issubdtype(tick.dtype, np.integer):
        raise SessionLogError("tick", str(tick.dtype), "integer tick numbers")
    for name, values in (("time_s", time_s), ("tick", tick)):
        steps = np.diff(values)
        if np.any(steps <= 0):
            index = int(np.argmax(steps <= 0)) + 1
            raise SessionLogError(f"{name}[{index}]", values[index].item(), f"must exceed {values[index - 1].item()}")


def timing_flags(columns: Mapping[str, np.ndarray], previous_tick: int | None = None) -> dict[str, np.ndarray]:
    """Per sample: `tick_gap`, the control periods missing just before it (deadlines the loop skipped plus
    tick numbers missing from the recording; 0 on time), and `late` (1 where the tick started more than the
    worker's 500 µs after its deadline; only when the log has `lateness_us`)."""
    tick = columns["tick"].astype(np.int64)
    first = tick[0] - 1 if previous_tick is None else previous_tick
    gap = np.diff(tick, prepend=first) - 1
    skipped = columns.get("skipped_ticks")
    if skipped is not None:
        gap = gap + skipped.astype(np.int64)
    flags = {"tick_gap": gap.astype(np.uint32)}
    lateness = columns.get("lateness_us")
    if lateness is not None:
        flags["late"] = (np.asarray(lateness) > LATE_THRESHOLD_US).astype(np.uint8)
    return flags


def validate_metadata(metadata: Mapping[str, Any]) -> None:
    """Refuse metadata without a session id or a sample rate. The rate is the nominal control rate, whatever
    the tick stamps say: late and skipped ticks are flagged per sample (`timing_flags`), never refused."""
    for key in REQUIRED_METADATA:
        if key not in metadata:
            raise SessionLogError(f"metadata.{key}", None, "required")
    for key in RESERVED_METADATA:
        if key in metadata:
            raise SessionLogError(f"metadata.{key}", "<present>", "reserved for the exporters")
    rate = metadata["sample_rate_hz"]
    if isinstance(rate, bool) or not isinstance(rate, int | float) or not math.isfinite(rate) or rate <= 0:
        raise SessionLogError("metadata.sample_rate_hz", rate, "a finite number > 0")
    try:
        json.dumps(metadata, default=json_default, allow_nan=False)
    except (TypeError, ValueError) as error:
        raise SessionLogError("metadata", type(metadata).__name__, f"must be JSON-serialisable: {error}") from error


def normalised_event(index: int, event: Mapping[str, Any]) -> dict[str, Any]:
    """An event with its required fields checked and its UTC time as ISO 8601 text."""
    prefix = f"events[{index}]"
    if not isinstance(event, Mapping):
        raise SessionLogError(prefix, type(event).__name__, "a dict")
    for key in REQUIRED_EVENT_FIELDS:
        if key not in event:
            raise SessionLogError(
                f"{prefix}.{key}", None, f"required (event fields: {', '.join(REQUIRED_EVENT_FIELDS)})"
            )
    kind, tick, tick_time_s, utc = (event[key] for key in REQUIRED_EVENT_FIELDS)
    if not isinstance(kind, str) or not kind:
        raise SessionLogError(f"{prefix}.kind", kind, "a non-empty string")
    if isinstance(tick, bool) or not isinstance(tick, int | np.integer):
        raise SessionLogError(f"{prefix}.tick", tick, "an integer tick number")
    if isinstance(tick_time_s, bool) or not isinstance(tick_time_s, int | float) or not math.isfinite(tick_time_s):
        raise SessionLogError(f"{prefix}.tick_time_s", tick_time_s, "finite seconds")
    if isinstance(utc, dt.datetime):
        utc = utc.isoformat()
    if not isinstance(utc, str):
        raise SessionLogError(f"{prefix}.utc", utc, "ISO 8601 text or a datetime")
    detector = event.get("detector")
    if detector is not None and not isinstance(detector, str):
        raise SessionLogError(f"{prefix}.detector", detector, "a string or absent")
    details = event.get("details") or {}
    if not isinstance(details, Mapping):
        raise SessionLogError(f"{prefix}.details", details, "a dict or absent")
    try:
        to_json(details)
    except (TypeError, ValueError) as error:
        raise SessionLogError(f"{prefix}.details", details, f"must be JSON-serialisable: {error}") from error
    return {
        "kind": kind,
        "tick": int(tick),
        "tick_time_s": float(tick_time_s),
        "utc": utc,
        "detector": detector,
        "details": dict(details),
    }


def json_default(value: Any) -> Any:
    """`json.dumps(default=...)` for numpy scalars/arrays and dates found in metadata and event details."""
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    if isinstance(value, dt.date | dt.datetime):
        return value.isoformat()
    raise TypeError(f"{type(value).__name__} is not JSON-serialisable")


def to_json(value: Any, *, indent: int | None = None) -> str:
    """Strict JSON (no NaN tokens, which standard parsers refuse) for metadata and events."""
    return json.dumps(value, default=json_default, allow_nan=False, indent=indent, ensure_ascii=False)
