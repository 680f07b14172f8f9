"""The timings and margins a plan is built with; the safety supervisor plays the plan with the same numbers
(`server.realtime.supervisor.SupervisorConfig` extends this with its own stop and watchdog settings)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import ClassVar

import numpy as np

from core.clearance import IK_EXACT_BELOW_M, STOP_CLEARANCE_MARGIN_M
from core.cues import CUE_TIME_MAX_S
from core.errors import InvalidValueError
from core.plan.ramps import return_duration_s

DEFAULT_CONTROL_RATE_HZ = 1000  # the worker's rate unless configured otherwise
# A segment's cue is generated for its duration plus the fade out, within the generator's span
# (core.cues.CUE_TIME_MAX_S); bounding the fade out lets the prescription model refuse, when a segment is
# saved, the duration that could not start (issue 20, defect 19): one rule, `SEGMENT_DURATION_MAX_S`.
FADE_OUT_MAX_S = 5.0
SEGMENT_DURATION_MAX_S = CUE_TIME_MAX_S - FADE_OUT_MAX_S


class PlanConfigError(InvalidValueError):
    """An invalid plan setting (soft start, fade out, return speeds, margins)."""


@dataclass(frozen=True)
class PlanConfig:
    soft_start_s: float = 1.0  # cue gain 0 → 1 (quintic) at each segment start and on resume
    fade_out_s: float = 1.0  # cue gain 1 → 0 after each segment's duration
    return_min_s: float = 1.0  # shortest return-to-neutral ramp
    return_speed_m_s: float = 0.05  # peak linear speed of a return to neutral
    return_rate_rad_s: float = 0.1  # peak angular rate of a return to neutral
    return_acceleration_m_s2: float = 0.3
    return_angular_acceleration_rad_s2: float = 0.5
    pause_stop_s: float = 0.5  # a pause: the plan's motion to standstill within this time,
    pause_hold_s: float = 1.0  # then held still this long, then back to neutral (core.plan.motion.pause)
    # Normal motion (cue, approach, return) must stay this far inside every limit; stop ramps may use the
    # margin (they are checked against the robot's own limits), so braking from a limit hit is possible.
    limit_margin_fraction: float = 0.05
    stroke_margin_m: float = 0.01
    # Normal motion keeps this much more clearance between the twin's parts than the robot's own margin.
    clearance_margin_m: float = STOP_CLEARANCE_MARGIN_M

    error: ClassVar[type[InvalidValueError]] = PlanConfigError  # subclasses refuse with their own kind

    def __post_init__(self) -> None:
        for item in fields(self):
            value = getattr(self, item.name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
                raise self.error(item.name, value, "must be a finite number > 0")
        if self.fade_out_s > FADE_OUT_MAX_S:
            raise self.error("fade_out_s", self.fade_out_s, f"must be <= {FADE_OUT_MAX_S:g} s")
        if self.limit_margin_fraction >= 0.5:
            raise self.error("limit_margin_fraction", self.limit_margin_fraction, "must be < 0.5")
        if self.clearance_margin_m > IK_EXACT_BELOW_M:  # the tick screens pairs for breaches that close only
            raise self.error("clearance_margin_m", self.clearance_margin_m, f"must be <= {IK_EXACT_BELOW_M} m")

    def return_duration_s(self, position: np.ndarray, velocity: np.ndarray) -> float:
        """How long the quintic return to neutral from (position, velocity) takes under these settings."""
        return return_duration_s(
            position,
            velocity,
            minimum_s=self.return_min_s,
            speed_m_s=self.return_speed_m_s,
            rate_rad_s=self.return_rate_rad_s,
            acceleration_m_s2=self.return_acceleration_m_s2,
            angular_acceleration_rad_s2=self.return_angular_acceleration_rad_s2,
        )
