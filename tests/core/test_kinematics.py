"""Kinematics (core/kinematics/): paper check values, IK/FK round trip, Jacobians, limits, the twin."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from core.kinematics import (
    ForwardKinematics,
    ForwardKinematicsError,
    LegViolation,
    UnreachablePoseError,
    condition_number,
    euler_from_rotation,
    forward_kinematics,
    inverse_kinematics,
    platform_twists,
    pose_jacobian,
    rotation_matrices,
    slider_velocities,
    stance_origin_world,
    twin_inverse_kinematics,
    twin_platform_poses,
    twist_jacobian,
)
from core.robot import SSPRobot, TwinRobot, rotation_matrix

NEUTRAL_SLIDERS_MM = [793.13, 1209.09, 965.26, -965.26, -1209.09, -793.13]
ROLL_20_SLIDERS_MM = [885.05, 1166.37, 831.88, -831.88, -1166.37, -885.05]  # paper §3.1.2


def neutral(robot: SSPRobot) -> np.ndarray:
    return np.asarray(robot.neutral_pose, dtype=float)


def random_reachable_poses(robot: SSPRobot, count: int, seed: int) -> np.ndarray:
    """Seeded poses spread over the reachable workspace (every limit, singularity margin included)."""
    rng = np.random.default_rng(seed)
    span = np.array([0.6, 0.3, 0.3, math.radians(30), math.radians(18), math.radians(30)])
    candidates = neutral(robot) + rng.uniform(-1.0, 1.0, (count * 40, 6)) * span
    reachable = candidates[inverse_kinematics(robot, candidates, check=False).reachable]
    assert len(reachable) >= count, "the sampling box should hold enough reachable poses"
    return reachable[:count]


# --- Paper check values ---------------------------------------------------------------------------


def test_neutral_pose_reproduces_reference_check_values(robot: SSPRobot) -> None:
    sliders_mm = inverse_kinematics(robot, neutral(robot)).slider_positions_m[0] * 1e3
    np.testing.assert_allclose(sliders_mm, NEUTRAL_SLIDERS_MM, atol=0.01)


def test_paper_roll_20_degrees_reproduces_published_sliders(robot: SSPRobot) -> None:
    pose = [0.0, 0.0, 0.6, math.radians(20.0), 0.0, 0.0]
    sliders_mm = inverse_kinematics(robot, pose).slider_positions_m[0] * 1e3
    np.testing.assert_allclose(sliders_mm, ROLL_20_SLIDERS_MM, atol=0.01)


def test_batch_gives_the_same_numbers_as_single_poses(robot: SSPRobot) -> None:
    poses = random_reachable_poses(robot, 10_000, seed=11)  # spans several internal chunks
    batch = inverse_kinematics(robot, poses).slider_positions_m
    singles = np.array([inverse_kinematics(robot, p).slider_positions_m[0] for p in poses[::997]])
    np.testing.assert_array_equal(batch[::997], singles)


def test_rotation_is_rx_ry_rz_and_euler_angles_invert_it() -> None:
    angles = np.random.default_rng(5).uniform(-1.2, 1.2, (200, 3))
    rotations = rotation_matrices(angles)
    for (roll, pitch, yaw), rotation in zip(angles[:5], rotations[:5], strict=True):
        c, s = math.cos, math.sin
        rx = np.array([[1, 0, 0], [0, c(roll), -s(roll)], [0, s(roll), c(roll)]])
        ry = np.array([[c(pitch), 0, s(pitch)], [0, 1, 0], [-s(pitch), 0, c(pitch)]])
        rz = np.array([[c(yaw), -s(yaw), 0], [s(yaw), c(yaw), 0], [0, 0, 1]])
        np.testing.assert_allclose(rotation, rx @ ry @ rz, atol=1e-15)
        np.testing.assert_allclose(rotation, rotation_matrix(roll, pitch, yaw), atol=1e-15)
    np.testing.assert_allclose(euler_from_rotation(rotations), angles, atol=1e-12)


# --- Forward kinematics -------------------------------------------------------------------------------


def test_fk_of_ik_returns_the_pose_for_thousands_of_random_poses(robot: SSPRobot) -> None:
    poses = random_reachable_poses(robot, 5000, seed=2024)
    sliders = inverse_kinematics(robot, poses).slider_positions_m
    # Warm start from a guess much farther off than one 1 kHz tick: up to 20 mm and 2° per axis.
    offsets = np.random.default_rng(2025).uniform(-1.0, 1.0, poses.shape) * ([0.02] * 3 + [math.radians(2)] * 3)
    guesses = poses + offsets
    # A guess must be a possible pose itself (every rod on its rail).
    possible = ~np.any(inverse_kinematics(robot, guesses, check=False).violations & LegViolation.ROD_CANNOT_REACH, 1)
    assert possible.sum() > 4500
    poses, sliders, guesses = poses[possible], sliders[possible], guesses[possible]
    found, iterations, residuals = forward_kinematics(robot, sliders, guesses)
    assert np.max(np.abs(found[:, :3] - poses[:, :3])) < 1e-9  # 1e-6 mm
    assert np.max(np.abs(found[:, 3:] - poses[:, 3:])) < 1e-8  # rad
    assert np.all(residuals <= 1e-12)
    assert np.all(iterations >= 1)


def test_cold_start_fk_finds_the_pose_or_refuses_never_a_wrong_pose(robot: SSPRobot) -> None:
    poses = random_reachable_poses(robot, 2000, seed=2027)
    sliders = inverse_kinematics(robot, poses).slider_positions_m
    solver = ForwardKinematics(robot)
    solved = 0
    for pose, slider_set in zip(poses, sliders, strict=True):
        try:
            result = solver.solve(slider_set, guess=neutral(robot))
        except ForwardKinematicsError:
            continue  # another assembly mode lay nearer along the way: refused, which is allowed
        np.testing.assert_allclose(result.pose, pose, atol=1e-9)
        solved += 1
    assert solved >= 0.99 * len(poses)


def test_warm_started_fk_follows_a_1khz_trajectory_in_few_iterations(robot: SSPRobot) -> None:
    time_s = np.arange(0.0, 3.0, 1e-3)
    poses = np.tile(neutral(robot), (len(time_s), 1))
    poses[:, 0] += 0.3 * np.sin(2 * np.pi * 0.4 * time_s)
    poses[:, 1] += 0.05 * np.sin(2 * np.pi * 0.3 * time_s)
    poses[:, 2] += 0.05 * np.sin(2 * np.pi * 0.5 * time_s)
    poses[:, 3] += math.radians(4) * np.sin(2 * np.pi * 0.7 * time_s)
    poses[:, 4] += math.radians(6) * np.sin(2 * np.pi * 0.6 * time_s)
    poses[:, 5] += math.radians(15) * np.sin(2 * np.pi * 0.2 * time_s)
    sliders = inverse_kinematics(robot, poses).slider_positions_m
    solver = ForwardKinematics(robot)
    solver.reset(poses[0])
    results = [solver.solve(s) for s in sliders]
    found = np.array([r.pose for r in results])
    assert np.max(np.abs(found[:, :3] - poses[:, :3])) < 1e-9
    assert np.max(np.abs(found[:, 3:] - poses[:, 3:])) < 1e-8
    assert max(r.iterations for r in results) <= 5
    assert max(r.residual_m for r in results) <= 1e-12


def test_fk_with_impossible_sliders_raises(robot: SSPRobot) -> None:
    # Sliders 1 and 6 share a rail and a platform joint pair 150 mm apart: 3 m apart they cannot be.
    sliders = inverse_kinematics(robot, neutral(robot)).slider_positions_m[0].copy()
    sliders[0] += 1.5
    sliders[5] -= 1.5
    with pytest.raises(ForwardKinematicsError) as error:
        ForwardKinematics(robot).solve(sliders)
    assert error.value.residual_m > 1e-3


def test_fk_out_of_iterations_raises_with_its_count_and_residual(robot: SSPRobot) -> None:
    target = np.array([0.3, 0.1, 0.7, 0.2, -0.1, 0.3])
    sliders = inverse_kinematics(robot, target, check=False).slider_positions_m[0]
    with pytest.raises(ForwardKinematicsError) as error:
        ForwardKinematics(robot, max_iterations=1).solve(sliders, guess=neutral(robot))
    assert error.value.iterations >= 1
    assert error.value.residual_m > 1e-6
    assert "did not converge" in str(error.value)


def test_batch_fk_names_the_slider_set_that_failed(robot: SSPRobot) -> None:
    good = inverse_kinematics(robot, neutral(robot)).slider_positions_m[0]
    impossible = good + np.array([1.5, 0, 0, 0, 0, -1.5])
    with pytest.raises(ForwardKinematicsError) as error:
        forward_kinematics(robot, np.array([good, good, impossible, good]))
    assert error.value.pose_index == 2


def test_fk_refuses_non_finite_sliders(robot: SSPRobot) -> None:
    with pytest.raises(ValueError, match="slider_positions_m"):
        ForwardKinematics(robot).solve(np.array([0.8, 1.2, np.nan, -0.9, -1.2, -0.8]))


# --- Jacobians ------------------------------------------------------------------------------------------


def finite_difference_jacobian(robot: SSPRobot, pose: np.ndarray, step: float = 1e-6) -> np.ndarray:
    steps = np.eye(6) * step
    plus = inverse_kinematics(robot, pose + steps, check=False).slider_positions_m
    minus = inverse_kinematics(robot, pose - steps, check=False).slider_positions_m
    return ((plus - minus) / (2 * step)).T


def test_pose_jacobian_matches_finite_differences(robot: SSPRobot) -> None:
    poses = random_reachable_poses(robot, 50, seed=7)
    analytic = pose_jacobian(robot, poses)
    for pose, jacobian in zip(poses, analytic, strict=True):
        np.testing.assert_allclose(jacobian, finite_difference_jacobian(robot, pose), atol=1e-7)


def test_twist_jacobian_matches_finite_differences_of_small_rotations(robot: SSPRobot) -> None:
    poses = random_reachable_poses(robot, 20, seed=8)
    step = 1e-6
    for pose, jacobian in zip(poses, twist_jacobian(robot, poses), strict=True):
        rotation = rotation_matrices(pose[None, 3:])[0]
        numeric = np.empty((6, 6))
        for axis in range(6):
            moved = []
            for sign in (1.0, -1.0):
                position = pose[:3].copy()
                turned = rotation
                if axis < 3:
                    position[axis] += sign * step
                else:  # a small rotation about the base-frame axis: ω is in the base frame
                    turned = rotation_matrices((np.eye(3)[axis - 3] * sign * step)[None, :])[0] @ rotation
                moved.append(np.concatenate([position, euler_from_rotation(turned)]))
            plus, minus = inverse_kinematics(robot, np.array(moved), check=False).slider_positions_m
            numeric[:, axis] = (plus - minus) / (2 * step)
        np.testing.assert_allclose(jacobian, numeric, atol=1e-7)


def test_slider_velocities_and_twists_round_trip(robot: SSPRobot) -> None:
    poses = random_reachable_poses(robot, 200, seed=9)
    twists = np.random.default_rng(10).normal(0.0, 0.3, (200, 6))
    velocities = slider_velocities(robot, poses, twists)
    np.testing.assert_allclose(platform_twists(robot, poses, velocities), twists, atol=1e-9)


def test_slider_velocities_match_the_motion_of_the_sliders(robot: SSPRobot) -> None:
    pose = neutral(robot)
    twist = np.array([0.1, -0.05, 0.02, 0.0, 0.0, 0.0])  # pure translation: no Euler-rate conversion
    dt = 1e-7
    moved = pose + np.concatenate([twist[:3] * dt, np.zeros(3)])
    sliders = inverse_kinematics(robot, np.array([pose, moved])).slider_positions_m
    np.testing.assert_allclose(slider_velocities(robot, pose, twist)[0], (sliders[1] - sliders[0]) / dt, atol=1e-5)


def test_condition_number_grows_toward_a_singularity(robot: SSPRobot) -> None:
    # The paper geometry has a singularity at roll ≈ −11.1° (finite differences confirm it).
    rolls = np.radians(np.linspace(0.0, -11.0, 23))
    poses = np.tile(neutral(robot), (len(rolls), 1))
    poses[:, 3] = rolls
    condition = condition_number(robot, poses)
    assert np.all(np.diff(condition) > 0)
    assert condition[0] < 15
    assert condition[-1] > 500


def test_jacobian_refuses_a_pose_whose_rods_cannot_reach(robot: SSPRobot) -> None:
    with pytest.raises(UnreachablePoseError, match="rod cannot reach"):
        twist_jacobian(robot, np.array([0.0, 0.0, 1.7, 0.0, 0.0, 0.0]))


# --- Limits: reported per pose, never clamped --------------------------------------------------------


def only_reason(robot: SSPRobot, pose: list[float]) -> set[LegViolation]:
    flags = int(np.bitwise_or.reduce(inverse_kinematics(robot, pose, check=False).violations[0]))
    return {flag for flag in LegViolation if flag and flags & flag}


def test_rod_cannot_reach_is_reported_and_its_sliders_are_nan(robot: SSPRobot) -> None:
    pose = [0.0, 0.0, 1.7, 0.0, 0.0, 0.0]
    solution = inverse_kinematics(robot, pose, check=False)
    assert only_reason(robot, pose) == {LegViolation.ROD_CANNOT_REACH}
    assert np.all(np.isnan(solution.slider_positions_m))
    violation = solution.limit_violations()[0]
    assert violation.reason == "rod cannot reach its rail"
    assert violation.value > violation.limit == robot.rod_length_m


def test_stroke_violation_reports_the_true_slider_position_not_a_clamped_one(robot: SSPRobot) -> None:
    pose = [0.7, 0.0, 0.6, 0.0, 0.0, 0.0]
    solution = inverse_kinematics(robot, pose, check=False)
    assert only_reason(robot, pose) == {LegViolation.STROKE}
    # A pure translation along the rails moves every slider by the same amount.
    np.testing.assert_allclose(solution.slider_positions_m[0] * 1e3, np.add(NEUTRAL_SLIDERS_MM, 700.0), atol=0.01)
    stroke = next(v for v in solution.limit_violations() if v.slider == 2)
    assert stroke.value == pytest.approx(1.20909 + 0.7, abs=1e-5)
    assert stroke.limit == 1.85


def test_base_cone_violation_is_reported(robot: SSPRobot) -> None:
    tight = replace(robot, limits=replace(robot.limits, base_joint_cone_rad=math.radians(3), platform_joint_cone_rad=3))
    pose = [0.0, 0.1, 0.6, 0.0, 0.0, 0.0]
    assert only_reason(tight, pose) == {LegViolation.BASE_CONE}
    assert only_reason(robot, pose) == set()
    violation = inverse_kinematics(tight, pose, check=False).limit_violations()[0]
    assert violation.reason == "slider joint beyond its cone"
    assert violation.value > violation.limit == math.radians(3)


def test_platform_cone_violation_is_reported(robot: SSPRobot) -> None:
    pose = [0.0, 0.0, 0.6, 0.0, 0.0, 0.6]  # yaw 34°
    assert only_reason(robot, pose) == {LegViolation.PLATFORM_CONE}
    violations = inverse_kinematics(robot, pose, check=False).limit_violations()
    assert {v.slider for v in violations} == {4, 5}
    assert all(v.value > v.limit == robot.limits.platform_joint_cone_rad for v in violations)


@pytest.mark.parametrize("pose", [[0.0, 0.0, 0.6, -0.2, 0.0, 0.0], [0.0, 0.0, 0.2, 0.0, 0.0, 0.0]])
def test_pose_near_or_beyond_a_singularity_is_refused(robot: SSPRobot, pose: list[float]) -> None:
    assert only_reason(robot, pose) == {LegViolation.SINGULARITY}
    relaxed = replace(robot, limits=replace(robot.limits, condition_number_max=1e12))
    violations = inverse_kinematics(robot, pose, check=False).limit_violations()
    assert [(v.slider, v.limit) for v in violations] == [(0, robot.limits.condition_number_max)]
    if pose[2] == 0.2:  # only too close: relaxing the limit admits it
        assert only_reason(relaxed, pose) == set()
    else:  # beyond the singularity (another assembly mode): no limit admits it
        assert only_reason(relaxed, pose) == {LegViolation.SINGULARITY}
        assert violations[0].value == math.inf


def test_check_raises_naming_only_the_unreachable_poses(robot: SSPRobot) -> None:
    poses = np.tile(neutral(robot), (4, 1))
    poses[1, 0] = 0.7  # stroke
    poses[3, 2] = 1.7  # rod cannot reach
    with pytest.raises(UnreachablePoseError) as error:
        inverse_kinematics(robot, poses)
    assert {v.pose_index for v in error.value.violations} == {1, 3}
    assert "pose 1, slider 2: slider outside its stroke" in str(error.value)
    solution = inverse_kinematics(robot, poses, check=False)
    np.testing.assert_array_equal(solution.reachable, [True, False, True, False])


@pytest.mark.parametrize("bad", [[0.0, 0.0, np.nan, 0.0, 0.0, 0.0], [0.0, 0.0, 0.6, 0.0, np.inf, 0.0], [0.0] * 5])
def test_invalid_pose_input_is_refused(robot: SSPRobot, bad: list[float]) -> None:
    with pytest.raises(ValueError, match="poses"):
        inverse_kinematics(robot, bad)


# --- The twin ------------------------------------------------------------------------------------------


def foot_plates_world(twin: TwinRobot, stance_poses: np.ndarray) -> dict[str, np.ndarray]:
    """World position of each foot plate, recomputed from the platform poses each robot is given."""
    feet = {}
    for side, (positions, rotations) in twin_platform_poses(twin, stance_poses).items():
        placement = twin.placement(side)
        yaw = rotation_matrices(np.array([[0.0, 0.0, placement.base_yaw_rad]]))[0]
        in_base = positions + rotations @ np.asarray(placement.foot_plate_offset_m)
        feet[side] = np.asarray(placement.base_origin_m) + in_base @ yaw.T
    return feet


def test_twin_feet_move_as_one_rigid_body(twin: TwinRobot) -> None:
    rng = np.random.default_rng(12)
    stance = rng.uniform(-1.0, 1.0, (300, 6)) * np.array([0.2, 0.05, 0.05, 0.08, 0.1, 0.2])
    neutral_feet = foot_plates_world(twin, np.zeros((1, 6)))
    moved_feet = foot_plates_world(twin, stance)
    origin = stance_origin_world(twin)
    stance_rotation = rotation_matrices(stance[:, 3:])
    for side in twin.sides:
        expected = origin + stance[:, :3] + (stance_rotation @ (neutral_feet[side][0] - origin))
        np.testing.assert_allclose(moved_feet[side], expected, atol=1e-12)
    distance = np.linalg.norm(moved_feet["left"] - moved_feet["right"], axis=1)
    np.testing.assert_allclose(distance, 0.4, atol=1e-12)  # the default layout's feet (issue 13; was 0.5)
    # Both platforms turn by the stance rotation (relative to their neutral orientation).
    platforms = twin_platform_poses(twin, stance)
    for side in twin.sides:
        np.testing.assert_allclose(platforms[side][1], stance_rotation, atol=1e-12)


def test_twin_at_neutral_puts_both_robots_at_their_neutral_pose(twin: TwinRobot) -> None:
    solutions = twin_inverse_kinematics(twin, np.zeros(6))
    np.testing.assert_allclose(solutions["right"].slider_positions_m[0] * 1e3, NEUTRAL_SLIDERS_MM, atol=0.01)
    np.testing.assert_allclose(solutions["left"].slider_positions_m[0] * 1e3, NEUTRAL_SLIDERS_MM, atol=0.01)


def test_mirrored_robot_is_symmetric(robot: SSPRobot) -> None:
    poses = random_reachable_poses(robot, 500, seed=13)
    mirror = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])  # y → −y flips y, roll and yaw
    original = inverse_kinematics(robot, poses)
    mirrored = inverse_kinematics(robot.mirrored(), poses * mirror)
    np.testing.assert_allclose(mirrored.slider_positions_m, original.slider_positions_m, atol=1e-12)
    np.testing.assert_array_equal(mirrored.violations, original.violations)


def test_twin_left_robot_sees_the_mirrored_motion_of_the_right(twin: TwinRobot) -> None:
    stance = np.random.default_rng(14).uniform(-1.0, 1.0, (200, 6)) * np.array([0.2, 0.05, 0.05, 0.05, 0.1, 0.1])
    mirror = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])
    direct = twin_inverse_kinematics(twin, stance, check=False)
    mirrored = twin_inverse_kinematics(twin, stance * mirror, check=False)
    np.testing.assert_allclose(direct["left"].slider_positions_m, mirrored["right"].slider_positions_m, atol=1e-12)
    # A motion symmetric about the sagittal plane drives both robots identically.
    symmetric = stance * np.array([1.0, 0.0, 1.0, 0.0, 1.0, 0.0])
    both = twin_inverse_kinematics(twin, symmetric)
    np.testing.assert_allclose(both["left"].slider_positions_m, both["right"].slider_positions_m, atol=1e-12)


def test_twin_unreachable_pose_names_the_robot(twin: TwinRobot) -> None:
    with pytest.raises(UnreachablePoseError, match="left robot") as error:
        # 0.25 rad of stance roll: beyond the default layout's ±12.0° (the old layout stopped at ±11.2°, so
        # 0.2 rad sufficed before issue 13; the side-by-side default reaches it).
        twin_inverse_kinematics(twin, np.array([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.25, 0.0, 0.0]]))
    assert {v.pose_index for v in error.value.violations} == {1}
