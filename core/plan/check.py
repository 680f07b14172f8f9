"""The independent batch check of a plan: every sample, every limit, before any motion.

It runs the plan's timeline (`core.plan.timeline`) through the batch front ends (`twin_inverse_kinematics`,
`TwinInverseDynamics`, the clearance model) and refuses the plan at the first sample that breaks a limit,
naming the segment, the time in it, the limit and the value. The worker's per-tick check
(`core.twin_kernels`) reads the same `SessionLimits`; normal motion keeps the stop margin inside them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from core.dynamics import TwinInverseDynamics
from core.kinematics import (
    IK_CHUNK_POSES,
    LegViolation,
    twin_inverse_kinematics,
    twin_singularity_report,
    violation_flag_stretches,
)
from core.plan import motion
from core.plan.limits import LIMIT_UNITS, LimitCode
from core.plan.motion import JOIN_SAMPLES, TIMELINE_SHARE, Transition, state_of
from core.plan.rejection import PrescriptionRejected
from core.plan.timeline import finite_differences
from core.robot import TwinRobot

if TYPE_CHECKING:
    from core.plan.build import PrescriptionPlan, SegmentPlan


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


def check_plan(
    plan: PrescriptionPlan, twin: TwinRobot, progress: Callable[[float], None] | None = None
) -> PrescriptionReport:
    """Every sample of the plan's motion (cue phases and returns to neutral), exactly as the worker will play
    it, against every limit of its segment; raises `PrescriptionRejected` at the first breach, else reports
    each limit's peak use. Velocities and accelerations are recomputed here from the poses."""
    period = plan.sample_period_s
    played = plan.played
    dynamics = TwinInverseDynamics(twin, plan.patient.payload() if plan.patient else None)
    previous_sliders, previous_slider_velocity = _neutral_sliders(twin), np.zeros(12)
    previous_pose, previous_velocity = np.zeros(6), np.zeros(6)
    peak_use: dict[str, float] = {}
    ends = [*played.segment_start[1:].tolist(), played.samples]
    for segment, start, end in zip(plan.segments, played.segment_start.tolist(), ends, strict=True):
        poses = played.poses[start:end]
        velocity, acceleration = finite_differences(poses, period, previous_pose, previous_velocity)
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
        previous_pose, previous_velocity = poses[-1], velocity[-1]
        if progress is not None:
            progress(TIMELINE_SHARE + (1.0 - TIMELINE_SHARE) * end / played.samples)
    return PrescriptionReport(
        played.samples * period,
        played.samples,
        [start * period for start in played.segment_start.tolist()],
        {k: round(v, 4) for k, v in peak_use.items()},
    )


def check_transition(
    plan: PrescriptionPlan, transition: Transition, twin: TwinRobot, before: np.ndarray
) -> dict[str, float]:
    """A transition, from the three samples `before` it (ending where the robot stands: its sample 0) on
    into the plan samples it hands over to, against every limit of its segment, as the plan itself is
    checked. Raises `PrescriptionRejected` (naming the transition) at the first breach; returns peak uses."""
    period = plan.sample_period_s
    if transition.resume_index is None:  # it ends parked: the robot holds its last pose
        after = np.repeat(transition.poses[-1:], JOIN_SAMPLES, axis=0)
    else:
        after = plan.played.following(transition.resume_index)
    poses = np.concatenate([transition.poses[1:], after])
    if not np.allclose(before[-1], transition.poses[0], rtol=0.0, atol=1e-12):
        raise ValueError(f"the {transition.kind} does not start where the robot stands")
    pose, velocity, _ = state_of(before, period)
    velocity, acceleration = finite_differences(poses, period, pose, velocity)
    history = _sliders(twin, before[1:])
    dynamics = TwinInverseDynamics(twin, plan.patient.payload() if plan.patient else None)
    peak_use: dict[str, float] = {}
    segment = plan.segments[transition.segment]
    _check_samples(
        twin,
        segment,
        poses,
        velocity,
        acceleration,
        period,
        dynamics,
        history[1],
        (history[1] - history[0]) / period,
        peak_use,
        phase=transition.kind,
    )
    return {k: round(v, 4) for k, v in peak_use.items()}


def checked_approach(plan: PrescriptionPlan, twin: TwinRobot, measured_pose: np.ndarray) -> Transition:
    """The approach from where the platform stands (at rest) to the plan's start, checked."""
    transition = motion.approach(measured_pose, plan.sample_period_s, plan.config)
    check_transition(plan, transition, twin, np.repeat(transition.poses[:1], 3, axis=0))
    return transition


