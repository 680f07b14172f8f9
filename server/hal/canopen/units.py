"""Drive configuration and the counts ↔ metres scaling of the twelve slider axes.

A drive type names its EDS file and its scaling (encoder counts per mm, rated force for 0x6077),
homing method (0x6098) and ramps; each axis maps a HAL axis (REFERENCE.md order) to a CANopen node.
The file speaks mm, like drive datasheets; everything returned here is SI. Along axis i:

    position_m = home_position_m[i] + direction[i] · counts / counts_per_m[i]

so counts are zero at the home switch and grow outwards. Invalid files are refused with a
`DriveConfigurationError` naming the field, the value and the limit, before any bus traffic.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import InvalidValueError
from core.kinematics import ForwardKinematicsError, forward_kinematics
from core.robot import TwinRobot
from server.hal.base import AXIS_COUNT, HalError, HardwareInterface

DEFAULT_CONFIGURATION_PATH = Path(__file__).with_name("drives.toml")
INT32_MAX = 2**31 - 1


class DriveConfigurationError(InvalidValueError, HalError):
    """A drive configuration, EDS or drive answer that forbids motion; names field, value and limit."""


@dataclass(frozen=True)
class DriveType:
    name: str
    eds_path: Path
    counts_per_mm: float
    rated_force_n: float
    homing_method: int
    homing_switch_speed_mm_s: float
    homing_zero_speed_mm_s: float
    homing_acceleration_mm_s2: float
    quick_stop_deceleration_mm_s2: float
    following_error_window_mm: float
    following_error_timeout_ms: int

    @property
    def counts_per_m(self) -> float:
        return self.counts_per_mm * 1e3

    def counts(self, length_mm: float) -> int:
        """A length, speed or acceleration in mm(/s, /s²) as drive units (counts, counts/s, counts/s²)."""
        return round(length_mm * self.counts_per_mm)


@dataclass(frozen=True)
class AxisDrive:
    node_id: int
    drive_type: DriveType
    home_position_m: float
    direction: int


@dataclass(frozen=True)
class DriveConfiguration:
    master_node_id: int
    heartbeat_period_ms: int
    heartbeat_timeout_ms: int
    axes: tuple[AxisDrive, ...]

    @property
    def node_ids(self) -> list[int]:
        return [axis.node_id for axis in self.axes]

    def with_homing_method(self, method: int) -> DriveConfiguration:
        """The same configuration with every drive type homing by `method` (a CLI override)."""
        if not -128 <= method <= 127:
            raise DriveConfigurationError("homing_method", method, "0x6098 is an INTEGER8: [-128, 127]")
        types = {a.drive_type.name: a.drive_type for a in self.axes}
        replaced = {name: replace(t, homing_method=method) for name, t in types.items()}
        axes = tuple(
            AxisDrive(a.node_id, replaced[a.drive_type.name], a.home_position_m, a.direction) for a in self.axes
        )
        return DriveConfiguration(self.master_node_id, self.heartbeat_period_ms, self.heartbeat_timeout_ms, axes)


def _positive(field_name: str, value: Any) -> float:
    if not isinstance(value, int | float) or isinstance(value, bool) or not math.isfinite(value) or value <= 0:
        raise DriveConfigurationError(field_name, value, "must be a finite number > 0")
    return float(value)


def _integer(field_name: str, value: Any, low: int, high: int) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
        raise DriveConfigurationError(field_name, value, f"must be an integer in [{low}, {high}]")
    return value


def _drive_type(name: str, data: Mapping[str, Any], base_directory: Path) -> DriveType:
    section = f"drive_types.{name}"
    known = {
        "eds",
        "counts_per_mm",
        "rated_force_n",
        "homing_method",
        "homing_switch_speed_mm_s",
        "homing_zero_speed_mm_s",
        "homing_acceleration_mm_s2",
        "quick_stop_deceleration_mm_s2",
        "following_error_window_mm",
        "following_error_timeout_ms",
    }
    unknown = sorted(set(data) - known)
    if unknown:
        raise DriveConfigurationError(f"{section}.{unknown[0]}", data[unknown[0]], "unknown field")
    missing = sorted(known - set(data))
    if missing:
        raise DriveConfigurationError(f"{section}.{missing[0]}", None, "required field is missing")
    eds_path = (base_directory / str(data["eds"])).resolve()
    if not eds_path.is_file():
        raise DriveConfigurationError(f"{section}.eds", str(data["eds"]), f"no EDS/DCF file at {eds_path}")
    return DriveType(
        name=name,
        eds_path=eds_path,
        counts_per_mm=_positive(f"{section}.counts_per_mm", data["counts_per_mm"]),
        rated_force_n=_positive(f"{section}.rated_force_n", data["rated_force_n"]),
        homing_method=_integer(f"{section}.homing_method", data["homing_method"], -128, 127),
        homing_switch_speed_mm_s=_positive(f"{section}.homing_switch_speed_mm_s", data["homing_switch_speed_mm_s"]),
        homing_zero_speed_mm_s=_positive(f"{section}.homing_zero_speed_mm_s", data["homing_zero_speed_mm_s"]),
        homing_acceleration_mm_s2=_positive(f"{section}.homing_acceleration_mm_s2", data["homing_acceleration_mm_s2"]),
        quick_stop_deceleration_mm_s2=_positive(
            f"{section}.quick_stop_deceleration_mm_s2", data["quick_stop_deceleration_mm_s2"]
        ),
        following_error_window_mm=_positive(f"{section}.following_error_window_mm", data["following_error_window_mm"]),
        following_error_timeout_ms=_integer(
            f"{section}.following_error_timeout_ms", data["following_error_timeout_ms"], 0, 65535
        ),
    )


def drive_configuration_from_dict(data: Mapping[str, Any], base_directory: Path) -> DriveConfiguration:
    """Validate a parsed drive configuration; EDS paths are relative to `base_directory`."""
    master_node_id = _integer("master_node_id", data.get("master_node_id"), 1, 127)
    heartbeat_period_ms = _integer("heartbeat_period_ms", data.get("heartbeat_period_ms"), 1, 65535)
    heartbeat_timeout_ms = _integer("heartbeat_timeout_ms", data.get("heartbeat_timeout_ms"), 1, 65535)
    if heartbeat_timeout_ms < 2 * heartbeat_period_ms:
        raise DriveConfigurationError(
            "heartbeat_timeout_ms",
            heartbeat_timeout_ms,
            f"must be ≥ 2 × heartbeat_period_ms = {2 * heartbeat_period_ms}",
        )
    types = {name: _drive_type(name, section, base_directory) for name, section in data.get("drive_types", {}).items()}
    axes_data = data.get("axes", [])
    if len(axes_data) != AXIS_COUNT:
        raise DriveConfigurationError("axes", len(axes_data), f"exactly {AXIS_COUNT} axes (right 1–6, left 1–6)")
    axes = []
    for number, axis in enumerate(axes_data):
        name = f"axes[{number}] ({HardwareInterface.axis_name(number)})"
        node_id = _integer(f"{name}.node_id", axis.get("node_id"), 1, 127)
        if node_id == master_node_id:
            raise DriveConfigurationError(
                f"{name}.node_id", node_id, f"must differ from master_node_id {master_node_id}"
            )
        if axis.get("drive_type") not in types:
            raise DriveConfigurationError(f"{name}.drive_type", axis.get("drive_type"), f"one of {sorted(types)}")
        direction = axis.get("direction")
        if direction not in (1, -1) or isinstance(direction, bool):
            raise DriveConfigurationError(f"{name}.direction", direction, "must be 1 or -1")
        home_mm = axis.get("home_position_mm")
        if not isinstance(home_mm, int | float) or isinstance(home_mm, bool) or not math.isfinite(home_mm):
            raise DriveConfigurationError(f"{name}.home_position_mm", home_mm, "must be a finite number")
        axes.append(AxisDrive(node_id, types[axis["drive_type"]], home_mm / 1e3, direction))
    node_ids = [a.node_id for a in axes]
    duplicates = sorted({n for n in node_ids if node_ids.count(n) > 1})
    if duplicates:
        raise DriveConfigurationError("axes.node_id", duplicates[0], "node ids must be unique")
    return DriveConfiguration(master_node_id, heartbeat_period_ms, heartbeat_timeout_ms, tuple(axes))


def load_drive_configuration(path: str | Path | None = None) -> DriveConfiguration:
    """Load and validate a drive configuration TOML file (default: the shipped `drives.toml`)."""
    path = Path(path) if path is not None else DEFAULT_CONFIGURATION_PATH
    try:
        with open(path, "rb") as handle:
            data = tomllib.load(handle)
    except (OSError, tomllib.TOMLDecodeError) as error:
        raise DriveConfigurationError(str(path), "<file>", f"not a readable TOML file: {error}") from error
    return drive_configuration_from_dict(data, path.parent)


class AxisScaling:
    """Vectorised counts ↔ SI conversion for the twelve axes; per-tick methods write into `out`."""

    def __init__(self, configuration: DriveConfiguration, twin: TwinRobot) -> None:
        axes = configuration.axes
        self.home_position_m = np.array([a.home_position_m for a in axes])
        self.direction = np.array([float(a.direction) for a in axes])
        self.counts_per_m = np.array([a.drive_type.counts_per_m for a in axes])
        self.rated_force_n = np.array([a.drive_type.rated_force_n for a in axes])
        self._m_per_count = self.direction / self.counts_per_m
        self._check_against_twin(twin)

    def _check_against_twin(self, twin: TwinRobot) -> None:
        robots = [twin.robot_for(side) for side in ("right", "left")]
        stroke_min = np.concatenate([r.stroke_min_m for r in robots])
        stroke_max = np.concatenate([r.stroke_max_m for r in robots])
        for axis in range(AXIS_COUNT):
            name = f"axes[{axis}] ({HardwareInterface.axis_name(axis)}).home_position_mm"
            home = self.home_position_m[axis]
            if not stroke_min[axis] <= home <= stroke_max[axis]:
                raise DriveConfigurationError(
                    name,
                    home * 1e3,
                    f"must lie in the stroke [{stroke_min[axis] * 1e3:.1f}, {stroke_max[axis] * 1e3:.1f}] mm",
                )
            far_counts = max(abs(stroke_min[axis] - home), abs(stroke_max[axis] - home)) * self.counts_per_m[axis]
            if far_counts > INT32_MAX:
                raise DriveConfigurationError(
                    f"axes[{axis}].drive_type.counts_per_mm",
                    self.counts_per_m[axis] / 1e3,
                    f"the stroke spans {far_counts:.0f} counts, beyond 0x607A's INTEGER32 range",
                )
        # A closed chain: the six sliders of a robot can only stand where one platform pose puts them.
        for index, (side, robot) in enumerate(zip(("right", "left"), robots, strict=True)):
            homes = self.home_position_m[6 * index : 6 * index + 6]
            try:
                forward_kinematics(robot, homes[None, :])
            except ForwardKinematicsError as error:
                raise DriveConfigurationError(
                    f"axes[{6 * index}..{6 * index + 5}] ({side} robot).home_position_mm",
                    [round(float(h) * 1e3, 3) for h in homes],
                    f"must be the sliders of one platform pose: {error}",
                ) from None

    def counts_from_positions(self, positions_m: np.ndarray, out: np.ndarray) -> None:
        np.rint((positions_m - self.home_position_m) / self._m_per_count, out=out, casting="unsafe")

    def positions_from_counts(self, counts: np.ndarray, out: np.ndarray) -> None:
        np.multiply(counts, self._m_per_count, out=out)
        out += self.home_position_m

    def velocities_from_counts(self, counts_per_s: np.ndarray, out: np.ndarray) -> None:
        np.multiply(counts_per_s, self._m_per_count, out=out)

    def forces_from_torque(self, torque_per_mille: np.ndarray, out: np.ndarray) -> None:
        """0x6077 is per mille of the rated force, positive in the count direction."""
        np.multiply(torque_per_mille, self.rated_force_n * self.direction / 1000.0, out=out)
