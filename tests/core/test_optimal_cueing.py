"""Optimal cueing with preview (issue 14 §3): the spline, the fidelity it reaches on a cue that fits the
workspace, its own limits, and its settings."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.clearance import min_clearance
from core.fidelity import fidelity
from core.optimal_cueing import (
    CueingError,
    CueingWorkspace,
    OptimalCueingParameters,
    OptimalCueingPlanner,
    evaluate_spline,
    workspace_quantities,
)
from core.perception import head_angular_velocity, tilt_rate_check
from core.robot import default_twin
from core.shaping import FIRST_MODE_HZ
from core.vestibular import VestibularModel
from core.washout import WashoutTrajectory

DT = 0.001


@pytest.fixture(scope="module")
def workspace() -> CueingWorkspace:
    twin = default_twin()
    robots = [twin.robot_for(side) for side in twin.sides]
    return CueingWorkspace(
        twin,
        twin.robot.limits,
        np.concatenate([r.stroke_min_m for r in robots]),
        np.concatenate([r.stroke_max_m for r in robots]),
    )


def _smooth_sine(seconds: float, amplitude_m: float, frequency_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """The lateral acceleration of a sway y = A sin(2πft) sin²(πt/D): a sine that starts and ends at rest at
    neutral, so a platform that fits it can deliver it exactly (a cue that drifts could not return)."""
    time_s = np.arange(round(seconds / DT)) * DT
    omega, window = 2 * np.pi * frequency_hz, np.pi / seconds
    sway = amplitude_m * np.sin(omega * time_s) * np.sin(window * time_s) ** 2
    force = np.zeros((len(time_s), 3))
    force[:, 1] = np.gradient(np.gradient(sway, DT), DT)
    return force, np.zeros_like(force)


def _trajectory(pose: np.ndarray) -> WashoutTrajectory:
    velocity = np.gradient(pose, DT, axis=0)
    acceleration = np.gradient(velocity, DT, axis=0)
    flags = np.zeros(len(pose), dtype=bool)
    return WashoutTrajectory(DT, pose, velocity, acceleration, flags, flags)


@pytest.fixture(scope="module")
def sine_plan(workspace: CueingWorkspace):
    force, rates = _smooth_sine(8.0, 0.03, 0.3)  # ±0.1 m/s², 3 cm of sway
    return force, rates, OptimalCueingPlanner(workspace).plan(force, rates, DT)


def test_a_small_slow_sine_is_reproduced_at_the_head_within_5_percent(sine_plan) -> None:
    """Bound: the perceived specific-force error at the head is below 5 % of the perceived cue (RMS)."""
    force, rates, plan = sine_plan
    metrics = fidelity(_trajectory(plan.pose), force, rates)
    perceived_cue = VestibularModel(sample_period_s=DT).perceive_specific_force(force)
    cue_rms = float(np.sqrt(np.mean(perceived_cue[:, 1] ** 2)))
    assert metrics.specific_force_error_rms_m_s2[1] < 0.05 * cue_rms, (metrics.specific_force_error_rms_m_s2, cue_rms)
    assert np.all(metrics.angular_velocity_error_rms_rad_s < math.radians(0.5))


def test_the_plan_starts_and_ends_at_rest_at_neutral_and_stays_in_the_workspace(sine_plan, workspace) -> None:
    _, _, plan = sine_plan
    pose = plan.pose
    # Exactly, not nearly: three zero control points at each end.
    assert np.array_equal(pose[0], np.zeros(6)) and np.array_equal(pose[-1], np.zeros(6))
    low, high = workspace.quantity_bounds(1.0)
    quantities = workspace_quantities(workspace, pose[::10])
    assert np.all(np.isfinite(quantities)) and np.all((quantities >= low) & (quantities <= high))
    check = tilt_rate_check(pose, np.gradient(pose, DT, axis=0), DT)
    assert not check.above_threshold


def test_the_first_natural_frequency_is_kept_out_without_a_post_filter(sine_plan) -> None:
    """The jerk penalty and the spline leave the first-mode band ≥ 40 dB below the motion's peak."""
    _, _, plan = sine_plan
    acceleration = np.gradient(np.gradient(plan.pose[:, 1], DT), DT)
    spectrum = np.abs(np.fft.rfft(acceleration * np.hanning(len(acceleration))))
    frequency = np.fft.rfftfreq(len(acceleration), DT)
    band = (frequency > 0.9 * FIRST_MODE_HZ) & (frequency < 1.1 * FIRST_MODE_HZ)
    assert 20 * np.log10(spectrum.max() / spectrum[band].max()) > 40.0


