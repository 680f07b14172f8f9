"""The limits a session runs under: the robot description's, optionally tightened by the prescription,
and the codes that name a broken limit.

A prescription may only tighten a limit; loosening one, or naming one that does not exist, is refused
with the field, the value and the limit. The per-tick check (`core.twin_kernels`) and the offline check
(`core.plan.check`) both read `SessionLimits`, so the two can never disagree on a number.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from core.errors import InvalidValueError
from core.robot import MotionLimits, TwinRobot


class LimitOverrideError(InvalidValueError):
    """A prescription limit override that would loosen or break a robot limit."""


class LimitCode(enum.IntEnum):
    """Which limit a command broke; the per-tick check (`core.twin_kernels`, the same numbers) and the
    offline check share it, and the worker's telemetry carries it."""

    NONE = 0
    ROD_REACH = 1
    STROKE = 2
    BASE_JOINT_CONE = 3
    PLATFORM_JOINT_CONE = 4
    TILT = 5
    SLIDER_VELOCITY = 6
    SLIDER_ACCELERATION = 7
    DRIVE_FORCE = 8
    SINGULARITY = 9  # offline check only (core.kinematics' condition-number test)
    COLLISION = 10  # two parts of the twin closer than the clearance margin (core.clearance)

    @property
    def label(self) -> str:
        return self.name.lower()


LIMIT_UNITS = {
    LimitCode.ROD_REACH: "m",
    LimitCode.STROKE: "m",
    LimitCode.BASE_JOINT_CONE: "rad",
    LimitCode.PLATFORM_JOINT_CONE: "rad",
    LimitCode.TILT: "rad",
    LimitCode.SLIDER_VELOCITY: "m/s",
    LimitCode.SLIDER_ACCELERATION: "m/s²",
    LimitCode.DRIVE_FORCE: "N",
    LimitCode.SINGULARITY: "",
    LimitCode.COLLISION: "m",
}


@dataclass(frozen=True)
class SessionLimits:
    motion: MotionLimits
    stroke_min_m: np.ndarray  # (12,) right sliders 1–6, then left 1–6
    stroke_max_m: np.ndarray
    # Smallest clearance between the twin's parts (core.clearance): the robot's, plus the stop margin for
    # normal motion, so that a controlled stop can brake before the parts meet.
    clearance_min_m: float = 0.0

    @classmethod
    def for_twin(
        cls, twin: TwinRobot, overrides: Mapping[str, Any] | None = None, prefix: str = "limits"
    ) -> SessionLimits:
        robots = [twin.robot_for(side) for side in twin.sides]
        motion = tighten(robots[0].limits, overrides or {}, prefix)
        return cls(
            motion=motion,
            stroke_min_m=np.concatenate([r.stroke_min_m for r in robots]),
            stroke_max_m=np.concatenate([r.stroke_max_m for r in robots]),
            clearance_min_m=twin.parts.clearance_min_m,
        )

    def with_margin(self, fraction: float, stroke_margin_m: float, clearance_margin_m: float = 0.0) -> SessionLimits:
        """Limits for normal motion: every bound pulled in by `fraction`, the strokes by `stroke_margin_m`,
        and `clearance_margin_m` more clearance required between parts."""
        scaled = {name: value * (1.0 - fraction) for name, value in asdict(self.motion).items()}
        return SessionLimits(
            motion=replace(self.motion, **scaled),
            stroke_min_m=self.stroke_min_m + stroke_margin_m,
            stroke_max_m=self.stroke_max_m - stroke_margin_m,
            clearance_min_m=self.clearance_min_m + clearance_margin_m,
        )

    def kernel_vector(self) -> np.ndarray:
        """The (LIMITS_VECTOR_SIZE,) limits vector `twin_command_kernel` reads."""
        m = self.motion
        return np.array(
            [
                m.base_joint_cone_rad,
                m.platform_joint_cone_rad,
                m.tilt_max_rad,
                m.slider_velocity_max_m_s,
                m.slider_acceleration_max_m_s2,
                m.drive_force_max_n,
                self.clearance_min_m,
            ]
        )


def tighten(limits: MotionLimits, overrides: Mapping[str, float], prefix: str = "limits") -> MotionLimits:
    """`limits` with each override applied. The prescription model has already checked that each override
    names a limit and is a finite number > 0; this is the robot-dependent part: no larger than the robot's."""
    robot_limits = asdict(limits)
    for name, value in overrides.items():
        if name not in robot_limits:
            raise LimitOverrideError(f"{prefix}.{name}", value, f"unknown limit; known: {sorted(robot_limits)}")
        if value > robot_limits[name]:
            raise LimitOverrideError(
                f"{prefix}.{name}", value, f"may only tighten the robot's limit of {robot_limits[name]:g}"
            )
    return replace(limits, **{name: float(value) for name, value in overrides.items()})
