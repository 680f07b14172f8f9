"""The independent batch check of a plan: every sample, every limit, before any motion.

It runs the plan's timeline (`core.plan.timeline`) through the batch front ends (`twin_inverse_kinematics`,
`TwinInverseDynamics`, the clearance model) and refuses the plan at the first sample that breaks a limit,
naming the segment, the time in it, the limit and the value. The worker's per-tick check
(`core.twin_kernels`) reads the same `SessionLimits`; normal motion keeps the stop margin inside them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from core.dynamics import TwinInverseDynamics
from core.kinematics import LegViolation, twin_inverse_kinematics, twin_singularity_report, violation_stretches
from core.plan.limits import LIMIT_UNITS, LimitCode
from core.plan.timeline import segment_timelines
from core.robot import TwinRobot

if TYPE_CHECKING:
    from core.plan.build import PrescriptionPlan, SegmentPlan


class PrescriptionRejected(ValueError):  # noqa: N818 — the agreed interface name
    """The prescription would exceed a limit: where (segment, time in it) and which limit."""

    def __init__(
        self, segment: int, time_s: float, limit: str, value: float, message: str, details: dict[str, Any] | None = None
    ) -> None:
        self.segment, self.time_s, self.limit, self.value = segment, time_s, limit, value
        # Beyond the first breach: every kinematic limit broken in the segment (by reason, with its stretches)
        # and each robot's singularity report (worst cond(J) and when, every det J sign change).
        self.details = details or {}
        super().__init__(message)

    def to_dict(self) -> dict[str, Any]:
        return {
            "segment": self.segment,
            "time_s": self.time_s,
            "limit": self.limit,
            "value": self.value,
            "message": str(self),
            **self.details,
        }


@dataclass(frozen=True)
class PrescriptionReport:
    """What the offline check found: every limit's peak use (fraction of the limit) and the timeline."""

    duration_s: float
    samples: int
    segment_start_s: list[float]
    peak_use: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "duration_s": self.duration_s,
            "samples": self.samples,
            "segment_start_s": self.segment_start_s,
            "peak_use": self.peak_use,
        }


def check_plan(plan: PrescriptionPlan, twin: TwinRobot) -> PrescriptionReport:
    """Every sample of the plan (cue phases and returns to neutral) against every limit of its segment;
    raises `PrescriptionRejected` at the first breach, else reports each limit's peak use."""
    period = plan.sample_period_s
    dynamics = TwinInverseDynamics(twin, plan.patient.payload() if plan.patient else None)
    previous_sliders, previous_slider_velocity = _neutral_sliders(twin), np.zeros(12)
    peak_use: dict[str, float] = {}
    segment_start_s, elapsed = [], 0.0
    samples = 0
    for segment, _, _, poses, velocity, acceleration in segment_timelines(plan):
        segment_start_s.append(elapsed)
        sliders = _check_samples(
            twin,
            segment,
            poses,
            velocity,
            acceleration,
            period,
            dynamics,
            previous_sliders,
            previous_slider_velocity,
            peak_use,
        )
        previous_slider_velocity = (sliders[-1] - sliders[-2]) / period
        previous_sliders = sliders[-1]
        elapsed += len(poses) * period
        samples += len(poses)
    return PrescriptionReport(elapsed, samples, segment_start_s, {k: round(v, 4) for k, v in peak_use.items()})


def _neutral_sliders(twin: TwinRobot) -> np.ndarray:
    solutions = twin_inverse_kinematics(twin, np.zeros((1, 6)))
    return np.concatenate([solutions[side].slider_positions_m[0] for side in twin.sides])


