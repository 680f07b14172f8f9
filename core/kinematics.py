"""Inverse and forward kinematics of the 6-SSP robot and of the twin (paper §3.1, Formulas 1–10).

Inverse kinematics is closed form (REFERENCE.md §1): with W_i = p + R·B_i,
x_i = W_ix + side_i · sqrt(L² − (W_iy − y_rail,i)² − (W_iz − z_rail)²), vectorised over N poses.
Forward kinematics is Newton's method on IK(pose) = sliders with the analytic Jacobian, warm-started
from the last pose (as LinuxCNC's genhexkins does); it reports iterations and residual.

Poses are (x, y, z, roll, pitch, yaw) in m and rad with R = Rx(roll)·Ry(pitch)·Rz(yaw); batches
are arrays of shape (N, 6).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, replace

import numba
import numpy as np

from core.robot import SSPRobot, TwinRobot


class LegViolation(enum.IntFlag):
    """Why a leg cannot take a pose; a pose is reachable when every leg is NONE."""

    NONE = 0
    ROD_CANNOT_REACH = 1  # the platform joint is farther than one rod length from the rail
    STROKE = 2  # the slider would leave its stroke
    BASE_CONE = 4  # the slider's spherical joint would leave its cone
    PLATFORM_CONE = 8  # the platform's spherical joint would leave its cone


@dataclass(frozen=True)
class LimitViolation:
    pose_index: int
    slider: int  # 1-based, REFERENCE.md order
    reason: str
    value: float
    limit: float
    unit: str

    def __str__(self) -> str:
        return (
            f"pose {self.pose_index}, slider {self.slider}: {self.reason} "
            f"(value {self.value:.6g} {self.unit}, limit {self.limit:.6g} {self.unit})"
        )


class UnreachablePoseError(ValueError):
    """One or more poses cannot be reached; `violations` lists each pose, slider and reason."""

    def __init__(self, violations: list[LimitViolation]) -> None:
        self.violations = violations
        shown = "; ".join(str(v) for v in violations[:5])
        more = f" (+{len(violations) - 5} more)" if len(violations) > 5 else ""
        super().__init__(f"unreachable pose: {shown}{more}")


class ForwardKinematicsError(RuntimeError):
    def __init__(self, iterations: int, residual_m: float) -> None:
        self.iterations = iterations
        self.residual_m = residual_m
        super().__init__(
            f"forward kinematics did not converge: {iterations} iterations, residual {residual_m * 1e3:.3g} mm"
        )


# --- Rotations ------------------------------------------------------------------------------------


def rotation_matrices(angles: np.ndarray) -> np.ndarray:
    """(N, 3) roll, pitch, yaw → (N, 3, 3) rotations, R = Rx·Ry·Rz (Formula 9, typo corrected)."""
    angles = np.asarray(angles, dtype=float)
    ca, cb, cc = np.cos(angles).T
    sa, sb, sc = np.sin(angles).T
    rotation = np.empty((*angles.shape[:-1], 3, 3))
    rotation[..., 0, 0] = cb * cc
    rotation[..., 0, 1] = -cb * sc
    rotation[..., 0, 2] = sb
    rotation[..., 1, 0] = ca * sc + sa * sb * cc
    rotation[..., 1, 1] = ca * cc - sa * sb * sc
    rotation[..., 1, 2] = -sa * cb
    rotation[..., 2, 0] = sa * sc - ca * sb * cc
    rotation[..., 2, 1] = sa * cc + ca * sb * sc
    rotation[..., 2, 2] = ca * cb
    return rotation


def euler_from_rotation(rotation: np.ndarray) -> np.ndarray:
    """(N, 3, 3) → (N, 3) roll, pitch, yaw for R = Rx·Ry·Rz; pitch in [−π/2, π/2]."""
    roll = np.arctan2(-rotation[..., 1, 2], rotation[..., 2, 2])
    pitch = np.arcsin(np.clip(rotation[..., 0, 2], -1.0, 1.0))
    yaw = np.arctan2(-rotation[..., 0, 1], rotation[..., 0, 0])
    return np.stack([roll, pitch, yaw], axis=-1)


def euler_rate_matrices(angles: np.ndarray) -> np.ndarray:
    """E with ω = E · (roll', pitch', yaw'), ω in the base frame, for R = Rx·Ry·Rz. Shape (N, 3, 3)."""
    angles = np.asarray(angles, dtype=float)
    roll, pitch = angles[..., 0], angles[..., 1]
    ca, sa, cb, sb = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    matrix = np.zeros((*angles.shape[:-1], 3, 3))
    matrix[..., 0, 0] = 1.0
    matrix[..., 0, 2] = sb
    matrix[..., 1, 1] = ca
    matrix[..., 1, 2] = -sa * cb
    matrix[..., 2, 1] = sa
    matrix[..., 2, 2] = ca * cb
    return matrix


def _as_poses(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=float)
    if poses.ndim == 1:
        poses = poses[None, :]
    if poses.ndim != 2 or poses.shape[1] != 6:
        raise ValueError(f"poses: shape {poses.shape}, expected (N, 6) as (x, y, z, roll, pitch, yaw)")
    if not np.all(np.isfinite(poses)):
        bad = int(np.argwhere(~np.isfinite(poses))[0, 0])
        raise ValueError(f"poses[{bad}] = {poses[bad].tolist()}: must be finite (no NaN/inf)")
    return poses


# --- Inverse kinematics -----------------------------------------------------------------------------


@dataclass(frozen=True)
class IKSolution:
    """Slider positions for N poses, with every leg's limit check.

    `slider_positions_m` holds NaN only where `violations` has ROD_CANNOT_REACH for that leg.
    """

    poses: np.ndarray  # (N, 6)
    slider_positions_m: np.ndarray  # (N, 6)
    violations: np.ndarray  # (N, 6) LegViolation bit flags
    base_cone_rad: np.ndarray  # (N, 6)
    platform_cone_rad: np.ndarray  # (N, 6)
    robot: SSPRobot

    @property
    def reachable(self) -> np.ndarray:
        return np.all(self.violations == 0, axis=1)

    def limit_violations(self, max_count: int | None = None) -> list[LimitViolation]:
        """Each violated (pose, slider, reason) with its value and limit, in pose order."""
        limits = self.robot.limits
        found: list[LimitViolation] = []
        for pose_index, leg in np.argwhere(self.violations != 0):
            flags = LegViolation(int(self.violations[pose_index, leg]))
            slider = int(leg) + 1
            if LegViolation.ROD_CANNOT_REACH in flags:
                reach = _rod_reach_distance(self.robot, self.poses[pose_index : pose_index + 1])[0, leg]
                found.append(
                    LimitViolation(
                        int(pose_index), slider, "rod cannot reach its rail", reach, self.robot.rod_length_m, "m"
                    )
                )
            if LegViolation.STROKE in flags:
                position = float(self.slider_positions_m[pose_index, leg])
                low, high = self.robot.stroke_min_m[leg], self.robot.stroke_max_m[leg]
                found.append(
                    LimitViolation(
                        int(pose_index),
                        slider,
                        "slider outside its stroke",
                        position,
                        low if position < low else high,
                        "m",
                    )
                )
            if LegViolation.BASE_CONE in flags:
                found.append(
                    LimitViolation(
                        int(pose_index),
                        slider,
                        "slider joint beyond its cone",
                        float(self.base_cone_rad[pose_index, leg]),
                        limits.base_joint_cone_rad,
                        "rad",
                    )
                )
            if LegViolation.PLATFORM_CONE in flags:
                found.append(
                    LimitViolation(
                        int(pose_index),
                        slider,
                        "platform joint beyond its cone",
                        float(self.platform_cone_rad[pose_index, leg]),
                        limits.platform_joint_cone_rad,
                        "rad",
                    )
                )
            if max_count is not None and len(found) >= max_count:
                break
        return found

    def raise_if_unreachable(self) -> None:
        if not np.all(self.reachable):
            raise UnreachablePoseError(self.limit_violations(max_count=50))


def platform_joints_world(robot: SSPRobot, positions: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """W_i = p + R·B_i in the base frame: (N, 3), (N, 3, 3) → (N, 6, 3)."""
    return positions[:, None, :] + np.einsum("nij,kj->nki", rotations, robot.platform_joints_m)


def _rod_reach_distance(robot: SSPRobot, poses: np.ndarray) -> np.ndarray:
    joints = platform_joints_world(robot, poses[:, :3], rotation_matrices(poses[:, 3:]))
    return np.hypot(joints[..., 1] - robot.rail_y_m, joints[..., 2] - robot.rail_z_m)


def _neutral_rod_directions(robot: SSPRobot) -> np.ndarray:
    """Unit rod vectors, slider joint → platform joint, at the neutral pose: the cone axes. (6, 3)."""
    neutral = np.asarray(robot.neutral_pose, dtype=float)[None, :]
    joints = platform_joints_world(robot, neutral[:, :3], rotation_matrices(neutral[:, 3:]))[0]
    reach_sq = robot.rod_length_m**2 - (joints[:, 1] - robot.rail_y_m) ** 2 - (joints[:, 2] - robot.rail_z_m) ** 2
    sliders = np.stack(
        [joints[:, 0] + robot.sides * np.sqrt(reach_sq), robot.rail_y_m, np.full(6, robot.rail_z_m)], axis=1
    )
    return (joints - sliders) / robot.rod_length_m


def solve_ik_pose_rotation(
    robot: SSPRobot, positions: np.ndarray, rotations: np.ndarray, poses: np.ndarray
) -> IKSolution:
    """IK from platform positions (N, 3) and rotations (N, 3, 3); `poses` is kept for reporting."""
    joints = platform_joints_world(robot, positions, rotations)
    offset_y = joints[..., 1] - robot.rail_y_m
    offset_z = joints[..., 2] - robot.rail_z_m
    reach_sq = robot.rod_length_m**2 - offset_y**2 - offset_z**2
    cannot_reach = reach_sq < 0.0
    along_rail = np.sqrt(np.where(cannot_reach, np.nan, reach_sq))
    sliders = joints[..., 0] + robot.sides * along_rail

    violations = np.where(cannot_reach, LegViolation.ROD_CANNOT_REACH.value, 0).astype(np.uint8)
    outside = (sliders < robot.stroke_min_m) | (sliders > robot.stroke_max_m)
    violations |= np.where(outside, LegViolation.STROKE.value, 0).astype(np.uint8)

    # Rod direction d = W − A = (−side·√reach², Δy, Δz)/L; cone angles against the neutral directions,
    # at the slider in the base frame and at the platform in the (rotating) platform frame.
    rod = np.stack([-robot.sides * along_rail, offset_y, offset_z], axis=-1) / robot.rod_length_m
    axes = _neutral_rod_directions(robot)
    base_cone = np.arccos(np.clip(np.einsum("nki,ki->nk", rod, axes), -1.0, 1.0))
    rotated_axes = np.einsum("nij,kj->nki", rotations, axes)
    platform_cone = np.arccos(np.clip(np.einsum("nki,nki->nk", rod, rotated_axes), -1.0, 1.0))
    limits = robot.limits
    violations |= np.where(base_cone > limits.base_joint_cone_rad, LegViolation.BASE_CONE.value, 0).astype(np.uint8)
    violations |= np.where(platform_cone > limits.platform_joint_cone_rad, LegViolation.PLATFORM_CONE.value, 0).astype(
        np.uint8
    )
    return IKSolution(poses, sliders, violations, base_cone, platform_cone, robot)


def inverse_kinematics(robot: SSPRobot, poses: np.ndarray, *, check: bool = True) -> IKSolution:
    """Slider positions (m) for poses (N, 6). With `check`, any unreachable pose raises
    `UnreachablePoseError` naming the pose, slider, reason and limit; without it the caller reads
    `violations` (the safety supervisor and the workspace tool do)."""
    poses = _as_poses(poses)
    solution = solve_ik_pose_rotation(robot, poses[:, :3], rotation_matrices(poses[:, 3:]), poses)
    if check:
        solution.raise_if_unreachable()
    return solution


# --- Jacobians ------------------------------------------------------------------------------------


def twist_jacobian(robot: SSPRobot, poses: np.ndarray, slider_positions_m: np.ndarray | None = None) -> np.ndarray:
    """J with slider velocities = J · (v, ω), ω in the base frame. Shape (N, 6, 6).

    From |W_i − A_i|² = L²: d·(v + ω × R·B_i − ẋ_i e_x) = 0, so ẋ_i = (d·v + (R·B_i × d)·ω) / d_x.
    """
    poses = _as_poses(poses)
    rotations = rotation_matrices(poses[:, 3:])
    if slider_positions_m is None:
        slider_positions_m = inverse_kinematics(robot, poses).slider_positions_m
    lever = np.einsum("nij,kj->nki", rotations, robot.platform_joints_m)
    joints = poses[:, None, :3] + lever
    rod = joints - np.stack(
        np.broadcast_arrays(slider_positions_m, robot.rail_y_m, np.full(6, robot.rail_z_m)), axis=-1
    )
    jacobian = np.concatenate([rod, np.cross(lever, rod)], axis=-1)
    return jacobian / rod[..., 0:1]


def pose_jacobian(robot: SSPRobot, poses: np.ndarray, slider_positions_m: np.ndarray | None = None) -> np.ndarray:
    """J with slider velocities = J · (ẋ, ẏ, ż, roll', pitch', yaw'). Shape (N, 6, 6)."""
    poses = _as_poses(poses)
    jacobian = twist_jacobian(robot, poses, slider_positions_m)
    jacobian[..., 3:] = np.einsum("nkj,nji->nki", jacobian[..., 3:], euler_rate_matrices(poses[:, 3:]))
    return jacobian


def slider_velocities(robot: SSPRobot, poses: np.ndarray, twists: np.ndarray) -> np.ndarray:
    """Platform twists (N, 6) as (v m/s, ω rad/s in the base frame) → slider velocities (N, 6) m/s."""
    return np.einsum("nkj,nj->nk", twist_jacobian(robot, poses), np.atleast_2d(twists))


def platform_twists(robot: SSPRobot, poses: np.ndarray, slider_velocities_m_s: np.ndarray) -> np.ndarray:
    """Slider velocities (N, 6) m/s → platform twists (N, 6) as (v m/s, ω rad/s in the base frame)."""
    return np.linalg.solve(twist_jacobian(robot, poses), np.atleast_2d(slider_velocities_m_s)[..., None])[..., 0]


def condition_number(robot: SSPRobot, poses: np.ndarray) -> np.ndarray:
    """Closeness to a singularity: cond(J) with ω columns scaled by the platform radius so that the
    matrix is dimensionless (metres of joint travel per metre of joint motion). Shape (N,)."""
    jacobian = twist_jacobian(robot, poses)
    jacobian[..., 3:] /= robot.platform_radius_m
    return np.linalg.cond(jacobian)


# --- Forward kinematics (single pose, per tick) -----------------------------------------------------


@dataclass(frozen=True)
class FKResult:
    pose: np.ndarray  # (6,)
    iterations: int
    residual_m: float  # max |IK(pose) − sliders|


@numba.njit(cache=True, fastmath=False)
def _fk_newton(
    sliders: np.ndarray,
    guess: np.ndarray,
    joints: np.ndarray,
    rail_y: np.ndarray,
    rail_z: float,
    sides: np.ndarray,
    rod_length: float,
    tolerance: float,
    max_iterations: int,
    pose_out: np.ndarray,
) -> tuple[int, float]:
    pose = guess.copy()
    residual = np.empty(6)
    jacobian = np.empty((6, 6))
    rotation = np.empty((3, 3))
    max_residual = np.inf
    for iteration in range(max_iterations + 1):
        ca, sa = np.cos(pose[3]), np.sin(pose[3])
        cb, sb = np.cos(pose[4]), np.sin(pose[4])
        cc, sc = np.cos(pose[5]), np.sin(pose[5])
        rotation[0, 0] = cb * cc
        rotation[0, 1] = -cb * sc
        rotation[0, 2] = sb
        rotation[1, 0] = ca * sc + sa * sb * cc
        rotation[1, 1] = ca * cc - sa * sb * sc
        rotation[1, 2] = -sa * cb
        rotation[2, 0] = sa * sc - ca * sb * cc
        rotation[2, 1] = sa * cc + ca * sb * sc
        rotation[2, 2] = ca * cb
        max_residual = 0.0
        for leg in range(6):
            lx = rotation[0, 0] * joints[leg, 0] + rotation[0, 1] * joints[leg, 1] + rotation[0, 2] * joints[leg, 2]
            ly = rotation[1, 0] * joints[leg, 0] + rotation[1, 1] * joints[leg, 1] + rotation[1, 2] * joints[leg, 2]
            lz = rotation[2, 0] * joints[leg, 0] + rotation[2, 1] * joints[leg, 1] + rotation[2, 2] * joints[leg, 2]
            dy = pose[1] + ly - rail_y[leg]
            dz = pose[2] + lz - rail_z
            reach_sq = rod_length * rod_length - dy * dy - dz * dz
            if reach_sq <= 0.0:
                return -(iteration + 1), np.inf
            along = np.sqrt(reach_sq)
            residual[leg] = pose[0] + lx + sides[leg] * along - sliders[leg]
            max_residual = max(max_residual, abs(residual[leg]))
            # Row of the twist Jacobian: (d, (R·B) × d) / d_x with d = (−side·along, dy, dz).
            dx = -sides[leg] * along
            jacobian[leg, 0] = 1.0
            jacobian[leg, 1] = dy / dx
            jacobian[leg, 2] = dz / dx
            wx = (ly * dz - lz * dy) / dx
            wy = (lz * dx - lx * dz) / dx
            wz = (lx * dy - ly * dx) / dx
            # ω = E · Euler rates, E = [e_x, Rx·e_y, Rx·Ry·e_z].
            jacobian[leg, 3] = wx
            jacobian[leg, 4] = ca * wy + sa * wz
            jacobian[leg, 5] = sb * wx - sa * cb * wy + ca * cb * wz
        if max_residual <= tolerance:
            pose_out[:] = pose
            return iteration, max_residual
        if iteration == max_iterations:
            break
        pose -= np.linalg.solve(jacobian, residual)
    pose_out[:] = pose
    return -max_iterations, max_residual


class ForwardKinematics:
    """Warm-started Newton FK for one robot: call once per tick with measured slider positions."""

    def __init__(self, robot: SSPRobot, *, tolerance_m: float = 1e-12, max_iterations: int = 20) -> None:
        self.robot = robot
        self.tolerance_m = tolerance_m
        self.max_iterations = max_iterations
        self._joints = np.ascontiguousarray(robot.platform_joints_m)
        self._rail_y = np.ascontiguousarray(robot.rail_y_m)
        self._sides = np.ascontiguousarray(robot.sides)
        self._last_pose = np.asarray(robot.neutral_pose, dtype=float).copy()
        self._pose_out = np.empty(6)
        self.solve(inverse_kinematics(robot, self._last_pose).slider_positions_m[0])  # compile and check

    def reset(self, pose: np.ndarray | None = None) -> None:
        self._last_pose[:] = self.robot.neutral_pose if pose is None else pose

    def solve(self, slider_positions_m: np.ndarray, guess: np.ndarray | None = None) -> FKResult:
        """Pose for six slider positions (m); raises `ForwardKinematicsError` when Newton does not converge."""
        sliders = np.asarray(slider_positions_m, dtype=float)
        if sliders.shape != (6,) or not np.all(np.isfinite(sliders)):
            raise ValueError(f"slider_positions_m = {sliders.tolist()}: expected 6 finite values (m)")
        start = self._last_pose if guess is None else np.asarray(guess, dtype=float)
        iterations, residual = _fk_newton(
            sliders,
            start,
            self._joints,
            self._rail_y,
            self.robot.rail_z_m,
            self._sides,
            self.robot.rod_length_m,
            self.tolerance_m,
            self.max_iterations,
            self._pose_out,
        )
        if iterations < 0 or not np.isfinite(residual):
            raise ForwardKinematicsError(abs(iterations), residual)
        self._last_pose[:] = self._pose_out
        return FKResult(self._pose_out.copy(), iterations, residual)


def forward_kinematics(
    robot: SSPRobot, slider_positions_m: np.ndarray, guesses: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """FK for many slider sets (N, 6), each from its own guess (default: neutral).
    Returns poses (N, 6), iterations (N,) and residuals (N,) in m; raises on any non-convergence."""
    sliders = np.atleast_2d(np.asarray(slider_positions_m, dtype=float))
    solver = ForwardKinematics(robot)
    starts = np.broadcast_to(np.asarray(robot.neutral_pose if guesses is None else guesses, dtype=float), sliders.shape)
    results = [solver.solve(s, guess=g) for s, g in zip(sliders, starts, strict=True)]
    return (
        np.array([r.pose for r in results]),
        np.array([r.iterations for r in results]),
        np.array([r.residual_m for r in results]),
    )


# --- The twin ---------------------------------------------------------------------------------------


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def stance_origin_world(twin: TwinRobot) -> np.ndarray:
    """The stance frame's origin: midpoint of the two foot plates at the neutral pose (world, m)."""
    feet = []
    for side in twin.sides:
        placement, robot = twin.placement(side), twin.robot_for(side)
        neutral = np.asarray(robot.neutral_pose)
        platform_rotation = rotation_matrices(neutral[None, 3:])[0]
        foot_in_base = neutral[:3] + platform_rotation @ np.asarray(placement.foot_plate_offset_m)
        feet.append(np.asarray(placement.base_origin_m) + _yaw_matrix(placement.base_yaw_rad) @ foot_in_base)
    return np.mean(feet, axis=0)


def twin_platform_poses(twin: TwinRobot, stance_poses: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each robot's platform (positions (N, 3), rotations (N, 3, 3)) in its own base frame, for the
    stance frame moved by `stance_poses` (N, 6) from neutral. Both feet move as one rigid body."""
    stance_poses = _as_poses(stance_poses)
    stance_rotation = rotation_matrices(stance_poses[:, 3:])
    origin = stance_origin_world(twin)
    result = {}
    for side in twin.sides:
        placement, robot = twin.placement(side), twin.robot_for(side)
        base_yaw = _yaw_matrix(placement.base_yaw_rad)
        base_origin = np.asarray(placement.base_origin_m)
        neutral = np.asarray(robot.neutral_pose)
        neutral_rotation_world = base_yaw @ rotation_matrices(neutral[None, 3:])[0]
        lever_world = base_origin + base_yaw @ neutral[:3] - origin
        platform_world = origin + stance_poses[:, :3] + stance_rotation @ lever_world
        positions = (platform_world - base_origin) @ base_yaw  # = base_yawᵀ · (world − origin)
        rotations = base_yaw.T @ stance_rotation @ neutral_rotation_world
        result[side] = (positions, rotations)
    return result


def twin_inverse_kinematics(twin: TwinRobot, stance_poses: np.ndarray, *, check: bool = True) -> dict[str, IKSolution]:
    """IK of both robots for stance-frame poses (N, 6); keys 'right' and 'left'."""
    stance_poses = _as_poses(stance_poses)
    solutions = {}
    for side, (positions, rotations) in twin_platform_poses(twin, stance_poses).items():
        poses = np.concatenate([positions, euler_from_rotation(rotations)], axis=1)
        solutions[side] = solve_ik_pose_rotation(twin.robot_for(side), positions, rotations, poses)
    if check:
        for side, solution in solutions.items():
            if not np.all(solution.reachable):
                raise UnreachablePoseError(
                    [replace(v, reason=f"{side} robot: {v.reason}") for v in solution.limit_violations(max_count=50)]
                )
    return solutions
