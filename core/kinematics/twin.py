"""The twin: two robots, one per foot, driven by one stance pose (both feet move as one rigid body)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from core.kinematics.conditioning import SingularityReport, singularity_report, stretches
from core.kinematics.ik import VIOLATION_REASONS, IKSolution, UnreachablePoseError, as_poses, solve_ik_pose_rotation
from core.kinematics.legs import leg_geometry
from core.kinematics.rotations import euler_from_rotation, rotation_matrices, yaw_matrix
from core.robot import TwinRobot


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


def twin_platform_poses(twin: TwinRobot, stance_poses: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each robot's platform (positions (N, 3), rotations (N, 3, 3)) in its own base frame, for the
    stance frame moved by `stance_poses` (N, 6) from neutral. Both feet move as one rigid body."""
    stance_poses = as_poses(stance_poses)
    stance_rotation = rotation_matrices(stance_poses[:, 3:])
    origin = stance_origin_world(twin)
    result = {}
    for side in twin.sides:
        placement, robot = twin.placement(side), twin.robot_for(side)
        base_yaw = yaw_matrix(placement.base_yaw_rad)
        base_origin = np.asarray(placement.base_origin_m)
        neutral = np.asarray(robot.neutral_pose)
        neutral_rotation_world = base_yaw @ rotation_matrices(neutral[None, 3:])[0]
        lever_world = base_origin + base_yaw @ neutral[:3] - origin
        platform_world = origin + stance_poses[:, :3] + stance_rotation @ lever_world
        positions = (platform_world - base_origin) @ base_yaw  # = base_yawᵀ · (world − origin)
        rotations = base_yaw.T @ stance_rotation @ neutral_rotation_world
        result[side] = (positions, rotations)
    return result


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
    report: dict[str, dict[str, dict[str, object]]] = {}
    for side, solution in solutions.items():
        flags = np.bitwise_or.reduce(solution.violations, axis=1)
        by_reason: dict[str, dict[str, object]] = {}
        for flag, reason in VIOLATION_REASONS.items():
            hit = (flags & np.uint8(flag)) != 0
            if np.any(hit):
                by_reason[reason] = {
                    "samples": int(np.sum(hit)),
                    "stretches": [{"from_s": a, "to_s": b} for a, b in stretches(hit, np.asarray(times_s))],
                }
        report[side] = by_reason
    return report
