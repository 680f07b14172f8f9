"""The tick's motion source: where each tick's stance pose comes from while motion is checked motion.

`PlayedPlan` plays a checked plan (`core.plan.motion`): the approach from where the platform stood, the
plan's samples, and the pause and resume transitions, each checked before it was sent here. Samples are
indexed by time: a late tick skips ahead (`step` > 1); it never stretches the plan. The tick
(`server.realtime.pipeline`) owns everything else: the limits every candidate pose is held to, the safety
ramps of a stop, the HAL, the monitors and the telemetry record.

This is the seam a closed-loop source plugs into (issue 22: sway-referenced support, clamped to the
envelope checked before its run); the supervisor, the limits and the stops stay the tick's.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from core.plan.build import PrescriptionPlan
from core.plan.limits import SessionLimits
from core.plan.motion import PlannedMotion, Transition

# A stored plan's played pages go back to the kernel every this many samples, this far behind (a resume
# reads them again from the page cache): a 60-minute plan does not stay resident in the worker.
RELEASE_EVERY_SAMPLES = 2048
RELEASE_BEHIND_SAMPLES = 30_000


class PhaseEvents(Protocol):
    """What a motion source tells the supervisor (`server.realtime.supervisor.Supervisor`) as it plays."""

    def phase_finished(self) -> None: ...
    def pause_begins(self) -> None: ...
    def plan_finished(self) -> None: ...


class PlayedPlan:
    """A checked plan and its checked transitions, played sample by sample."""

    def __init__(
        self, plan: PrescriptionPlan, phases: PhaseEvents, use_limits: Callable[[SessionLimits], None]
    ) -> None:
        self.plan = plan
        self.motion: PlannedMotion = plan.played
        self._phases = phases
        self._use_limits = use_limits  # a new segment brings its own motion limits
        self.plan_index = -1  # the plan sample played last (-1: none yet)
        self.segment_index = -1
        self.transition: Transition | None = None  # the checked transition being played
        self.transition_index = 0  # its sample played last
        self.pending_pause: Transition | None = None  # a checked pause waiting for its first sample
        self._release_before = getattr(self.motion, "release_before", None)  # a stored plan's pages

    def begin(self, approach: Transition) -> None:
        """From the start: the checked approach, then the plan from its first sample."""
        self.segment_index, self.plan_index = 0, -1
        self.transition, self.transition_index, self.pending_pause = approach, 0, None

    def arm_pause(self, pause: Transition) -> None:
        """The plan plays on to its sample `pause.after_index`, then the pause takes over."""
        self.pending_pause = pause

    def play_transition(self, transition: Transition) -> None:
        self.transition, self.transition_index = transition, 0

    def abandon(self) -> None:
        """A stop: no checked motion plays on (the tick's stop ramp takes over)."""
        self.transition, self.pending_pause = None, None

    def limits(self, segment: int | None = None) -> SessionLimits:
        """The motion limits of `segment`; by default of what plays now (a transition's, or the plan's)."""
        if segment is None:
            segment = self.transition.segment if self.transition is not None else self.segment_index
        return self.plan.segments[segment].motion_limits

    def advance(self, step: int, out: np.ndarray) -> None:
        """The checked sample for this time into `out`: `step` samples on (more than one after a late tick)."""
        transition = self.transition
        if transition is not None:
            index = self.transition_index + step
            last = len(transition.poses) - 1
            following = transition.resume_index  # None: a pause, which ends parked at neutral
            if index < last or (index == last and following is not None):
                self.transition_index = index
                out[:] = transition.poses[index]
                return
            self.transition = None
            if following is None:
                out[:] = transition.poses[last]
                self._phases.phase_finished()
                return
            if transition.kind == "approach":
                self._phases.phase_finished()  # into the plan
            self._play_plan(following + index - last - 1, out)
            return
        self._play_plan(self.plan_index + step, out)

    def _play_plan(self, index: int, out: np.ndarray) -> None:
        motion = self.motion
        pause = self.pending_pause
        if pause is not None and index > pause.after_index:
            self.pending_pause = None
            self.transition, self.transition_index = pause, 0
            self._phases.pause_begins()
            self.advance(index - pause.after_index, out)
            return
        last = motion.samples - 1
        if self.plan_index == last:  # the last sample (neutral, at rest) went out in the previous tick
            out[:] = motion.poses[last]
            self._phases.plan_finished()
            return
        self.plan_index = min(index, last)
        out[:] = motion.poses[self.plan_index]
        if self._release_before is not None and self.plan_index % RELEASE_EVERY_SAMPLES == 0:
            self._release_before(self.plan_index - RELEASE_BEHIND_SAMPLES)
        segment = int(motion.segment[self.plan_index])
        if segment != self.segment_index:
            self.segment_index = segment
            self._use_limits(self.limits(segment))

    def segment_time_s(self, period_s: float) -> float:
        """Time into the current segment's samples (its cue, then its return to neutral)."""
        if self.plan_index < 0:
            return 0.0
        return float(self.plan_index - self.motion.segment_start[self.segment_index]) * period_s

    def cue(self) -> np.ndarray | None:
        """The prescribed cue (specific force, angular velocity) of the plan sample played last, while the
        plan itself plays (not a transition); None otherwise."""
        if self.transition is not None or self.plan_index < 0:
            return None
        return self.motion.cue[self.plan_index]
