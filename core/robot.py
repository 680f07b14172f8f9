"""Robot description: one 6-SSP robot and the mirrored twin (paper §2.2 and §3.1.2).

The default geometry is the one identified in REFERENCE.md §1; it reproduces every slider position
the paper publishes. Everything is SI (m, rad, kg). A description is validated on construction and
refused with a `DescriptionError` that names the field, the value and the limit.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from core.errors import InvalidValueError
from core.rotations import rotation_matrix

SLIDER_COUNT = 6


class DescriptionError(InvalidValueError):
    """An invalid robot description; names the field, the value and the limit it broke."""


def _require_finite(field_name: str, values: Iterable[float] | float) -> None:
    try:
        array = np.atleast_1d(np.asarray(values, dtype=float))
    except (TypeError, ValueError) as error:
        raise DescriptionError(field_name, values, "must be a number (or a list of numbers)") from error
    if not np.all(np.isfinite(array)):
        raise DescriptionError(field_name, np.asarray(values).tolist(), "must be a finite number (no NaN/inf)")


def _require_positive(field_name: str, value: float) -> None:
    _require_finite(field_name, value)
    if value <= 0.0:
        raise DescriptionError(field_name, value, "must be > 0")


@dataclass(frozen=True)
class Slider:
    """One slider: its rail, the side of the rail centre it travels on, and its rod's platform joint."""

    rail_y_m: float
    side: int  # +1: slider on the +X half of its rail, -1: on the -X half
    platform_joint_m: tuple[float, float, float]  # B_i in the platform frame
    stroke_m: tuple[float, float]  # allowed slider x along the rail, base frame (min, max)


@dataclass(frozen=True)
class MotionLimits:
    """Limits the safety supervisor enforces; the paper gives none, these are documented defaults."""

    slider_velocity_max_m_s: float = 1.5
    slider_acceleration_max_m_s2: float = 20.0
    drive_force_max_n: float = 4000.0
    tilt_max_rad: float = math.radians(25.0)
    # Half-angle of each spherical joint's cone around the rod direction at the neutral pose.
    base_joint_cone_rad: float = math.radians(40.0)
    platform_joint_cone_rad: float = math.radians(40.0)
    # Largest allowed condition number of the (dimensionless) twist Jacobian: keeps every pose away
    # from the singularities that lie inside the stroke and cone limits (docs/kinematics.md).
    condition_number_max: float = 40.0


@dataclass(frozen=True)
class MassProperties:
    """Masses of one robot's moving parts. The paper gives none: these are stated assumptions."""

    platform_mass_kg: float = 45.0
    platform_inertia_kg_m2: tuple[float, float, float] = (2.2, 2.2, 4.3)  # principal, about its centre
    platform_com_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # platform frame
    slider_mass_kg: float = 8.0
    rod_mass_kg: float = 4.0  # uniform slender rod, spherical joint to spherical joint
    rated_payload_kg: float = 250.0  # paper §3.3.1: static rated load at the platform centre