def _check_samples(
    twin: TwinRobot,
    segment: SegmentPlan,
    poses: np.ndarray,
    velocity: np.ndarray,
    acceleration: np.ndarray,
    period: float,
    dynamics: TwinInverseDynamics,
    previous_sliders: np.ndarray,
    previous_slider_velocity: np.ndarray,
    peak_use: dict[str, float],
) -> np.ndarray:
    """Every limit over one segment's samples; raises at the earliest breach. Returns sliders (N, 12)."""
    limits = segment.motion_limits.motion
    solutions = twin_inverse_kinematics(twin, poses, check=False)
    sides = [solutions[side] for side in ("right", "left")]
    sliders = np.concatenate([s.slider_positions_m for s in sides], axis=1)
    unreachable = np.isnan(sliders)
    # Distance from each platform joint to its rail (only reported when the rod cannot reach).
    reach = np.where(unreachable, twin.robot.rod_length_m + 1e-9, 0.0)
    sliders_filled = np.where(unreachable, previous_sliders, sliders)
    slider_velocity = np.diff(sliders_filled, axis=0, prepend=previous_sliders[None, :]) / period
    slider_acceleration = np.diff(slider_velocity, axis=0, prepend=previous_slider_velocity[None, :]) / period
    tilt = np.arccos(np.clip(np.cos(poses[:, 3]) * np.cos(poses[:, 4]), -1.0, 1.0))
    forces = dynamics.slider_forces(np.where(unreachable.any(axis=1)[:, None], 0.0, poses), velocity, acceleration)
    violations = np.concatenate([s.violations for s in sides], axis=1)
    singular = (violations & np.uint8(LegViolation.SINGULARITY)) != 0
    collisions = sides[0].collisions
    clearance = collisions.clearance_m if collisions is not None else np.full(len(poses), np.inf)
    clearance_min = segment.motion_limits.clearance_min_m  # the robot's margin plus the stop margin
    base_cone = np.concatenate([s.base_cone_rad for s in sides], axis=1)
    platform_cone = np.concatenate([s.platform_cone_rad for s in sides], axis=1)
    stroke_min, stroke_max = segment.motion_limits.stroke_min_m, segment.motion_limits.stroke_max_m
    below, above = sliders_filled < stroke_min, sliders_filled > stroke_max
    checks: list[tuple[LimitCode, np.ndarray, np.ndarray, float | np.ndarray]] = [
        # code, breached (N, k), value (N, k), limit
        (LimitCode.ROD_REACH, unreachable, reach, twin.robot.rod_length_m),
        (LimitCode.STROKE, below | above, sliders_filled, np.where(below, stroke_min, stroke_max)),
        (LimitCode.BASE_JOINT_CONE, base_cone > limits.base_joint_cone_rad, base_cone, limits.base_joint_cone_rad),
        (
            LimitCode.PLATFORM_JOINT_CONE,
            platform_cone > limits.platform_joint_cone_rad,
            platform_cone,
            limits.platform_joint_cone_rad,
        ),
        (LimitCode.TILT, (tilt > limits.tilt_max_rad)[:, None], tilt[:, None], limits.tilt_max_rad),
        (
            LimitCode.SLIDER_VELOCITY,
            np.abs(slider_velocity) > limits.slider_velocity_max_m_s,
            slider_velocity,
            limits.slider_velocity_max_m_s,
        ),
        (
            LimitCode.SLIDER_ACCELERATION,
            np.abs(slider_acceleration) > limits.slider_acceleration_max_m_s2,
            slider_acceleration,
            limits.slider_acceleration_max_m_s2,
        ),
        (LimitCode.DRIVE_FORCE, np.abs(forces) > limits.drive_force_max_n, forces, limits.drive_force_max_n),
        (LimitCode.SINGULARITY, singular, singular.astype(float), 0.0),
        (LimitCode.COLLISION, (~(clearance >= clearance_min))[:, None], clearance[:, None], clearance_min),
    ]
    first: tuple[int, LimitCode, int, float, float] | None = None
    for code, breached, values, limit in checks:
        if code in (
            LimitCode.TILT,
            LimitCode.SLIDER_VELOCITY,
            LimitCode.SLIDER_ACCELERATION,
            LimitCode.DRIVE_FORCE,
            LimitCode.BASE_JOINT_CONE,
            LimitCode.PLATFORM_JOINT_CONE,
        ):
            use = float(np.nanmax(np.abs(values))) / float(np.max(limit))
            peak_use[code.label] = max(peak_use.get(code.label, 0.0), use)
        rows = np.flatnonzero(breached.any(axis=1))
        if rows.size and (first is None or rows[0] < first[0]):
            sample = int(rows[0])
            axis = int(np.argmax(breached[sample]))
            limit_value = float(np.broadcast_to(limit, breached.shape)[sample, axis])
            first = (sample, code, axis, float(values[sample, axis]), limit_value)
    if first is not None:
        sample, code, axis, value, limit_value = first
        time_s = sample * period
        where = "" if code is LimitCode.TILT else f", {_axis_label(axis)}"
        unit = LIMIT_UNITS[code]
        phase = "cue" if sample < segment.cue_samples else "return to neutral"
        name = code.label.replace("_", " ")
        times = np.arange(len(poses)) * period
        details: dict[str, Any] = {"violations_by_reason": violation_stretches(solutions, times)}
        if code is LimitCode.SINGULARITY:
            reports = twin_singularity_report(twin, poses, times)
            details["singularity"] = {side: report.to_dict() for side, report in reports.items()}
            worst = max(reports.items(), key=lambda item: item[1].worst_condition_number)
            side, report = worst
            detail = f"the platform would come too close to (or pass) a singularity; {side} robot: {report.summary()}"
        elif code is LimitCode.COLLISION and collisions is not None:
            where = ""
            pair = collisions.pair_names[int(collisions.closest_pair[sample])]
            detail = f"collision {pair}: clearance {value * 1e3:.2f} mm against the margin {limit_value * 1e3:.2f} mm"
        elif code is LimitCode.ROD_REACH:
            detail = "a rod could not reach its rail"
        else:
            detail = (
                f"{name} {value:.6g} {unit} exceeds the limit {limit_value:.6g} {unit} "
                "(normal motion keeps the configured stop margin inside each limit)"
            )
        raise PrescriptionRejected(
            segment.index,
            time_s,
            code.label,
            value,
            f"segment {segment.index} at t = {time_s:.3f} s ({phase}{where}): {detail}",
            details,
        )
    return sliders_filled


def _axis_label(axis: int) -> str:
    return f"{('right', 'left')[axis // 6]} slider {axis % 6 + 1}"
