"""Jacobians and velocities of one robot: twist and pose Jacobians, slider velocities ↔ twists, cond(J)."""

from __future__ import annotations

import numpy as np

from core.kinematics.ik import VIOLATION_REASONS, LegViolation, UnreachablePoseError, as_poses, inverse_kinematics
from core.kinematics.rotations import euler_rate_matrices, rotation_matrices
from core.robot import SSPRobot


def twist_jacobian(robot: SSPRobot, poses: np.ndarray, slider_positions_m: np.ndarray | None = None) -> np.ndarray:
    """J with slider velocities = J · (v, ω), ω in the base frame. Shape (N, 6, 6).

    From |W_i − A_i|² = L²: d·(v + ω × R·B_i − ẋ_i e_x) = 0, so ẋ_i = (d·v + (R·B_i × d)·ω) / d_x.
    The Jacobian is geometry: it exists beyond the stroke and cone limits (so that the condition number
    can be followed toward a singularity), but not where a rod cannot reach its rail, which raises
    `UnreachablePoseError`.
    """
    poses = as_poses(poses)
    rotations = rotation_matrices(poses[:, 3:])
    if slider_positions_m is None:
        solution = inverse_kinematics(robot, poses, check=False)
        if np.any(solution.violations & LegViolation.ROD_CANNOT_REACH):
            reach_failures = [
                v for v in solution.limit_violations() if v.reason == VIOLATION_REASONS[LegViolation.ROD_CANNOT_REACH]
            ]
            raise UnreachablePoseError(reach_failures[:50])
        slider_positions_m = solution.slider_positions_m
    lever = np.matmul(rotations, robot.platform_joints_m.T).swapaxes(1, 2)
    joints = poses[:, None, :3] + lever
    rod = joints - np.stack(
        np.broadcast_arrays(slider_positions_m, robot.rail_y_m, np.full(6, robot.rail_z_m)), axis=-1
    )
    jacobian = np.concatenate([rod, np.cross(lever, rod)], axis=-1)
    return jacobian / rod[..., 0:1]


def pose_jacobian(robot: SSPRobot, poses: np.ndarray, slider_positions_m: np.ndarray | None = None) -> np.ndarray:
    """J with slider velocities = J · (ẋ, ẏ, ż, roll', pitch', yaw'). Shape (N, 6, 6)."""
    poses = as_poses(poses)
    jacobian = twist_jacobian(robot, poses, slider_positions_m)
    jacobian[..., 3:] = np.matmul(jacobian[..., 3:], euler_rate_matrices(poses[:, 3:]))
    return jacobian


def slider_velocities(robot: SSPRobot, poses: np.ndarray, twists: np.ndarray) -> np.ndarray:
    """Platform twists (N, 6) as (v m/s, ω rad/s in the base frame) → slider velocities (N, 6) m/s."""
    return np.matmul(twist_jacobian(robot, poses), np.atleast_2d(twists)[..., None])[..., 0]


def platform_twists(robot: SSPRobot, poses: np.ndarray, slider_velocities_m_s: np.ndarray) -> np.ndarray:
    """Slider velocities (N, 6) m/s → platform twists (N, 6) as (v m/s, ω rad/s in the base frame)."""
    return np.linalg.solve(twist_jacobian(robot, poses), np.atleast_2d(slider_velocities_m_s)[..., None])[..., 0]


def condition_number(robot: SSPRobot, poses: np.ndarray) -> np.ndarray:
    """Closeness to a singularity: cond(J) with ω columns scaled by the platform radius so that the
    matrix is dimensionless (metres of joint travel per metre of joint motion). Shape (N,)."""
    jacobian = twist_jacobian(robot, poses)
    jacobian[..., 3:] /= robot.platform_radius_m
    return np.linalg.cond(jacobian)