@dataclass(frozen=True)
class SSPRobot:
    """One 6-SSP robot in its own base frame: X along the rails, Z up, rails in the plane z = rail_z_m."""

    sliders: tuple[Slider, ...]
    rod_length_m: float = 1.0
    rail_z_m: float = 0.0
    neutral_pose: tuple[float, float, float, float, float, float] = (0.0, 0.0, 0.6, 0.0, 0.0, 0.0)
    limits: MotionLimits = field(default_factory=MotionLimits)
    mass: MassProperties = field(default_factory=MassProperties)

    def __post_init__(self) -> None:
        self._validate()

    # Arrays used by the vectorised kinematics; cheap to build, so derived rather than stored.
    @property
    def rail_y_m(self) -> np.ndarray:
        return np.array([s.rail_y_m for s in self.sliders])

    @property
    def sides(self) -> np.ndarray:
        return np.array([float(s.side) for s in self.sliders])

    @property
    def platform_joints_m(self) -> np.ndarray:
        return np.array([s.platform_joint_m for s in self.sliders])

    @property
    def stroke_min_m(self) -> np.ndarray:
        return np.array([s.stroke_m[0] for s in self.sliders])

    @property
    def stroke_max_m(self) -> np.ndarray:
        return np.array([s.stroke_m[1] for s in self.sliders])

    @property
    def platform_radius_m(self) -> float:
        """Largest joint distance from the platform centre: the length scale for mixed m/rad quantities."""
        return float(np.max(np.linalg.norm(self.platform_joints_m, axis=1)))

    def _validate(self) -> None:
        if len(self.sliders) != SLIDER_COUNT:
            raise DescriptionError("sliders", len(self.sliders), f"exactly {SLIDER_COUNT} sliders/joints")
        _require_positive("rod_length_m", self.rod_length_m)
        _require_finite("rail_z_m", self.rail_z_m)
        _require_finite("neutral_pose", self.neutral_pose)
        if len(self.neutral_pose) != 6:
            raise DescriptionError("neutral_pose", list(self.neutral_pose), "6 values (x, y, z, roll, pitch, yaw)")
        for name, value in asdict(self.limits).items():
            _require_positive(f"limits.{name}", value)
        for name, value in asdict(self.mass).items():
            _require_finite(f"mass.{name}", value)
            if np.any(np.asarray(value, dtype=float) < 0.0):
                raise DescriptionError(f"mass.{name}", value, "must be >= 0")
        for index, slider in enumerate(self.sliders, start=1):
            prefix = f"sliders[{index}]"
            _require_finite(f"{prefix}.rail_y_m", slider.rail_y_m)
            _require_finite(f"{prefix}.platform_joint_m", slider.platform_joint_m)
            _require_finite(f"{prefix}.stroke_m", slider.stroke_m)
            if len(slider.platform_joint_m) != 3:
                raise DescriptionError(f"{prefix}.platform_joint_m", slider.platform_joint_m, "3 coordinates")
            if slider.side not in (-1, 1):
                raise DescriptionError(f"{prefix}.side", slider.side, "must be +1 or -1")
            low, high = slider.stroke_m
            if not low < high:
                raise DescriptionError(f"{prefix}.stroke_m", list(slider.stroke_m), "min must be < max")
        self._validate_neutral_reach()

    def _validate_neutral_reach(self) -> None:
        x, y, z = self.neutral_pose[:3]
        rotation = rotation_matrix(*self.neutral_pose[3:])
        for index, slider in enumerate(self.sliders, start=1):
            joint = np.array([x, y, z]) + rotation @ np.asarray(slider.platform_joint_m)
            reach_sq = self.rod_length_m**2 - (joint[1] - slider.rail_y_m) ** 2 - (joint[2] - self.rail_z_m) ** 2
            if reach_sq < 0.0:
                distance = math.hypot(joint[1] - slider.rail_y_m, joint[2] - self.rail_z_m)
                raise DescriptionError(
                    f"sliders[{index}].platform_joint_m",
                    list(slider.platform_joint_m),
                    f"rod cannot reach its rail at the neutral pose: joint is {distance:.4f} m from the rail, "
                    f"rod_length_m is {self.rod_length_m}",
                )
            slider_x = joint[0] + slider.side * math.sqrt(reach_sq)
            low, high = slider.stroke_m
            if not low <= slider_x <= high:
                raise DescriptionError(
                    f"sliders[{index}].stroke_m",
                    list(slider.stroke_m),
                    f"neutral slider position {slider_x:.4f} m lies outside the stroke",
                )

    def mirrored(self) -> SSPRobot:
        """The mirror image about the base XZ plane (y -> -y): the other foot's robot (paper §2.2)."""
        sliders = tuple(
            replace(
                s,
                rail_y_m=-s.rail_y_m,
                platform_joint_m=(s.platform_joint_m[0], -s.platform_joint_m[1], s.platform_joint_m[2]),
            )
            for s in self.sliders
        )
        x, y, z, roll, pitch, yaw = self.neutral_pose
        return replace(self, sliders=sliders, neutral_pose=(x, -y, z, -roll, pitch, -yaw))


