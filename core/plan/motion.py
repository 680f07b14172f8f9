"""The one played object: the checked motion of a whole prescription, sample by sample, and the checked
transitions around it (issue 21).

    PlannedMotion  every control tick of the prescription: stance pose, the cue as played, its segment
    Transition     approach (measured pose → neutral), pause (the plan → standstill → hold → neutral) and
                   resume (neutral → back into the plan); each is built here and checked
                   (`core.plan.check.check_transition`) before the worker may play it

The worker indexes these arrays by time: it plays exactly the samples the check saw, and a late tick skips
ahead rather than stretching the plan. Nothing in the tick computes motion of its own, apart from the safety
reactions (controlled and emergency stops), which the tick checks against the robot's own limits.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from core.plan.config import PlanConfig
from core.plan.ramps import PoseRamp, start_velocity
from core.plan.timeline import return_ramp, segment_timelines

if TYPE_CHECKING:
    from core.plan.build import PrescriptionPlan

PLANNED_SHARE = 0.8  # progress: an optimal plan's trajectories are this far along when the timeline begins
TIMELINE_SHARE = 0.85  # and the timeline this far when the check begins (the classical washout is quick)
HISTORY_SAMPLES = 3  # a transition's check starts from the motion's last three samples (pose, velocity, acceleration)
JOIN_SAMPLES = 3  # and runs on into the samples it hands over to, so the junction is checked too


@dataclass(frozen=True)
class PlannedMotion:
    """Every control tick of a prescription from neutral at rest to neutral at rest."""

    poses: np.ndarray  # (N, 6) float64: stance pose, m and rad
    cue: np.ndarray  # (N, 6) float32: the cue as played, specific force m/s² (3) and angular velocity rad/s (3)
    segment: np.ndarray  # (N,) int16: the segment each sample belongs to (its cue, then its return to neutral)
    segment_start: np.ndarray  # (S,) int64: each segment's first sample

    @property
    def samples(self) -> int:
        return len(self.poses)

    @classmethod
    def of(cls, plan: PrescriptionPlan, progress: Callable[[float], None] | None = None) -> PlannedMotion:
        """The plan's timeline (`core.plan.timeline`) as the arrays the worker plays."""
        poses, cue, segment, starts = [], [], [], []
        count = 0
        begun = PLANNED_SHARE if plan.segments and plan.segments[0].planned_poses is not None else 0.0
        for part in segment_timelines(plan):
            if progress is not None:
                progress(begun + (TIMELINE_SHARE - begun) * (part.segment.index + 1) / len(plan.segments))
            starts.append(count)
            poses.append(part.poses)
            cue.append(np.concatenate([part.force, part.angular], axis=1).astype(np.float32))
            segment.append(np.full(len(part.poses), part.segment.index, dtype=np.int16))
            count += len(part.poses)
        return cls(
            np.ascontiguousarray(np.concatenate(poses)),
            np.ascontiguousarray(np.concatenate(cue)),
            np.concatenate(segment),
            np.asarray(starts, dtype=np.int64),
        )

    def pose_at(self, index: int) -> np.ndarray:
        """The pose of sample `index`; before the first sample the plan is at neutral, at rest."""
        return self.poses[index] if index >= 0 else np.zeros(6)

    def history(self, index: int) -> np.ndarray:
        """Samples index−2 … index (3, 6): what a transition leaving the plan after `index` starts from."""
        return np.array([self.pose_at(i) for i in range(index - HISTORY_SAMPLES + 1, index + 1)])

    def following(self, index: int) -> np.ndarray:
        """Up to `JOIN_SAMPLES` samples from `index` on: what a transition hands over to."""
        return self.poses[index : index + JOIN_SAMPLES]


@dataclass(frozen=True)
class Transition:
    """A way into, out of or back into the plan. Sample 0 is where the robot stands when it begins (the
    measured pose, the plan's sample `after_index`, or neutral); the worker plays it from sample 1."""

    kind: str  # "approach" | "pause" | "resume"
    poses: np.ndarray  # (M, 6) stance poses, m and rad
    after_index: int  # pause: the last plan sample played before it; resume: the plan sample it blends in first
    resume_index: int | None  # the plan sample played after its last (None: it ends parked at neutral)
    segment: int  # whose limits it was checked against


def state_of(history: np.ndarray, sample_period_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pose, velocity, acceleration) at the last of three samples, by backward differences as the tick
    computes them."""
    velocity = (history[2] - history[1]) / sample_period_s
    acceleration = (velocity - (history[1] - history[0]) / sample_period_s) / sample_period_s
    return history[2], velocity, acceleration


def approach(measured_pose: np.ndarray, sample_period_s: float, config: PlanConfig) -> Transition:
    """From where the platform stands (at rest) to neutral at rest: the quintic of the returns. Sample 0
    is the measured pose itself; the plan's first sample follows the last."""
    start = np.asarray(measured_pose, dtype=float).reshape(6)
    rest = np.zeros(6)
    poses = np.concatenate([start[None, :], return_ramp(start, rest, rest, sample_period_s, config)])
    return Transition("approach", poses, -1, 0, 0)


def pause(
    motion: PlannedMotion,
    after_index: int,
    sample_period_s: float,
    config: PlanConfig,
) -> Transition:
    """Leave the plan after sample `after_index`: to standstill within `pause_stop_s` (the bounded-jerk
    stop ramp), hold still for `pause_hold_s`, then return to neutral, where the robot stays parked."""
    stop_s, hold_s = config.pause_stop_s, config.pause_hold_s
    if not 0 <= after_index < motion.samples - 1:
        raise ValueError(f"pause after sample {after_index}: the plan has {motion.samples} samples")
    position, velocity, acceleration = state_of(motion.history(after_index), sample_period_s)
    ramp = PoseRamp()
    ramp.to_standstill(
        position, start_velocity(velocity, acceleration, sample_period_s, np.zeros(6)), acceleration, stop_s
    )
    times = np.arange(1, math.ceil(stop_s / sample_period_s) + 1) * sample_period_s
    t = np.minimum(times, stop_s)[:, None]
    c = ramp.coefficients
    down = c[0] + t * (c[1] + t * (c[2] + t * (c[3] + t * (c[4] + t * c[5]))))
    held = np.repeat(down[-1:], round(hold_s / sample_period_s), axis=0)
    rest = np.zeros(6)
    back = return_ramp(down[-1], rest, rest, sample_period_s, config)
    segment = int(motion.segment[after_index])
    poses = np.concatenate([position[None, :], down, held, back])
    return Transition("pause", poses, after_index, None, segment)


def resume(motion: PlannedMotion, into_index: int, sample_period_s: float, config: PlanConfig) -> Transition:
    """From neutral at rest back into the plan at sample `into_index`: the plan's own samples, blended in
    from neutral over the soft start (a quintic gain 0 → 1 with zero slope and curvature at both ends).
    Sample 0 is neutral (gain 0); the plan's sample `resume_index` follows the last, at full gain."""
    if not 0 <= into_index < motion.samples:
        raise ValueError(f"resume into sample {into_index}: the plan has {motion.samples} samples")
    blend = round(config.soft_start_s / sample_period_s)
    count = min(blend, motion.samples - into_index)
    x = np.arange(count) / blend
    gain = x * x * x * (10.0 + x * (-15.0 + 6.0 * x))
    poses = motion.poses[into_index : into_index + count] * gain[:, None]
    return Transition("resume", poses, into_index, into_index + count, int(motion.segment[into_index]))