def test_rotation_the_cue_does_not_ask_for_stays_below_the_configured_threshold(workspace) -> None:
    """A sustained lateral cue: optimal cueing tilts (gravity carries it) but never faster than 1.5 °/s."""
    time_s = np.arange(round(8.0 / DT)) * DT
    force = np.zeros((len(time_s), 3))
    force[:, 1] = 1.0 * np.clip(time_s / 0.5, 0, 1) * np.clip((6.5 - time_s) / 0.5, 0, 1)
    params = OptimalCueingParameters(roll_rate_threshold_rad_s=math.radians(1.5))
    plan = OptimalCueingPlanner(workspace, params).plan(force, np.zeros_like(force), DT)
    rates = head_angular_velocity(plan.pose.T, np.gradient(plan.pose, DT, axis=0).T).T
    assert np.max(np.abs(rates[:, 0])) <= math.radians(1.5) * 1.02
    assert np.max(plan.pose[:, 3]) > 0.02  # it does tilt: the sustained part is carried by gravity


def test_spline_evaluation_matches_the_knot_formulas() -> None:
    rng = np.random.default_rng(3)
    control = rng.normal(size=(12, 6))
    period = 0.04
    knots = np.arange(1, 9) * period
    pose = evaluate_spline(control, period, knots)
    expected = (control[1:9] + 4 * control[2:10] + control[3:11]) / 6  # row k + 1 holds c_k
    assert np.max(np.abs(pose - expected)) < 1e-12


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"knot_period_s": 0.5}, "knot_period_s"),
        ({"jerk_weight": -1.0}, "jerk_weight"),
        ({"roll_rate_threshold_rad_s": 0.0}, "roll_rate_threshold_rad_s"),
        ({"overlap_s": 20.0}, "overlap_s"),
        ({"limit_fraction": 1.5}, "limit_fraction"),
        ({"head_height_m": float("nan")}, "head_height_m"),
    ],
)
def test_invalid_settings_name_the_field(changes: dict[str, float], field: str) -> None:
    with pytest.raises(CueingError) as refused:
        OptimalCueingParameters(**changes)
    assert refused.value.field == field
    with pytest.raises(CueingError, match="unknown"):
        OptimalCueingParameters.from_dict({"colour": 1})


def test_bad_cues_are_refused(workspace) -> None:
    planner = OptimalCueingPlanner(workspace)
    with pytest.raises(CueingError, match="specific_force_m_s2"):
        planner.plan(np.zeros((100, 2)), np.zeros((100, 3)), DT)
    with pytest.raises(CueingError, match="duration_s"):
        planner.plan(np.zeros((50, 3)), np.zeros((50, 3)), DT)


def test_a_clearance_function_is_a_constraint_of_the_plan(workspace: CueingWorkspace) -> None:
    """The hook for the twin's collision model: here a fake wall 2 cm to each side of neutral."""
    force, rates = _smooth_sine(8.0, 0.03, 0.3)  # asks for 3 cm of sway
    walled = CueingWorkspace(
        workspace.twin,
        workspace.limits,
        workspace.stroke_min_m,
        workspace.stroke_max_m,
        clearance_m=lambda poses: 0.02 - np.abs(poses[:, 1]),
        clearance_min_m=0.0,
    )
    plan = OptimalCueingPlanner(walled).plan(force, rates, DT)
    assert 0.015 < np.max(np.abs(plan.pose[:, 1])) <= 0.02


def test_the_twin_clearance_feeds_the_planner_by_default(workspace: CueingWorkspace) -> None:
    """§3 constraints: without a clearance function the workspace uses the twin's own parts (core.clearance,
    as the IK and the independent check see them) with the robot's margin plus the 20 mm stop margin."""
    poses = np.zeros((3, 6))
    poses[:, 1] = [0.0, 0.05, -0.1]
    quantities = workspace_quantities(workspace, poses)
    expected = min_clearance(workspace.twin, poses).clearance_m
    assert quantities.shape[1] == 40
    np.testing.assert_allclose(quantities[:, -1], expected, atol=1e-12)
    assert workspace.minimum_clearance_m == pytest.approx(workspace.twin.parts.clearance_min_m + 0.02)
    low, _ = workspace.quantity_bounds(1.0)
    assert low[-1] == pytest.approx(workspace.minimum_clearance_m)
