"""The twin: two robots, one per foot, driven by one stance pose (both feet move as one rigid body)."""

from __future__ import annotations

from dataclasses import replace

import numba
import numpy as np

from core.kinematics.conditioning import SingularityReport, singularity_report, stretches
from core.kinematics.ik import VIOLATION_REASONS, IKSolution, UnreachablePoseError, as_poses, solve_ik_pose_rotation
from core.kinematics.legs import leg_geometry
from core.kinematics.rotations import euler_from_rotation, rotation_matrices, yaw_matrix
from core.robot import TwinRobot
from core.rotations import rotation_into


def stance_origin_world(twin: TwinRobot) -> np.ndarray:
    """The stance frame's origin: midpoint of the two foot plates at the neutral pose (world, m)."""
    return np.mean([foot_plate_neutral_world(twin, side) for side in twin.sides], axis=0)


def foot_plate_neutral_world(twin: TwinRobot, side: str) -> np.ndarray:
    """Centre of one foot plate at the neutral pose (world, m)."""
    placement, robot = twin.placement(side), twin.robot_for(side)
    neutral = np.asarray(robot.neutral_pose)
    platform_rotation = rotation_matrices(neutral[None, 3:])[0]
    foot_in_base = neutral[:3] + platform_rotation @ np.asarray(placement.foot_plate_offset_m)
    return np.asarray(placement.base_origin_m) + yaw_matrix(placement.base_yaw_rad) @ foot_in_base


@numba.njit(cache=True, nogil=True)
def _platform_poses_kernel(
    stance_poses: np.ndarray,  # (N, 6)
    origin: np.ndarray,  # (3,) stance origin, world
    base_yaw: np.ndarray,  # (2, 3, 3) Y
    base_origin: np.ndarray,  # (2, 3)
    lever_world: np.ndarray,  # (2, 3) platform origin at neutral − stance origin, world
    neutral_rotation_world: np.ndarray,  # (2, 3, 3) N = Y·R(neutral)
    positions_out: np.ndarray,  # (2, N, 3)
    rotations_out: np.ndarray,  # (2, N, 3, 3)
) -> None:
    """p = Yᵀ·(o + t + S·ℓ − o_b) and R = Yᵀ·S·N per stance pose (t, S) and robot."""
    stance_rotation = np.empty((3, 3))
    world_rotation = np.empty((3, 3))
    world = np.empty(3)
    for pose in range(stance_poses.shape[0]):
        rotation_into(stance_poses[pose, 3], stance_poses[pose, 4], stance_poses[pose, 5], stance_rotation)
        for side in range(2):
            for i in range(3):
                lever = stance_rotation[i, 0] * lever_world[side, 0] + stance_rotation[i, 1] * lever_world[side, 1]
                lever += stance_rotation[i, 2] * lever_world[side, 2]
                world[i] = origin[i] + stance_poses[pose, i] + lever - base_origin[side, i]
                for j in range(3):
                    total = stance_rotation[i, 0] * neutral_rotation_world[side, 0, j]
                    total += stance_rotation[i, 1] * neutral_rotation_world[side, 1, j]
                    world_rotation[i, j] = total + stance_rotation[i, 2] * neutral_rotation_world[side, 2, j]
            for i in range(3):
                yaw = base_yaw[side]
                positions_out[side, pose, i] = yaw[0, i] * world[0] + yaw[1, i] * world[1] + yaw[2, i] * world[2]
                for j in range(3):
                    total = yaw[0, i] * world_rotation[0, j] + yaw[1, i] * world_rotation[1, j]
                    rotations_out[side, pose, i, j] = total + yaw[2, i] * world_rotation[2, j]