def _paper_sliders() -> tuple[Slider, ...]:
    """REFERENCE.md §1: joint pairs at the corners of a 775 mm equilateral triangle, split 75 mm apart."""
    circumradius_m = 0.775 / math.sqrt(3.0)
    half_split_m = 0.075
    stroke_inner_m, stroke_outer_m = 0.15, 1.85

    def corner_pair(angle_deg: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        angle = math.radians(angle_deg)
        cx, cy = circumradius_m * math.cos(angle), circumradius_m * math.sin(angle)
        tx, ty = -math.sin(angle), math.cos(angle)  # tangent, at right angles to the radius
        return (
            (cx - half_split_m * tx, cy - half_split_m * ty, 0.0),
            (cx + half_split_m * tx, cy + half_split_m * ty, 0.0),
        )

    bottom = corner_pair(270.0)  # joints 1 and 6
    right = corner_pair(30.0)  # joints 2 and 3
    left = corner_pair(150.0)  # joints 4 and 5
    plus_x = (stroke_inner_m, stroke_outer_m)
    minus_x = (-stroke_outer_m, -stroke_inner_m)
    return (
        Slider(rail_y_m=-0.8, side=1, platform_joint_m=bottom[1], stroke_m=plus_x),
        Slider(rail_y_m=0.0, side=1, platform_joint_m=right[0], stroke_m=plus_x),
        Slider(rail_y_m=0.8, side=1, platform_joint_m=right[1], stroke_m=plus_x),
        Slider(rail_y_m=0.8, side=-1, platform_joint_m=left[0], stroke_m=minus_x),
        Slider(rail_y_m=0.0, side=-1, platform_joint_m=left[1], stroke_m=minus_x),
        Slider(rail_y_m=-0.8, side=-1, platform_joint_m=bottom[0], stroke_m=minus_x),
    )


def paper_robot() -> SSPRobot:
    """The robot of the paper (§3.1.2): rails 800 mm apart, 1000 mm rods, neutral height 600 mm."""
    return SSPRobot(sliders=_paper_sliders())


# --- The twin: one robot under each foot ------------------------------------------------------------


@dataclass(frozen=True)
class RobotPlacement:
    """Where one robot's base frame stands in the world, and where the foot plate sits on its platform."""

    base_origin_m: tuple[float, float, float]
    base_yaw_rad: float = 0.0
    mirrored: bool = False
    foot_plate_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # platform frame


@dataclass(frozen=True)
class PartDimensions:
    """Sizes of the physical parts for the clearance check (core.clearance). The paper gives none: these
    are stated assumptions. Every part is a capsule (a segment swept by a sphere)."""

    rod_diameter_m: float = 0.04
    rail_diameter_m: float = 0.05
    rail_overhang_m: float = 0.10  # rail length beyond the outermost stroke end
    slider_length_m: float = 0.15  # along its rail, centred on the slider joint
    slider_diameter_m: float = 0.08
    platform_thickness_m: float = 0.04  # the platform as its joint hexagon's edges, this thick
    foot_plate_length_m: float = 0.30  # along the platform's X axis
    foot_plate_width_m: float = 0.12
    foot_plate_thickness_m: float = 0.03
    clearance_min_m: float = 0.005  # closer than this is a collision

    def validate(self, prefix: str = "twin.parts") -> None:
        for name, value in asdict(self).items():
            _require_positive(f"{prefix}.{name}", value)
        if self.foot_plate_width_m < self.foot_plate_thickness_m:
            raise DescriptionError(
                f"{prefix}.foot_plate_width_m", self.foot_plate_width_m, "must be >= foot_plate_thickness_m"
            )


@dataclass(frozen=True)
class TwinRobot:
    """Two 6-SSP robots, symmetrically mirrored (paper §2.2), one per foot.

    The paper does not say where the second robot stands. Default (`side_by_side_placements`, issue 13
    layout study): bases at world y = ∓0.88 m, rails not interleaved, the left robot the mirror image of
    the right, each foot plate cantilevered 0.68 m inboard so that the feet stand 0.4 m apart. The layout
    before issue 13 (`legacy-interleaved`: bases at y = ±0.5 m) cannot be built: its rods 3 and 4 cross.
    """

    robot: SSPRobot = field(default_factory=paper_robot)
    right: RobotPlacement = field(default_factory=lambda: side_by_side_placements()[0])
    left: RobotPlacement = field(default_factory=lambda: side_by_side_placements()[1])
    parts: PartDimensions = field(default_factory=PartDimensions)

    def __post_init__(self) -> None:
        self.parts.validate()
        for side_name, placement in (("right", self.right), ("left", self.left)):
            _require_finite(f"{side_name}.base_origin_m", placement.base_origin_m)
            _require_finite(f"{side_name}.base_yaw_rad", placement.base_yaw_rad)
            _require_finite(f"{side_name}.foot_plate_offset_m", placement.foot_plate_offset_m)

    @property
    def sides(self) -> tuple[str, str]:
        return ("right", "left")

    def placement(self, side: str) -> RobotPlacement:
        if side not in self.sides:
            raise DescriptionError("side", side, "must be 'right' or 'left'")
        return self.right if side == "right" else self.left

    def robot_for(self, side: str) -> SSPRobot:
        return self._mirrored_robot if self.placement(side).mirrored else self.robot

    @functools.cached_property
    def _mirrored_robot(self) -> SSPRobot:
        # Built (and validated) once: per-tick callers ask for it at every sample.
        return self.robot.mirrored()


def symmetric_placements(
    base_offset_y_m: float, stagger_x_m: float, feet_apart_m: float, *, base_yaw_rad: float = 0.0, mirrored: bool = True
) -> tuple[RobotPlacement, RobotPlacement]:
    """Right and left placements, point-symmetric about the world Z axis: the right base at
    (stagger, −offset), yawed by −yaw, the left at (−stagger, +offset), yawed by +yaw (the mirror image of
    the right when `mirrored`); each foot plate where the feet stand side by side at world (0, ∓feet/2)."""
    placements = []
    for sign, yaw in ((1.0, -base_yaw_rad), (-1.0, base_yaw_rad)):
        origin = np.array([sign * stagger_x_m, -sign * base_offset_y_m, 0.0])
        foot_world = np.array([0.0, -sign * feet_apart_m / 2, 0.0])
        # The platform centre sits above the base origin at neutral (the paper's neutral pose has x = y = 0).
        offset = rotation_matrix(0.0, 0.0, yaw).T @ (foot_world - origin)
        placements.append(
            RobotPlacement(
                base_origin_m=tuple(float(v) for v in origin),  # type: ignore[arg-type]
                base_yaw_rad=float(yaw),
                mirrored=mirrored and sign < 0,
                foot_plate_offset_m=(float(offset[0]), float(offset[1]), 0.0),
            )
        )
    return placements[0], placements[1]


# The default layout (issue 13 layout study, docs/kinematics.md): bases 1.76 m apart, the inner rails 160 mm
# apart (not interleaved), no stagger, no yaw, feet 0.4 m apart.
DEFAULT_BASE_OFFSET_Y_M = 0.88
DEFAULT_FEET_APART_M = 0.4


def side_by_side_placements() -> tuple[RobotPlacement, RobotPlacement]:
    """The default layout: the left robot the mirror image of the right, side by side."""
    return symmetric_placements(DEFAULT_BASE_OFFSET_Y_M, 0.0, DEFAULT_FEET_APART_M)


def legacy_interleaved_placements() -> tuple[RobotPlacement, RobotPlacement]:
    """The default before issue 13: bases at y = ±0.5 m, x = 0, feet 0.5 m apart. Its rods 3 and 4 cross
    at neutral; kept loadable (`--robot legacy-interleaved`) so that the collision stays demonstrable."""
    return (
        RobotPlacement(base_origin_m=(0.0, -0.5, 0.0), foot_plate_offset_m=(0.0, 0.25, 0.0)),
        RobotPlacement(base_origin_m=(0.0, 0.5, 0.0), mirrored=True, foot_plate_offset_m=(0.0, -0.25, 0.0)),
    )


NAMED_LAYOUTS = {
    "side-by-side": side_by_side_placements,
    "legacy-interleaved": legacy_interleaved_placements,
}


def default_twin() -> TwinRobot:
    return TwinRobot()


def named_twin(name: str) -> TwinRobot:
    """A built-in layout by name (`NAMED_LAYOUTS`) with the paper's robot."""
    if name not in NAMED_LAYOUTS:
        raise DescriptionError("robot", name, f"not a file and not a built-in layout; known: {sorted(NAMED_LAYOUTS)}")
    right, left = NAMED_LAYOUTS[name]()
    return TwinRobot(right=right, left=left)


# --- TOML -----------------------------------------------------------------------------------------


def twin_to_dict(twin: TwinRobot) -> dict[str, Any]:
    robot = twin.robot
    return {
        "robot": {
            "rod_length_m": robot.rod_length_m,
            "rail_z_m": robot.rail_z_m,
            "neutral_pose": list(robot.neutral_pose),
            "limits": asdict(robot.limits),
            "mass": {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(robot.mass).items()},
            "sliders": [
                {
                    "rail_y_m": s.rail_y_m,
                    "side": s.side,
                    "platform_joint_m": list(s.platform_joint_m),
                    "stroke_m": list(s.stroke_m),
                }
                for s in robot.sliders
            ],
        },
        "twin": {
            name: {
                "base_origin_m": list(p.base_origin_m),
                "base_yaw_rad": p.base_yaw_rad,
                "mirrored": p.mirrored,
                "foot_plate_offset_m": list(p.foot_plate_offset_m),
            }
            for name, p in (("right", twin.right), ("left", twin.left))
        }
        | {"parts": asdict(twin.parts)},
    }


def twin_digest(twin: TwinRobot) -> str:
    """A hash of the whole description (geometry, limits, masses, layout): a plan made for another robot
    description is never played on this one."""
    canonical = json.dumps(twin_to_dict(twin), sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(canonical.encode()).hexdigest()[:16]


def _build(cls: type, section: str, data: Mapping[str, Any], **overrides: Any) -> Any:
    _refuse_unknown_keys(section, data, {f.name for f in fields(cls)} - set(overrides))
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items() if k not in overrides}
    try:
        return cls(**values, **overrides)
    except TypeError as error:
        raise DescriptionError(section, dict(data), f"malformed section: {error}") from error


def _refuse_unknown_keys(section: str, data: Mapping[str, Any], known: set[str]) -> None:
    unknown = sorted(set(data) - known)
    if unknown:
        name = f"{section}.{unknown[0]}" if section else unknown[0]
        raise DescriptionError(name, data[unknown[0]], "unknown field")


def twin_from_dict(data: Mapping[str, Any]) -> TwinRobot:
    _refuse_unknown_keys("", data, {"robot", "twin"})
    _refuse_unknown_keys("twin", data.get("twin", {}), {"right", "left", "parts"})
    robot_data = dict(data.get("robot", {}))
    sliders = [_build(Slider, f"robot.sliders[{i}]", s) for i, s in enumerate(robot_data.pop("sliders", []), 1)]
    limits = _build(MotionLimits, "robot.limits", robot_data.pop("limits", {}))
    mass = _build(MassProperties, "robot.mass", robot_data.pop("mass", {}))
    robot = _build(SSPRobot, "robot", robot_data, sliders=tuple(sliders), limits=limits, mass=mass)
    twin_data = data.get("twin", {})
    placements = {
        name: _build(RobotPlacement, f"twin.{name}", twin_data[name]) for name in ("right", "left") if name in twin_data
    }
    parts = _build(PartDimensions, "twin.parts", twin_data.get("parts", {}))
    return TwinRobot(robot=robot, parts=parts, **placements)


def load_twin(path: str | Path) -> TwinRobot:
    """Load and validate a robot description TOML file."""
    with open(path, "rb") as handle:
        try:
            data = tomllib.load(handle)
        except tomllib.TOMLDecodeError as error:
            raise DescriptionError(str(path), "<file>", f"not valid TOML: {error}") from error
    return twin_from_dict(data)


def save_twin(twin: TwinRobot, path: str | Path) -> None:
    Path(path).write_text(tomli_w.dumps(twin_to_dict(twin)))