def checked_pause(plan: PrescriptionPlan, twin: TwinRobot, after_index: int) -> Transition:
    """The pause leaving the plan after its sample `after_index`, checked."""
    transition = motion.pause(plan.played, after_index, plan.sample_period_s, plan.config)
    check_transition(plan, transition, twin, plan.played.history(after_index))
    return transition


def checked_resume(plan: PrescriptionPlan, twin: TwinRobot, into_index: int) -> Transition:
    """The resume from neutral (where a pause parks) back into the plan at its sample `into_index`, checked."""
    transition = motion.resume(plan.played, into_index, plan.sample_period_s, plan.config)
    check_transition(plan, transition, twin, np.zeros((3, 6)))
    return transition


def _sliders(twin: TwinRobot, poses: np.ndarray) -> np.ndarray:
    solutions = twin_inverse_kinematics(twin, poses)
    return np.concatenate([solutions[side].slider_positions_m for side in twin.sides], axis=1)


def _neutral_sliders(twin: TwinRobot) -> np.ndarray:
    return _sliders(twin, np.zeros((1, 6)))[0]


# Samples checked at once: bounds the check's memory whatever a segment's length (about 3 kB of intermediate
# arrays per sample), while each chunk still spreads over both cores (`core.kinematics.for_each_chunk`).
CHECK_CHUNK_SAMPLES = 4 * IK_CHUNK_POSES


@dataclass(frozen=True)
class _Breach:
    sample: int  # in the segment
    code: LimitCode
    axis: int
    value: float
    limit: float
    collision_pair: str | None = None


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
    phase: str | None = None,
) -> np.ndarray:
    """Every limit over one segment's samples (or a transition's: `phase` names it), chunk by chunk; raises at
    the earliest breach. Returns sliders (N, 12)."""
    sliders = np.empty((len(poses), 12))
    # Each robot's violation flags over the whole segment, for a refusal's details.
    flags = {side: np.empty(len(poses), dtype=np.uint8) for side in twin.sides}
    first: _Breach | None = None
    last_sliders, last_velocity = previous_sliders, previous_slider_velocity
    for start in range(0, len(poses), CHECK_CHUNK_SAMPLES):
        rows = slice(start, start + CHECK_CHUNK_SAMPLES)
        breach, last_velocity = _check_chunk(
            twin,
            segment,
            poses[rows],
            velocity[rows],
            acceleration[rows],
            period,
            dynamics,
            previous_sliders,
            last_sliders,
            last_velocity,
            peak_use,
            sliders[rows],
            {side: side_flags[rows] for side, side_flags in flags.items()},
        )
        if first is None and breach is not None:
            first = replace(breach, sample=breach.sample + start)
        last_sliders = sliders[rows][-1]
    if first is not None:
        raise _rejection(twin, segment, first, poses, period, flags, phase)
    return sliders


