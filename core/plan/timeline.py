"""Each segment as the worker plays it, sample by sample at the control rate.

    cue (core.cues) × gain (soft start, full, fade out: `ramps.cue_gains`)
    → classical: washout (paper §4.1) → command shaping        optimal: the trajectory planned at build time
    → stance poses → quintic return to neutral (`ramps.PoseRamp`)

Velocities and accelerations are backward differences, as the worker computes them tick by tick, and each
segment starts from the state the previous one ended in.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from core.cues import cue_from_spec
from core.plan.config import PlanConfig
from core.plan.ramps import PoseRamp, cue_gains, start_velocity
from core.shaping import CommandShaper
from core.washout import washout_batch

if TYPE_CHECKING:
    from core.plan.build import PrescriptionPlan, SegmentPlan


def segment_cue(segment: SegmentPlan, sample_period_s: float, config: PlanConfig) -> tuple[np.ndarray, np.ndarray]:
    """The segment's cue (N, 3) ×2 as the worker plays it: × soft-start and fade-out gains."""
    cue = cue_from_spec(segment.cue_spec, sample_period_s, segment.seed)
    force, angular = cue.generate(segment.cue_samples * sample_period_s)
    gains = cue_gains(
        np.arange(len(force)) * sample_period_s, segment.duration_s, config.soft_start_s, config.fade_out_s
    )
    return force * gains[:, None], angular * gains[:, None]


def segment_poses(
    segment: SegmentPlan, sample_period_s: float, played_force: np.ndarray, played_angular: np.ndarray
) -> np.ndarray:
    """Stance poses (N, 6) from rest for the played cue: the batch twin of the worker's CUE phase."""
    if segment.planned_poses is not None:
        return segment.planned_poses
    trajectory = washout_batch(segment.washout, sample_period_s, played_force, played_angular)
    return CommandShaper(segment.shaping, sample_period_s).shape_batch(trajectory.pose)


def finite_differences(
    poses: np.ndarray, sample_period_s: float, previous: np.ndarray, previous_velocity: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Backward-difference velocity and acceleration, as the worker computes them tick by tick."""
    velocity = np.diff(poses, axis=0, prepend=previous[None, :]) / sample_period_s
    acceleration = np.diff(velocity, axis=0, prepend=previous_velocity[None, :]) / sample_period_s
    return velocity, acceleration


def return_ramp(
    position: np.ndarray, velocity: np.ndarray, acceleration: np.ndarray, sample_period_s: float, config: PlanConfig
) -> np.ndarray:
    """Stance poses (M, 6) of the quintic return to neutral the worker plays after a segment."""
    ramp = PoseRamp()
    velocity = start_velocity(velocity, acceleration, sample_period_s, np.zeros(6))
    duration = config.return_duration_s(position, velocity)
    ramp.to_pose(position, velocity, acceleration, np.zeros(6), duration)
    times = np.arange(1, math.ceil(duration / sample_period_s) + 1) * sample_period_s
    t = np.minimum(times, duration)[:, None]
    c = ramp.coefficients
    return c[0] + t * (c[1] + t * (c[2] + t * (c[3] + t * (c[4] + t * c[5]))))


class SegmentTimeline(NamedTuple):
    segment: SegmentPlan
    force: np.ndarray  # (N, 3) m/s², the cue as played (zero during the return)
    angular: np.ndarray  # (N, 3) rad/s
    poses: np.ndarray  # (N, 6) stance pose, m and rad: cue phase, then the return to neutral
    velocity: np.ndarray  # (N, 6)
    acceleration: np.ndarray  # (N, 6)


def segment_timelines(plan: PrescriptionPlan) -> Iterator[SegmentTimeline]:
    """Every segment of the plan in order, each continuing from where the previous one ended."""
    period, config = plan.sample_period_s, plan.config
    previous_pose, previous_velocity = np.zeros(6), np.zeros(6)
    for segment in plan.segments:
        force, angular = segment_cue(segment, period, config)
        cue_poses = segment_poses(segment, period, force, angular)
        velocity, acceleration = finite_differences(cue_poses, period, previous_pose, previous_velocity)
        back = return_ramp(cue_poses[-1], velocity[-1], acceleration[-1], period, config)
        poses = np.concatenate([cue_poses, back])
        velocity, acceleration = finite_differences(poses, period, previous_pose, previous_velocity)
        rest = np.zeros((len(back), 3))
        yield SegmentTimeline(
            segment, np.concatenate([force, rest]), np.concatenate([angular, rest]), poses, velocity, acceleration
        )
        previous_pose, previous_velocity = poses[-1], velocity[-1]


def prescription_timeline(plan: PrescriptionPlan) -> dict[str, np.ndarray]:
    """Every control tick of the whole prescription: cue (N, 3) ×2 as played, stance pose, velocity and
    acceleration (N, 6) each, and the segment index (N,)."""
    parts = list(segment_timelines(plan))
    timeline = {name: np.concatenate([getattr(p, name) for p in parts]) for name in SegmentTimeline._fields[1:]}
    timeline["segment"] = np.concatenate([np.full(len(p.poses), p.segment.index) for p in parts])
    return timeline
