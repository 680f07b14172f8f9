"""Inverse and forward kinematics of the 6-SSP robot and of the twin (paper §3.1, Formulas 1–10).

Split by concept; this package re-exports every public name the single module had:

- `rotations`: R = Rx·Ry·Rz (one compiled kernel), Euler angles and rates;
- `legs`: the geometry as a numba NamedTuple and the one per-leg kernel (lever, rod vector, slider,
  Jacobian row) that IK, FK, dynamics, the clearance check and the tick all call;
- `ik`: closed-form IK with every leg's limit check; `conditioning`: the singularity screen and the
  trajectory report; `jacobians`: twist/pose Jacobians and velocities; `fk`: Newton FK; `twin`: both robots.

Poses are (x, y, z, roll, pitch, yaw) in m and rad; batches are arrays of shape (N, 6).
"""

from core.kinematics.conditioning import SingularityReport, singularity_report
from core.kinematics.fk import FKResult, ForwardKinematics, ForwardKinematicsError, forward_kinematics
from core.kinematics.ik import (
    IK_CHUNK_POSES,
    IK_THREADS,
    VIOLATION_REASONS,
    IKSolution,
    LegViolation,
    LimitViolation,
    PoseCollisions,
    UnreachablePoseError,
    _as_poses,
    as_poses,
    for_each_chunk,
    inverse_kinematics,
    platform_joints_world,
    solve_ik_pose_rotation,
)
from core.kinematics.jacobians import (
    condition_number,
    platform_twists,
    pose_jacobian,
    slider_velocities,
    twist_jacobian,
)
from core.kinematics.legs import LegGeometry, leg_geometry, leg_kernel, leg_solution, neutral_rod_directions, twist_row
from core.kinematics.rotations import euler_from_rotation, euler_rate_matrices, rotation_matrices, yaw_matrix
from core.kinematics.twin import (
    foot_plate_neutral_world,
    stance_origin_world,
    twin_inverse_kinematics,
    twin_platform_poses,
    twin_singularity_report,
    violation_flag_stretches,
    violation_stretches,
)

__all__ = [
    "IK_CHUNK_POSES",
    "IK_THREADS",
    "VIOLATION_REASONS",
    "FKResult",
    "ForwardKinematics",
    "ForwardKinematicsError",
    "IKSolution",
    "LegGeometry",
    "LegViolation",
    "LimitViolation",
    "PoseCollisions",
    "SingularityReport",
    "UnreachablePoseError",
    "_as_poses",
    "as_poses",
    "condition_number",
    "euler_from_rotation",
    "euler_rate_matrices",
    "foot_plate_neutral_world",
    "for_each_chunk",
    "forward_kinematics",
    "inverse_kinematics",
    "leg_geometry",
    "leg_kernel",
    "leg_solution",
    "neutral_rod_directions",
    "platform_joints_world",
    "platform_twists",
    "pose_jacobian",
    "rotation_matrices",
    "singularity_report",
    "slider_velocities",
    "solve_ik_pose_rotation",
    "stance_origin_world",
    "twin_inverse_kinematics",
    "twin_platform_poses",
    "twin_singularity_report",
    "twist_jacobian",
    "twist_row",
    "violation_flag_stretches",
    "violation_stretches",
    "yaw_matrix",
]