def _check_chunk(
    twin: TwinRobot,
    segment: SegmentPlan,
    poses: np.ndarray,
    velocity: np.ndarray,
    acceleration: np.ndarray,
    period: float,
    dynamics: TwinInverseDynamics,
    fill_sliders: np.ndarray,
    previous_sliders: np.ndarray,
    previous_slider_velocity: np.ndarray,
    peak_use: dict[str, float],
    sliders_out: np.ndarray,
    flags_out: dict[str, np.ndarray],
) -> tuple[_Breach | None, np.ndarray]:
    """Every limit over consecutive samples that follow `previous_sliders` and `previous_slider_velocity`; a rod
    that cannot reach keeps its slider at `fill_sliders` (where the segment started). Writes the sliders and each
    robot's violation flags, updates `peak_use`; returns the chunk's earliest breach and its last slider velocity."""
    limits = segment.motion_limits.motion
    solutions = twin_inverse_kinematics(twin, poses, check=False)
    sides = [solutions[side] for side in twin.sides]
    for side, solution in solutions.items():
        np.bitwise_or.reduce(solution.violations, axis=1, out=flags_out[side])
    sliders = np.concatenate([s.slider_positions_m for s in sides], axis=1)
    unreachable = np.isnan(sliders)
    np.copyto(sliders_out, np.where(unreachable, fill_sliders, sliders))
    slider_velocity = np.diff(sliders_out, axis=0, prepend=previous_sliders[None, :]) / period
    slider_acceleration = np.diff(slider_velocity, axis=0, prepend=previous_slider_velocity[None, :]) / period
    tilt = np.arccos(np.clip(np.cos(poses[:, 3]) * np.cos(poses[:, 4]), -1.0, 1.0))
    reachable_poses = np.where(unreachable.any(axis=1)[:, None], 0.0, poses) if unreachable.any() else poses
    forces = dynamics.slider_forces(reachable_poses, velocity, acceleration)
    violations = np.concatenate([s.violations for s in sides], axis=1)
    singular = (violations & np.uint8(LegViolation.SINGULARITY)) != 0
    collisions = sides[0].collisions
    clearance = collisions.clearance_m if collisions is not None else np.full(len(poses), np.inf)
    clearance_min = segment.motion_limits.clearance_min_m  # the robot's margin plus the stop margin
    base_cone = np.concatenate([s.base_cone_rad for s in sides], axis=1)
    platform_cone = np.concatenate([s.platform_cone_rad for s in sides], axis=1)
    stroke_min, stroke_max = segment.motion_limits.stroke_min_m, segment.motion_limits.stroke_max_m
    below, above = sliders_out < stroke_min, sliders_out > stroke_max
    # Distance from each platform joint to its rail (only reported when the rod cannot reach).
    reach = np.where(unreachable, twin.robot.rod_length_m + 1e-9, 0.0)
    checks: list[tuple[LimitCode, np.ndarray, np.ndarray, float | np.ndarray]] = [
        # code, breached (N, k), value (N, k), limit
        (LimitCode.ROD_REACH, unreachable, reach, twin.robot.rod_length_m),
        (LimitCode.STROKE, below | above, sliders_out, np.where(below, stroke_min, stroke_max)),
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
    first: _Breach | None = None
    for code, breached, values, limit in checks:
        if code in PEAK_USE_CODES:
            use = float(np.nanmax(np.abs(values))) / float(np.max(limit))
            peak_use[code.label] = max(peak_use.get(code.label, 0.0), use)
        if not breached.any():
            continue
        rows = np.flatnonzero(breached.any(axis=1))
        if first is None or rows[0] < first.sample:
            sample = int(rows[0])
            axis = int(np.argmax(breached[sample]))
            limit_value = float(np.broadcast_to(limit, breached.shape)[sample, axis])
            pair = None
            if code is LimitCode.COLLISION and collisions is not None:
                pair = collisions.pair_names[int(collisions.closest_pair[sample])]
            first = _Breach(sample, code, axis, float(values[sample, axis]), limit_value, pair)
    return first, slider_velocity[-1]


PEAK_USE_CODES = frozenset(
    {
        LimitCode.TILT,
        LimitCode.SLIDER_VELOCITY,
        LimitCode.SLIDER_ACCELERATION,
        LimitCode.DRIVE_FORCE,
        LimitCode.BASE_JOINT_CONE,
        LimitCode.PLATFORM_JOINT_CONE,
    }
)


def _rejection(
    twin: TwinRobot,
    segment: SegmentPlan,
    breach: _Breach,
    poses: np.ndarray,
    period: float,
    flags: dict[str, np.ndarray],
    phase: str | None = None,
) -> PrescriptionRejected:
    """The refusal of a segment at its earliest breach, with every kinematic limit it breaks (by reason, with
    its stretches) and, for a singularity, each robot's singularity report."""
    sample, code, axis, value, limit_value = breach.sample, breach.code, breach.axis, breach.value, breach.limit
    time_s = sample * period
    where = "" if code is LimitCode.TILT else f", {_axis_label(axis)}"
    unit = LIMIT_UNITS[code]
    if phase is None:
        phase = "cue" if sample < segment.cue_samples else "return to neutral"
    name = code.label.replace("_", " ")
    times = np.arange(len(poses)) * period
    details: dict[str, Any] = {"violations_by_reason": violation_flag_stretches(flags, times)}
    if code is LimitCode.SINGULARITY:
        reports = twin_singularity_report(twin, poses, times)
        details["singularity"] = {side: report.to_dict() for side, report in reports.items()}
        worst = max(reports.items(), key=lambda item: item[1].worst_condition_number)
        side, report = worst
        detail = f"the platform would come too close to (or pass) a singularity; {side} robot: {report.summary()}"
    elif code is LimitCode.COLLISION and breach.collision_pair is not None:
        where = ""
        detail = (
            f"collision {breach.collision_pair}: clearance {value * 1e3:.2f} mm against the margin "
            f"{limit_value * 1e3:.2f} mm"
        )
    elif code is LimitCode.ROD_REACH:
        detail = "a rod could not reach its rail"
    else:
        detail = (
            f"{name} {value:.6g} {unit} exceeds the limit {limit_value:.6g} {unit} "
            "(normal motion keeps the configured stop margin inside each limit)"
        )
    return PrescriptionRejected(
        segment.index,
        time_s,
        code.label,
        value,
        f"segment {segment.index} at t = {time_s:.3f} s ({phase}{where}): {detail}",
        details,
    )


def _axis_label(axis: int) -> str:
    return f"{('right', 'left')[axis // 6]} slider {axis % 6 + 1}"