def twin_platform_poses(twin: TwinRobot, stance_poses: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each robot's platform (positions (N, 3), rotations (N, 3, 3)) in its own base frame, for the
    stance frame moved by `stance_poses` (N, 6) from neutral. Both feet move as one rigid body."""
    stance_poses = as_poses(stance_poses)
    origin = stance_origin_world(twin)
    base_yaw, base_origin, lever_world, neutral_rotation_world = (
        np.empty((2, 3, 3)),
        np.empty((2, 3)),
        np.empty((2, 3)),
        np.empty((2, 3, 3)),
    )
    for index, side in enumerate(twin.sides):
        placement, robot = twin.placement(side), twin.robot_for(side)
        base_yaw[index] = yaw_matrix(placement.base_yaw_rad)
        base_origin[index] = placement.base_origin_m
        neutral = np.asarray(robot.neutral_pose)
        neutral_rotation_world[index] = base_yaw[index] @ rotation_matrices(neutral[None, 3:])[0]
        lever_world[index] = base_origin[index] + base_yaw[index] @ neutral[:3] - origin
    positions, rotations = np.empty((2, len(stance_poses), 3)), np.empty((2, len(stance_poses), 3, 3))
    _platform_poses_kernel(
        np.ascontiguousarray(stance_poses),
        origin,
        base_yaw,
        base_origin,
        lever_world,
        neutral_rotation_world,
        positions,
        rotations,
    )
    return {side: (positions[index], rotations[index]) for index, side in enumerate(twin.sides)}


def twin_inverse_kinematics(
    twin: TwinRobot, stance_poses: np.ndarray, *, check: bool = True, clearance_check: bool = True
) -> dict[str, IKSolution]:
    """IK of both robots for stance-frame poses (N, 6); keys 'right' and 'left'. With `clearance_check`
    (default) every pose is also checked for collisions between the twin's parts (core.clearance):
    COLLISION is set on every leg of both robots where two parts come closer than the margin."""
    stance_poses = as_poses(stance_poses)
    solutions = {}
    platform_poses = twin_platform_poses(twin, stance_poses)
    for side, (positions, rotations) in platform_poses.items():
        poses = np.concatenate([positions, euler_from_rotation(rotations)], axis=1)
        solutions[side] = solve_ik_pose_rotation(twin.robot_for(side), positions, rotations, poses)
    if clearance_check:
        from core.clearance import flag_collisions  # imported here: core.clearance builds on this module

        solutions = flag_collisions(twin, platform_poses, solutions)
    if check:
        for side, solution in solutions.items():
            if not np.all(solution.reachable):
                raise UnreachablePoseError(
                    [replace(v, reason=f"{side} robot: {v.reason}") for v in solution.limit_violations(max_count=50)]
                )
    return solutions


def twin_singularity_report(
    twin: TwinRobot, stance_poses: np.ndarray, times_s: np.ndarray
) -> dict[str, SingularityReport]:
    """Each robot's singularity report (worst cond(J) and when, every det J sign change, every stretch
    beyond the margin) for a stance trajectory sampled at `times_s`."""
    return {
        side: singularity_report(leg_geometry(twin.robot_for(side)), positions, rotations, np.asarray(times_s))
        for side, (positions, rotations) in twin_platform_poses(twin, stance_poses).items()
    }


def violation_stretches(
    solutions: dict[str, IKSolution], times_s: np.ndarray
) -> dict[str, dict[str, dict[str, object]]]:
    """Every limit each robot breaks over a trajectory: per robot and reason, the number of samples and
    each stretch of consecutive samples (from_s, to_s). All of them, not a first few."""
    flags = {side: np.bitwise_or.reduce(solution.violations, axis=1) for side, solution in solutions.items()}
    return violation_flag_stretches(flags, times_s)


def violation_flag_stretches(
    flags: dict[str, np.ndarray], times_s: np.ndarray
) -> dict[str, dict[str, dict[str, object]]]:
    """`violation_stretches` from each robot's `LegViolation` flags of all its legs per sample (N,)."""
    report: dict[str, dict[str, dict[str, object]]] = {}
    for side, side_flags in flags.items():
        by_reason: dict[str, dict[str, object]] = {}
        for flag, reason in VIOLATION_REASONS.items():
            hit = (side_flags & np.uint8(flag)) != 0
            if np.any(hit):
                by_reason[reason] = {
                    "samples": int(np.sum(hit)),
                    "stretches": [{"from_s": a, "to_s": b} for a, b in stretches(hit, np.asarray(times_s))],
                }
        report[side] = by_reason
    return report
