"""The checked transitions of the plan a worker holds: built and checked here, outside the real-time
worker, then sent to it (issue 21: the patient feels only what was checked).

- start: the approach from where the platform stands (the worker's latest measured pose) to neutral;
- pause: leaving the plan a little ahead of the sample being played (the lead: time to build and check it);
- resume: from neutral, where a pause parks, back into the plan just after the sample the pause left it.

The robot daemon uses it for every run; the command line and the benchmarks drive a worker with it too.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np

from core.plan.check import checked_approach, checked_pause, checked_resume
from server.errors import ConflictError

if TYPE_CHECKING:
    from core.plan.build import PrescriptionPlan
    from core.plan.motion import Transition
    from core.robot import TwinRobot

PAUSE_LEAD_S = 0.3  # a pause begins this long after it is asked for (at least): it is built and checked first
PAUSE_ATTEMPTS = 3  # each with twice the lead, when building and checking took longer than the lead


class Playback:
    def __init__(self, twin: TwinRobot, plan: PrescriptionPlan) -> None:
        self.twin, self.plan = twin, plan
        self.paused_after: int | None = None  # the last plan sample before the latest pause

    def start(self, worker: Any, estop_generation: int | None = None) -> None:
        measured = np.asarray(worker.latest_state()["measured_stance_pose"], dtype=float)
        worker.start_motion(checked_approach(self.plan, self.twin, measured), estop_generation=estop_generation)
        self.paused_after = None

    def prepare(self, command: str, worker: Any) -> Transition:
        """The checked pause or resume for the run `worker` plays now (built and checked in the caller's
        thread: the robot daemon does it outside its lock, so that a stop never waits for a check)."""
        return self._pause_transition(worker) if command == "pause" else self._resume_transition()

    def send(self, worker: Any, transition: Transition) -> None:
        """Arm the prepared pause, or resume along the prepared blend; the worker refuses a pause that
        would begin at a sample it has played already."""
        if transition.kind == "pause":
            worker.pause(transition)
            self.paused_after = transition.after_index
        else:
            worker.resume(transition)

    def pause(self, worker: Any) -> None:
        """Arm a checked pause that begins ahead of the sample being played."""
        self.send(worker, self._pause_transition(worker))

    def resume(self, worker: Any) -> None:
        """Back into the plan just after the sample the pause left it, along a checked blend from neutral."""
        self.send(worker, self._resume_transition())

    def _pause_transition(self, worker: Any) -> Transition:
        rate = self.plan.control_rate_hz
        lead = round(PAUSE_LEAD_S * rate)
        last = self.plan.played.samples - 1
        for _ in range(PAUSE_ATTEMPTS):
            began = time.monotonic()
            after = max(self._plan_index(worker), 0) + lead
            if after >= last:
                raise ConflictError("pause: the session ends before a pause could begin; it is returning to neutral")
            transition = checked_pause(self.plan, self.twin, after)
            elapsed = round((time.monotonic() - began) * rate)
            if self._plan_index(worker) < after - max(lead // 4, 1):  # still well ahead of the plan
                return transition
            lead = 2 * max(lead, elapsed)
        raise ConflictError(f"pause: the pause could not be checked ahead of the motion in {PAUSE_ATTEMPTS} tries")

    def _resume_transition(self) -> Transition:
        if self.paused_after is None:
            raise ConflictError("resume: the run was not paused")
        return checked_resume(self.plan, self.twin, self.paused_after + 1)

    @staticmethod
    def _plan_index(worker: Any) -> int:
        return int(worker.latest_state().get("plan_index", -1))


def plan_and_load(
    worker: Any,
    prescription: dict[str, Any],
    patient: dict[str, Any] | None = None,
    *,
    estop_generation: int | None = None,
) -> tuple[Playback, dict[str, Any]]:
    """Plan and check `prescription` in this process (as the daemon's planning process does), load it into
    `worker` (a `WorkerClient`) and return its playback and check report; raises the refusal. For the
    command line, the benchmarks and tests that drive a worker without a daemon."""
    from core.robot import default_twin, load_twin
    from server.robotd.planner import checked_plan

    twin = load_twin(worker.twin_path) if worker.twin_path else default_twin()
    plan, report = checked_plan(twin, worker.control_rate_hz, worker.supervisor_config, prescription, patient)
    worker.load_plan(plan, report, estop_generation=estop_generation)
    return Playback(twin, plan), report
