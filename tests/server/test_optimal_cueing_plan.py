"""A prescription with `"cueing": "optimal"` (issue 14 §3–4): planned at load time, honoured by the worker's
own offline check at every sample, and played by the tick pipeline as planned."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.clearance import STOP_CLEARANCE_MARGIN_M, min_clearance
from core.layout import LayoutCandidate
from core.optimal_cueing import CueingWorkspace
from core.perception import tilt_rate_check
from core.physics import GRAVITY_M_S2
from core.plan.build import check_prescription, plan_prescription
from core.plan.check import check_plan
from core.plan.prescription import PrescriptionError
from core.plan.rejection import PrescriptionRejected
from core.robot import TwinRobot, default_twin
from server.hal.kinematic import KinematicHal
from server.realtime.pipeline import TickPipeline, start_along_checked_approach
from server.realtime.supervisor import SupervisorConfig
from server.realtime.telemetry import SupervisorState

# The paper's §4.3 lateral step (0.2 g, held 10 s): the classical washout's plan breaks the twin's limits.
PAPER_STEP = {"kind": "step", "axis": "y", "final_m_s2": 0.2 * GRAVITY_M_S2, "end_time_s": 10.0}


@pytest.fixture(scope="module")
def twin() -> TwinRobot:
    return default_twin()


@pytest.fixture(scope="module")
def optimal_step_plan(twin: TwinRobot):
    return plan_prescription({"cueing": "optimal", "segments": [{"cue": PAPER_STEP, "duration_s": 14.0}]}, twin)


def test_classical_refuses_the_paper_step_that_optimal_cueing_plans_within_every_limit(twin, optimal_step_plan) -> None:
    with pytest.raises(PrescriptionRejected):
        check_prescription({"segments": [{"cue": PAPER_STEP, "duration_s": 14.0}]}, twin)
    report = check_plan(optimal_step_plan, twin)  # the worker's own check: raises at the first breach
    assert report.samples > 14_000 and max(report.peak_use.values()) <= 1.0
    poses = optimal_step_plan.segments[0].planned_poses
    assert poses is not None and np.max(poses[:, 3]) > 0.05  # it tilts: the sustained cue is carried by gravity
    check = tilt_rate_check(poses, np.gradient(poses, 0.001, axis=0), 0.001)
    assert not check.above_threshold, check


def test_the_pipeline_plays_the_planned_trajectory(twin, optimal_step_plan) -> None:
    hal = KinematicHal(twin, 0.001, communication_timeout_s=60.0)
    hal.configure()
    pipeline = TickPipeline(twin, hal, 1000, SupervisorConfig(), lambda *_: None)
    pipeline.load(optimal_step_plan)
    pipeline.heartbeat()
    start_along_checked_approach(pipeline)
    planned = optimal_step_plan.segments[0].planned_poses
    played = []
    for _ in range(8000):
        pipeline.heartbeat()
        pipeline.tick(0)
        if pipeline.supervisor.phase.name == "CUE" and 0 <= pipeline.source.plan_index < len(planned):
            played.append((pipeline.source.plan_index, pipeline.pose.copy()))
        assert pipeline.supervisor.state is SupervisorState.RUNNING
    assert len(played) > 3000
    ticks = np.array([tick for tick, _ in played])
    assert np.max(np.abs(np.array([pose for _, pose in played]) - planned[ticks])) < 1e-12


def test_an_unknown_cueing_algorithm_is_refused_naming_the_field(twin) -> None:
    with pytest.raises(PrescriptionError) as refused:
        plan_prescription({"cueing": "psychic", "segments": [{"cue": PAPER_STEP, "duration_s": 14.0}]}, twin)
    assert refused.value.field == "cueing" and "optimal" in refused.value.limit


# A buildable layout of the study's space (core.layout) where clearance binds: bases 0.93 m off the centre
# line, yawed 4° inward, so that the inner sliders 4 of the two robots close in as the stance surges
# backward (38.8 mm at neutral, 25 mm — the robot's 5 mm plus the 20 mm stop margin — near 0.1 m of surge).
CLOSE_LAYOUT = LayoutCandidate(0.93, 0.0, math.radians(4.0), 0.4, True)
SURGE_SINE = {"kind": "sine", "axis": "x", "amplitude_m_s2": 1.0, "frequency_hz": 0.4}


def test_the_optimal_plan_keeps_the_collision_clearance_the_worker_checks() -> None:
    """§3 constraints: the plan keeps the clearance of the twin's parts (core.clearance) with the margin the
    independent check enforces (SessionLimits.clearance_min_m plus the stop margin), at every sample."""
    twin = CLOSE_LAYOUT.twin()
    plan = plan_prescription({"cueing": "optimal", "segments": [{"cue": SURGE_SINE, "duration_s": 8.0}]}, twin)
    report = check_plan(plan, twin)  # the worker's own check: raises at the first breach, collision included
    assert report.samples > 8_000
    poses = plan.segments[0].planned_poses
    assert poses is not None
    clearance = min_clearance(twin, poses).clearance_m
    margin = plan.segments[0].motion_limits.clearance_min_m
    assert margin == pytest.approx(twin.parts.clearance_min_m + SupervisorConfig().clearance_margin_m)
    # Not vacuous: the constraint is what stops the surge (within 6 mm of the margin; unconstrained: 14 mm) ...
    assert margin <= float(np.min(clearance)) < margin + 0.006
    # ... and the plan still surges both ways (the cue is given as far as the clearance lets it).
    assert np.min(poses[:, 0]) < -0.05 and np.max(poses[:, 0]) > 0.1


def test_the_planner_keeps_the_clearance_margin_the_offline_check_enforces(twin, monkeypatch) -> None:
    """The planner's clearance row uses the segment's own margin, so a non-default stop margin is honoured
    (and by default it is the one `check_plan` requires)."""
    workspaces: list[CueingWorkspace] = []
    original_init = CueingWorkspace.__post_init__

    def recording_init(self: CueingWorkspace) -> None:
        original_init(self)
        workspaces.append(self)

    monkeypatch.setattr(CueingWorkspace, "__post_init__", recording_init)
    body = {"cueing": "optimal", "segments": [{"cue": PAPER_STEP, "duration_s": 14.0}]}
    for margin_m in (STOP_CLEARANCE_MARGIN_M, 0.035):
        plan = plan_prescription(body, twin, config=SupervisorConfig(clearance_margin_m=margin_m))
        required = plan.segments[0].motion_limits.clearance_min_m
        assert required == pytest.approx(twin.parts.clearance_min_m + margin_m)
        assert workspaces[-1].minimum_clearance_m == pytest.approx(required)
