"""Perception at the patient's head (issue 14 §2): the lever arm of platform rotation, and the tilt-rate
check against the perception threshold."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.fidelity import fidelity
from core.physics import GRAVITY_M_S2
from core.washout import WashoutTrajectory

DT = 0.001
HEAD_HEIGHT_M = 1.6


def _pure_roll(seconds: float = 4.0, amplitude_rad: float = 0.1, omega_rad_s: float = 2.0) -> dict[str, np.ndarray]:
    """Roll φ = A(1 − cos Ωt) about the foot-plate frame's origin, with exact rates and accelerations."""
    time_s = np.arange(round(seconds / DT)) * DT
    roll = amplitude_rad * (1.0 - np.cos(omega_rad_s * time_s))
    rate = amplitude_rad * omega_rad_s * np.sin(omega_rad_s * time_s)
    acceleration = amplitude_rad * omega_rad_s**2 * np.cos(omega_rad_s * time_s)
    pose, velocity, accel = (np.zeros((len(time_s), 6)) for _ in range(3))
    pose[:, 3], velocity[:, 3], accel[:, 3] = roll, rate, acceleration
    return {
        "pose": pose, "velocity": velocity, "acceleration": accel, "roll": roll, "rate": rate, "accel": acceleration
    }  # fmt: skip


def _analytic_head_force(motion: dict[str, np.ndarray], head_height_m: float) -> np.ndarray:
    """Head at (0, 0, h): f = (0, g sin φ − h φ̈, g (cos φ − 1) − h φ̇²), head axes, relative to standing."""
    roll, rate, accel = motion["roll"], motion["rate"], motion["accel"]
    force = np.zeros((len(roll), 3))
    force[:, 1] = GRAVITY_M_S2 * np.sin(roll) - head_height_m * accel
    force[:, 2] = GRAVITY_M_S2 * (np.cos(roll) - 1.0) - head_height_m * rate**2
    return force


def test_fidelity_is_judged_at_the_head_a_pure_roll_gives_the_lever_arm_force() -> None:
    """Cue = the analytic specific force at a head 1.6 m above the foot plates: perfectly delivered."""
    motion = _pure_roll()
    trajectory = WashoutTrajectory(
        DT, motion["pose"], motion["velocity"], motion["acceleration"],
        np.zeros(len(motion["roll"]), bool), np.zeros(len(motion["roll"]), bool),
    )  # fmt: skip
    angular = np.zeros((len(motion["roll"]), 3))
    angular[:, 0] = motion["rate"]
    metrics = fidelity(trajectory, _analytic_head_force(motion, HEAD_HEIGHT_M), angular)
    assert np.max(metrics.specific_force_error_peak_m_s2) < 1e-9, metrics.specific_force_error_peak_m_s2
    assert np.max(metrics.angular_velocity_error_peak_rad_s) < 1e-12


def test_head_specific_force_matches_the_analytic_lever_arm_case() -> None:
    from core.perception import head_specific_force

    motion = _pure_roll()
    force = head_specific_force(motion["pose"].T, motion["velocity"].T, motion["acceleration"].T, HEAD_HEIGHT_M).T
    expected = _analytic_head_force(motion, HEAD_HEIGHT_M)
    assert np.max(np.abs(force - expected)) < 1e-12
    # The lever arm is what separates the head from the rotation centre: h φ̈ is up to 1.6 × 0.4 m/s² here.
    centre = head_specific_force(motion["pose"].T, motion["velocity"].T, motion["acceleration"].T, 0.0).T
    assert np.max(np.abs(centre[:, 1] - force[:, 1])) == pytest.approx(HEAD_HEIGHT_M * 0.1 * 4.0, rel=1e-3)


def test_pitch_yaw_and_translation_lever_arm_against_finite_differences_of_the_head_position() -> None:
    """General motion: the analytic formula equals Rᵀ(d²/dt² of the head's inertial position + g) − g."""
    from core.kinematics import rotation_matrices
    from core.perception import head_specific_force

    time_s = np.arange(4000) * DT
    pose = np.stack(
        [0.05 * np.sin(time_s), -0.03 * np.sin(1.7 * time_s), 0.02 * np.cos(0.9 * time_s),
         0.1 * np.sin(1.3 * time_s), -0.08 * np.sin(2.1 * time_s), 0.12 * np.sin(0.7 * time_s)], axis=1,
    )  # fmt: skip
    velocity = np.gradient(pose, DT, axis=0, edge_order=2)
    acceleration = np.gradient(velocity, DT, axis=0, edge_order=2)
    rotations = rotation_matrices(pose[:, 3:])
    head = pose[:, :3] + rotations @ np.array([0.0, 0.0, HEAD_HEIGHT_M])
    head_acceleration = np.gradient(np.gradient(head, DT, axis=0, edge_order=2), DT, axis=0, edge_order=2)
    standing = np.array([0.0, 0.0, GRAVITY_M_S2])
    expected = np.einsum("nji,nj->ni", rotations, head_acceleration + standing) - standing
    force = head_specific_force(pose.T, velocity.T, acceleration.T, HEAD_HEIGHT_M).T
    inner = slice(10, -10)
    assert np.max(np.abs(force[inner] - expected[inner])) < 1e-4


def test_head_height_comes_from_the_patient_or_a_default() -> None:
    from core.perception import DEFAULT_HEAD_HEIGHT_M, head_height_m

    assert head_height_m(None) == DEFAULT_HEAD_HEIGHT_M == 1.6
    assert 1.5 < head_height_m(1.70) < 1.65  # ear level, about 93 % of stature
    with pytest.raises(ValueError, match="height_m"):
        head_height_m(-1.0)


def test_section_5_tilt_rate_is_flagged_above_the_roll_perception_threshold() -> None:
    """The paper's tilt (peak 0.147 rad/s) is perceptible by the product's own 3 °/s roll threshold."""
    from core.perception import tilt_rate_check
    from core.washout import paper_tilt_parameters, washout_batch

    force = np.zeros((round(25.0 / DT), 3))
    force[: round(10.0 / DT), 1] = 0.2 * GRAVITY_M_S2
    trajectory = washout_batch(paper_tilt_parameters(), DT, force, np.zeros_like(force))
    check = tilt_rate_check(trajectory.pose, trajectory.velocity, DT)
    assert check.above_threshold and check.axis == "roll"
    assert check.peak_rate_rad_s == pytest.approx(0.147, abs=0.003)
    assert check.threshold_rad_s == pytest.approx(math.radians(3.0))
    assert 0.0 < check.first_time_s < 1.0
    slow = washout_batch(paper_tilt_parameters(), DT, 0.02 * force, np.zeros_like(force))
    assert not tilt_rate_check(slow.pose, slow.velocity, DT).above_threshold
