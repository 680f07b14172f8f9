"""Reference outputs of IK, FK, dynamics and the tick kernels, for the kernel-refactor regression test.

`python -m tests.core.kernel_reference OUT.npz` writes them. The committed file
`tests/core/data/kernel_reference.npz` was written by the code *before* the geometry kernels were merged
(commit fe74a48), so `test_kernel_refactor.py` proves the refactor changed no result beyond 1e-12.
The inputs are regenerated here from fixed seeds; only the outputs are stored.
"""

from __future__ import annotations

import math
import sys

import numpy as np

from core.dynamics import InverseDynamics, TwinInverseDynamics
from core.kinematics import ForwardKinematics, inverse_kinematics, twin_inverse_kinematics
from core.plan.limits import LimitCode
from core.robot import RobotPlacement, TwinRobot, paper_robot
from core.twin_kernels import VIOLATION_FIELDS, TwinKernels

TICK_PERIOD_S = 0.001


def reference_twin() -> TwinRobot:
    """The layout the references were taken on (the pre-issue-13 default: interleaved rails)."""
    return TwinRobot(
        right=RobotPlacement(base_origin_m=(0.0, -0.5, 0.0), foot_plate_offset_m=(0.0, 0.25, 0.0)),
        left=RobotPlacement(base_origin_m=(0.0, 0.5, 0.0), mirrored=True, foot_plate_offset_m=(0.0, -0.25, 0.0)),
    )


def robot_poses(count: int = 1000) -> np.ndarray:
    rng = np.random.default_rng(13)
    span = np.array([0.4, 0.15, 0.15, math.radians(12), math.radians(12), math.radians(25)])
    return np.asarray(paper_robot().neutral_pose) + rng.uniform(-1.0, 1.0, (count, 6)) * span


def stance_trajectory(count: int = 1000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    time_s = np.arange(count) * TICK_PERIOD_S
    amplitude = np.array([0.05, 0.03, 0.02, math.radians(3), math.radians(4), math.radians(5)])
    omega = 2 * np.pi * np.array([0.7, 0.5, 0.9, 0.6, 0.8, 0.3])
    phase = omega * time_s[:, None]
    return amplitude * np.sin(phase), amplitude * omega * np.cos(phase), -amplitude * omega**2 * np.sin(phase)


def compute() -> dict[str, np.ndarray]:
    robot, twin = paper_robot(), reference_twin()
    poses = robot_poses()
    solution = inverse_kinematics(robot, poses, check=False)
    reachable = solution.reachable
    fk_poses, fk_iterations, fk_residuals = ForwardKinematics(robot).solve_batch(
        solution.slider_positions_m[reachable][:500]
    )
    stance, stance_velocity, stance_acceleration = stance_trajectory()
    twin_solution = twin_inverse_kinematics(twin, stance, check=False)
    robot_velocity = np.zeros_like(poses[:200])
    robot_velocity[:, 0] = 0.1
    robot_velocity[:, 3] = 0.2
    robot_acceleration = np.full_like(robot_velocity, 0.5)
    single_forces = InverseDynamics(robot).slider_forces(poses[reachable][:200], robot_velocity, robot_acceleration)
    twin_forces = TwinInverseDynamics(twin).slider_forces(stance, stance_velocity, stance_acceleration)
    kernels = TwinKernels(twin, TICK_PERIOD_S)
    sliders = kernels.neutral_sliders()
    velocity = np.zeros(12)
    tick_sliders, tick_violations, measured = [], [], []
    limits = np.array([math.radians(40), math.radians(40), math.radians(25), 1.5, 20.0, 4000.0])
    if "COLLISION" in LimitCode.__members__:  # since issue 13 the vector ends with the clearance margin
        limits = np.append(limits, -np.inf)
    for pose in stance:
        out, v_out, a_out, violation = np.zeros(12), np.zeros(12), np.zeros(12), np.zeros(VIOLATION_FIELDS)
        kernels.command(
            pose, sliders, velocity, np.full(12, -2.0), np.full(12, 2.0), limits, out, v_out, a_out, violation
        )
        tick_sliders.append(out)
        tick_violations.append(violation)
        stance_out = np.zeros(6)
        kernels.measured_stance_pose(out[:6], stance_out)
        measured.append(stance_out)
        sliders, velocity = out, v_out
    return {
        "ik_sliders": solution.slider_positions_m,
        "ik_violations": solution.violations.astype(np.int64),
        "ik_base_cone": solution.base_cone_rad,
        "ik_platform_cone": solution.platform_cone_rad,
        "fk_poses": fk_poses,
        "fk_iterations": fk_iterations,
        "fk_residuals": fk_residuals,
        "twin_right_sliders": twin_solution["right"].slider_positions_m,
        "twin_left_sliders": twin_solution["left"].slider_positions_m,
        "twin_right_violations": twin_solution["right"].violations.astype(np.int64),
        "twin_left_violations": twin_solution["left"].violations.astype(np.int64),
        "single_forces": single_forces,
        "twin_forces": twin_forces,
        "tick_sliders": np.array(tick_sliders),
        "tick_violations": np.array(tick_violations),
        "tick_measured_stance": np.array(measured),
    }


if __name__ == "__main__":
    np.savez_compressed(sys.argv[1], **compute())
