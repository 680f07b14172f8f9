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
import functools
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import NamedTuple

import numba
import numpy as np

from core.robot import SSPRobot, TwinRobot
from core.rotations import rotation_into


class LegViolation(enum.IntFlag):
    """Why a leg cannot take a pose; a pose is reachable when every leg is NONE."""

    NONE = 0
    ROD_CANNOT_REACH = 1  # the platform joint is farther than one rod length from the rail
    STROKE = 2  # the slider would leave its stroke
    BASE_CONE = 4  # the slider's spherical joint would leave its cone
    PLATFORM_CONE = 8  # the platform's spherical joint would leave its cone
    # The pose is too close to a singularity (cond(J) above the limit) or beyond one (det J has the
    # other sign than at neutral: another assembly mode). A property of the whole pose: set on all legs.
    SINGULARITY = 16


VIOLATION_REASONS = {
    LegViolation.ROD_CANNOT_REACH: "rod cannot reach its rail",
    LegViolation.STROKE: "slider outside its stroke",
    LegViolation.BASE_CONE: "slider joint beyond its cone",
    LegViolation.PLATFORM_CONE: "platform joint beyond its cone",
    LegViolation.SINGULARITY: "too close to or beyond a singularity",
}


@dataclass(frozen=True)
class LimitViolation:
    pose_index: int
    slider: int  # 1-based, REFERENCE.md order; 0 for a limit of the whole platform (singularity)
    reason: str
    value: float
    limit: float
    unit: str

    def __str__(self) -> str:
        where = "platform" if self.slider == 0 else f"slider {self.slider}"
        unit = f" {self.unit}" if self.unit else ""
        figures = f"value {self.value:.6g}{unit}, limit {self.limit:.6g}{unit}"
        return f"pose {self.pose_index}, {where}: {self.reason} ({figures})"


class UnreachablePoseError(ValueError):
    """One or more poses cannot be reached; `violations` lists each pose, slider and reason."""

    def __init__(self, violations: list[LimitViolation]) -> None:
        self.violations = violations
        shown = "; ".join(str(v) for v in violations[:5])
        more = f" (+{len(violations) - 5} more)" if len(violations) > 5 else ""
        super().__init__(f"unreachable pose: {shown}{more}")


class ForwardKinematicsError(RuntimeError):
    """Newton did not reach the tolerance (or left the reachable set); `pose_index` is set for batches."""

    def __init__(self, iterations: int, residual_m: float, pose_index: int | None = None) -> None:
        self.iterations = iterations
        self.residual_m = residual_m
        self.pose_index = pose_index
        where = "" if pose_index is None else f" for slider set {pose_index}"
        super().__init__(
            f"forward kinematics did not converge{where}: {iterations} iterations, residual {residual_m * 1e3:.3g} mm"
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

# Poses are solved in chunks of this many so that every temporary stays in cache; the loop is over
# chunks, each chunk is vectorised.
IK_THREADS = min(2, os.cpu_count() or 1)  # batches of more than one chunk use both cores
IK_CHUNK_POSES = 4096


@dataclass(frozen=True)
class _LegGeometry:
    """One robot's leg constants as arrays, built once per robot (the description is immutable)."""

    joint_x: np.ndarray  # (6,) B_i in the platform frame
    joint_y: np.ndarray
    joint_z: np.ndarray
    rail_y: np.ndarray  # (6,)
    rail_z: float
    sides: np.ndarray  # (6,) ±1
    stroke_min: np.ndarray  # (6,)
    stroke_max: np.ndarray  # (6,)
    rod_length: float
    cone_axes: np.ndarray  # (6, 3) unit rod directions at the neutral pose
    base_cone_limit: float
    platform_cone_limit: float
    rotation_scale: float  # 1 / platform radius: makes the ω columns of J dimensionless
    condition_number_max: float
    neutral_det_sign: float  # sign of det J at the neutral pose: the assembly mode the robot works in


@functools.lru_cache(maxsize=64)
def _leg_geometry(robot: SSPRobot) -> _LegGeometry:
    joints = robot.platform_joints_m
    legs = _LegGeometry(
        joint_x=joints[:, 0].copy(),
        joint_y=joints[:, 1].copy(),
        joint_z=joints[:, 2].copy(),
        rail_y=robot.rail_y_m,
        rail_z=robot.rail_z_m,
        sides=robot.sides,
        stroke_min=robot.stroke_min_m,
        stroke_max=robot.stroke_max_m,
        rod_length=robot.rod_length_m,
        cone_axes=_neutral_rod_directions(robot),
        base_cone_limit=robot.limits.base_joint_cone_rad,
        platform_cone_limit=robot.limits.platform_joint_cone_rad,
        rotation_scale=1.0 / robot.platform_radius_m,
        condition_number_max=robot.limits.condition_number_max,
        neutral_det_sign=1.0,
    )
    # Solve the neutral pose against a positive reference sign: the sign found is the reference.
    neutral = np.asarray(robot.neutral_pose, dtype=float)[None, :]
    _, _, det_sign = _chunk_conditioning(
        legs, _chunk_leg_vectors(legs, neutral[:, :3], rotation_matrices(neutral[:, 3:]))
    )
    return replace(legs, neutral_det_sign=float(det_sign[0]))


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
                        int(pose_index),
                        slider,
                        VIOLATION_REASONS[LegViolation.ROD_CANNOT_REACH],
                        reach,
                        self.robot.rod_length_m,
                        "m",
                    )
                )
            if LegViolation.STROKE in flags:
                position = float(self.slider_positions_m[pose_index, leg])
                low, high = self.robot.stroke_min_m[leg], self.robot.stroke_max_m[leg]
                found.append(
                    LimitViolation(
                        int(pose_index),
                        slider,
                        VIOLATION_REASONS[LegViolation.STROKE],
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
                        VIOLATION_REASONS[LegViolation.BASE_CONE],
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
                        VIOLATION_REASONS[LegViolation.PLATFORM_CONE],
                        float(self.platform_cone_rad[pose_index, leg]),
                        limits.platform_joint_cone_rad,
                        "rad",
                    )
                )
            if LegViolation.SINGULARITY in flags and leg == np.flatnonzero(self.violations[pose_index])[0]:
                found.append(
                    LimitViolation(
                        int(pose_index),
                        0,
                        VIOLATION_REASONS[LegViolation.SINGULARITY],
                        _singularity_figure(self.robot, self.poses[pose_index]),
                        limits.condition_number_max,
                        "",
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
    return positions[:, None, :] + np.matmul(rotations, robot.platform_joints_m.T).swapaxes(1, 2)


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


class _LegVectors(NamedTuple):
    """Per pose and leg (n, 6): lever R·B_i, rod vector W_i − A_i and slider position, base frame, m."""

    lever_x: np.ndarray
    lever_y: np.ndarray
    lever_z: np.ndarray
    rod_x: np.ndarray
    rod_y: np.ndarray
    rod_z: np.ndarray
    sliders: np.ndarray


@numba.njit(cache=True, fastmath=False)
def _spectral_norm_bounds(matrix: np.ndarray, gram: np.ndarray, power: np.ndarray) -> tuple[float, float]:
    """Bounds on ‖A‖₂ for a 6×6 A without an SVD: with M = AᵀA and r = ‖M⁸‖_∞ (three squarings),
    λ_max(M)⁸ ≤ r ≤ √6·λ_max(M)⁸, so (r/√6)^(1/16) ≤ ‖A‖₂ ≤ r^(1/16). `gram`, `power`: 6×6 scratch."""
    for i in range(6):
        for j in range(6):
            total = 0.0
            for k in range(6):
                total += matrix[k, i] * matrix[k, j]
            gram[i, j] = total
    for _ in range(3):
        for i in range(6):
            for j in range(6):
                total = 0.0
                for k in range(6):
                    total += gram[i, k] * gram[k, j]
                power[i, j] = total
        gram[:, :] = power
    row_max = 0.0
    for i in range(6):
        row = 0.0
        for j in range(6):
            row += abs(gram[i, j])
        row_max = max(row_max, row)
    return (row_max / np.sqrt(6.0)) ** (1.0 / 16.0), row_max ** (1.0 / 16.0)


@numba.njit(cache=True, fastmath=False, nogil=True)
def _conditioning_kernel(
    lever_x: np.ndarray,
    lever_y: np.ndarray,
    lever_z: np.ndarray,
    rod_x: np.ndarray,
    rod_y: np.ndarray,
    rod_z: np.ndarray,
    rotation_scale: float,
    condition_number_max: float,
    jacobians_out: np.ndarray,
    bounds_out: np.ndarray,
    det_sign_out: np.ndarray,
) -> None:
    """Per pose: the scaled twist Jacobian J, the sign of det J, and bounds on cond₂(J) = ‖J‖₂‖J⁻¹‖₂:
    a cheap one when it already clears the limit, else within 6^(1/16) each way (`_spectral_norm_bounds`).
    bounds_out[:, 0] is the lower bound, [:, 1] the upper; NaN where a rod cannot reach (flagged
    elsewhere), inf where J is singular."""
    lu = np.empty((6, 6))
    inverse = np.empty((6, 6))
    gram = np.empty((6, 6))
    power = np.empty((6, 6))
    permutation = np.empty(6, dtype=np.int64)
    for pose in range(lever_x.shape[0]):
        jacobian = jacobians_out[pose]
        for leg in range(6):
            dx, dy, dz = rod_x[pose, leg], rod_y[pose, leg], rod_z[pose, leg]
            lx, ly, lz = lever_x[pose, leg], lever_y[pose, leg], lever_z[pose, leg]
            jacobian[leg, 0] = 1.0
            jacobian[leg, 1] = dy / dx
            jacobian[leg, 2] = dz / dx
            jacobian[leg, 3] = (ly * dz - lz * dy) / dx * rotation_scale
            jacobian[leg, 4] = (lz * dx - lx * dz) / dx * rotation_scale
            jacobian[leg, 5] = (lx * dy - ly * dx) / dx * rotation_scale
        reachable = True
        for leg in range(6):
            reachable = reachable and np.isfinite(rod_x[pose, leg])
        if not reachable:
            bounds_out[pose, 0] = np.nan
            bounds_out[pose, 1] = np.nan
            det_sign_out[pose] = np.nan
            continue
        # LU with partial pivoting: the determinant's sign and, by six solves, the inverse.
        lu[:, :] = jacobian
        for row in range(6):
            permutation[row] = row
        sign = 1.0
        singular = False
        for col in range(6):
            pivot = col
            for row in range(col + 1, 6):
                if abs(lu[row, col]) > abs(lu[pivot, col]):
                    pivot = row
            if lu[pivot, col] == 0.0:
                singular = True
                break
            if pivot != col:
                for c in range(6):
                    lu[col, c], lu[pivot, c] = lu[pivot, c], lu[col, c]
                permutation[col], permutation[pivot] = permutation[pivot], permutation[col]
                sign = -sign
            sign *= 1.0 if lu[col, col] > 0.0 else -1.0
            for row in range(col + 1, 6):
                lu[row, col] /= lu[col, col]
                for c in range(col + 1, 6):
                    lu[row, c] -= lu[row, col] * lu[col, c]
        if singular:
            bounds_out[pose, 0] = np.inf
            bounds_out[pose, 1] = np.inf
            det_sign_out[pose] = 0.0
            continue
        det_sign_out[pose] = sign
        # Cheap first: cond₂ ≤ 2/|det J|·(‖J‖_F²/6)³ (Guggenheimer, Edelman & Johnson, 1995) clears most poses.
        abs_det = 1.0
        frobenius_sq = 0.0
        for i in range(6):
            abs_det *= abs(lu[i, i])
            for k in range(6):
                frobenius_sq += jacobian[i, k] * jacobian[i, k]
        loose_bound = 2.0 / abs_det * (frobenius_sq / 6.0) ** 3
        if loose_bound <= condition_number_max:
            bounds_out[pose, 0] = 1.0
            bounds_out[pose, 1] = loose_bound
            continue
        for unit in range(6):
            for row in range(6):  # forward substitution, L has a unit diagonal
                value = 1.0 if permutation[row] == unit else 0.0
                for c in range(row):
                    value -= lu[row, c] * inverse[c, unit]
                inverse[row, unit] = value
            for row in range(5, -1, -1):
                value = inverse[row, unit]
                for c in range(row + 1, 6):
                    value -= lu[row, c] * inverse[c, unit]
                inverse[row, unit] = value / lu[row, row]
        norm_low, norm_high = _spectral_norm_bounds(jacobian, gram, power)
        inverse_low, inverse_high = _spectral_norm_bounds(inverse, gram, power)
        bounds_out[pose, 0] = norm_low * inverse_low
        bounds_out[pose, 1] = norm_high * inverse_high


def _chunk_leg_vectors(legs: _LegGeometry, positions: np.ndarray, rotations: np.ndarray) -> _LegVectors:
    """Levers R·B_i (x, y, z), rod vectors W_i − A_i (x, y, z) and slider positions, each (n, 6)."""
    # Rotation entries as (n, 1) columns so that each product broadcasts over the six legs.
    r = [[rotations[:, row, col, None] for col in range(3)] for row in range(3)]
    lever_x = r[0][0] * legs.joint_x + r[0][1] * legs.joint_y + r[0][2] * legs.joint_z
    lever_y = r[1][0] * legs.joint_x + r[1][1] * legs.joint_y + r[1][2] * legs.joint_z
    lever_z = r[2][0] * legs.joint_x + r[2][1] * legs.joint_y + r[2][2] * legs.joint_z
    rod_y = lever_y + (positions[:, 1, None] - legs.rail_y)
    rod_z = lever_z + (positions[:, 2, None] - legs.rail_z)
    reach_sq = legs.rod_length**2 - rod_y * rod_y - rod_z * rod_z
    with np.errstate(invalid="ignore"):
        rod_x = -legs.sides * np.sqrt(reach_sq)  # NaN exactly where the rod cannot reach its rail
    sliders = lever_x + positions[:, 0, None] - rod_x
    return _LegVectors(lever_x, lever_y, lever_z, rod_x, rod_y, rod_z, sliders)


def _chunk_conditioning(legs: _LegGeometry, vectors: _LegVectors) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scaled twist Jacobians (n, 6, 6), bounds on their condition numbers (n, 2) and det signs (n,)."""
    count = len(vectors.lever_x)
    jacobians = np.empty((count, 6, 6))
    bounds = np.empty((count, 2))
    det_sign = np.empty(count)
    _conditioning_kernel(*vectors[:6], legs.rotation_scale, legs.condition_number_max, jacobians, bounds, det_sign)
    return jacobians, bounds, det_sign


def _solve_chunk(
    legs: _LegGeometry,
    positions: np.ndarray,
    rotations: np.ndarray,
    sliders_out: np.ndarray,
    violations_out: np.ndarray,
    base_cone_out: np.ndarray,
    platform_cone_out: np.ndarray,
    singularity_check: bool,
) -> None:
    """Closed-form IK of one chunk (n poses × 6 legs), written into the `*_out` arrays."""
    vectors = _chunk_leg_vectors(legs, positions, rotations)
    rod_x, rod_y, rod_z = vectors.rod_x, vectors.rod_y, vectors.rod_z
    sliders_out[:] = vectors.sliders
    cannot_reach = np.isnan(rod_x)

    # Cone angles of the rod direction d = (W − A)/L against the neutral directions: at the slider in
    # the base frame, and at the platform in the (rotating) platform frame.
    axis_x, axis_y, axis_z = legs.cone_axes.T
    inverse_length = 1.0 / legs.rod_length
    base_cos = (rod_x * axis_x + rod_y * axis_y + rod_z * axis_z) * inverse_length
    r = [[rotations[:, row, col, None] for col in range(3)] for row in range(3)]
    rotated_x = r[0][0] * axis_x + r[0][1] * axis_y + r[0][2] * axis_z
    rotated_y = r[1][0] * axis_x + r[1][1] * axis_y + r[1][2] * axis_z
    rotated_z = r[2][0] * axis_x + r[2][1] * axis_y + r[2][2] * axis_z
    platform_cos = (rod_x * rotated_x + rod_y * rotated_y + rod_z * rotated_z) * inverse_length
    np.arccos(np.clip(base_cos, -1.0, 1.0), out=base_cone_out)
    np.arccos(np.clip(platform_cos, -1.0, 1.0), out=platform_cone_out)

    violations_out[:] = cannot_reach.view(np.uint8) * np.uint8(LegViolation.ROD_CANNOT_REACH)
    violations_out |= ((sliders_out < legs.stroke_min) | (sliders_out > legs.stroke_max)).view(np.uint8) * np.uint8(
        LegViolation.STROKE
    )
    violations_out |= (base_cone_out > legs.base_cone_limit).view(np.uint8) * np.uint8(LegViolation.BASE_CONE)
    violations_out |= (platform_cone_out > legs.platform_cone_limit).view(np.uint8) * np.uint8(
        LegViolation.PLATFORM_CONE
    )
    if singularity_check:
        violations_out[_singular_poses(legs, vectors)] |= np.uint8(LegViolation.SINGULARITY)


def _singular_poses(legs: _LegGeometry, vectors: _LegVectors) -> np.ndarray:
    """(n,) True where cond(J) exceeds its limit or det J has left the neutral pose's sign. The exact
    condition number (an SVD) is computed only where the cheap bounds leave the answer open."""
    jacobians, bounds, det_sign = _chunk_conditioning(legs, vectors)
    other_mode = det_sign == -legs.neutral_det_sign
    singular = other_mode | (bounds[:, 0] > legs.condition_number_max) | (det_sign == 0.0)
    unclear = np.flatnonzero(~singular & (bounds[:, 1] > legs.condition_number_max))
    if unclear.size:
        singular[unclear] = np.linalg.cond(jacobians[unclear]) > legs.condition_number_max
    return singular


def _solve(
    robot: SSPRobot,
    positions: np.ndarray,
    rotations: np.ndarray | None,
    poses: np.ndarray,
    singularity_check: bool = True,
) -> IKSolution:
    """IK for all poses, chunk by chunk; rotations are built per chunk from `poses` when not given."""
    legs = _leg_geometry(robot)
    count = len(positions)
    sliders = np.empty((count, 6))
    violations = np.empty((count, 6), dtype=np.uint8)
    base_cone = np.empty((count, 6))
    platform_cone = np.empty((count, 6))

    def solve_chunk(start: int) -> None:
        chunk = slice(start, start + IK_CHUNK_POSES)
        chunk_rotations = rotation_matrices(poses[chunk, 3:]) if rotations is None else rotations[chunk]
        _solve_chunk(
            legs,
            positions[chunk],
            chunk_rotations,
            sliders[chunk],
            violations[chunk],
            base_cone[chunk],
            platform_cone[chunk],
            singularity_check,
        )

    starts = range(0, count, IK_CHUNK_POSES)
    if len(starts) > 1 and IK_THREADS > 1:
        # Chunks write disjoint slices; numpy's large ufuncs and the nogil conditioning kernel run in parallel.
        with ThreadPoolExecutor(IK_THREADS) as pool:
            list(pool.map(solve_chunk, starts))
    else:
        for start in starts:
            solve_chunk(start)
    return IKSolution(poses, sliders, violations, base_cone, platform_cone, robot)


def solve_ik_pose_rotation(
    robot: SSPRobot, positions: np.ndarray, rotations: np.ndarray, poses: np.ndarray
) -> IKSolution:
    """IK from platform positions (N, 3) and rotations (N, 3, 3); `poses` is kept for reporting."""
    return _solve(robot, np.asarray(positions, dtype=float), np.asarray(rotations, dtype=float), poses)


def inverse_kinematics(
    robot: SSPRobot, poses: np.ndarray, *, check: bool = True, singularity_check: bool = True
) -> IKSolution:
    """Slider positions (m) for poses (N, 6). With `check`, any unreachable pose raises
    `UnreachablePoseError` naming the pose, slider, reason and limit; without it the caller reads
    `violations` (the safety supervisor and the workspace tool do). `singularity_check=False` skips
    the Jacobian conditioning screen (SINGULARITY never set): only for callers that screen elsewhere."""
    poses = _as_poses(poses)
    solution = _solve(robot, poses[:, :3], None, poses, singularity_check)
    if check:
        solution.raise_if_unreachable()
    return solution


# --- Jacobians ------------------------------------------------------------------------------------


def twist_jacobian(robot: SSPRobot, poses: np.ndarray, slider_positions_m: np.ndarray | None = None) -> np.ndarray:
    """J with slider velocities = J · (v, ω), ω in the base frame. Shape (N, 6, 6).

    From |W_i − A_i|² = L²: d·(v + ω × R·B_i − ẋ_i e_x) = 0, so ẋ_i = (d·v + (R·B_i × d)·ω) / d_x.
    The Jacobian is geometry: it exists beyond the stroke and cone limits (so that the condition number
    can be followed toward a singularity), but not where a rod cannot reach its rail, which raises
    `UnreachablePoseError`.
    """
    poses = _as_poses(poses)
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
    poses = _as_poses(poses)
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


def _singularity_figure(robot: SSPRobot, pose: np.ndarray) -> float:
    """cond(J) of one pose, or inf when the pose lies beyond a singularity (det J changed sign)."""
    beyond = np.sign(np.linalg.det(twist_jacobian(robot, pose)[0])) == -_leg_geometry(robot).neutral_det_sign
    return np.inf if beyond else float(condition_number(robot, pose)[0])


# --- Forward kinematics (single pose, per tick) -----------------------------------------------------


@dataclass(frozen=True)
class FKResult:
    pose: np.ndarray  # (6,)
    iterations: int
    residual_m: float  # max |IK(pose) − sliders|


@numba.njit(cache=True, fastmath=False)
def _fk_residual_and_jacobian(
    pose: np.ndarray,
    sliders: np.ndarray,
    joints: np.ndarray,
    rail_y: np.ndarray,
    rail_z: float,
    sides: np.ndarray,
    rod_length: float,
    residual: np.ndarray,
    jacobian: np.ndarray,
    rotation: np.ndarray,
) -> tuple[float, float]:
    """IK(pose) − sliders into `residual` and the pose Jacobian into `jacobian`; returns (max |r|, |r|²),
    both inf when a rod cannot reach its rail at `pose`."""
    rotation_into(pose[3], pose[4], pose[5], rotation)
    r00, r01, r02 = rotation[0, 0], rotation[0, 1], rotation[0, 2]
    r10, r11, r12 = rotation[1, 0], rotation[1, 1], rotation[1, 2]
    r20, r21, r22 = rotation[2, 0], rotation[2, 1], rotation[2, 2]
    ca, sa = np.cos(pose[3]), np.sin(pose[3])
    cb, sb = np.cos(pose[4]), np.sin(pose[4])
    max_residual = 0.0
    squared_norm = 0.0
    for leg in range(6):
        bx, by, bz = joints[leg, 0], joints[leg, 1], joints[leg, 2]
        lx = r00 * bx + r01 * by + r02 * bz
        ly = r10 * bx + r11 * by + r12 * bz
        lz = r20 * bx + r21 * by + r22 * bz
        dy = pose[1] + ly - rail_y[leg]
        dz = pose[2] + lz - rail_z
        reach_sq = rod_length * rod_length - dy * dy - dz * dz
        if reach_sq <= 0.0:
            return np.inf, np.inf
        along = np.sqrt(reach_sq)
        value = pose[0] + lx + sides[leg] * along - sliders[leg]
        residual[leg] = value
        max_residual = max(max_residual, abs(value))
        squared_norm += value * value
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
    return max_residual, squared_norm


# Step halvings allowed per Newton step before giving up: 2⁻¹⁰ of a Newton step is no progress.
_FK_MAX_HALVINGS = 10


@numba.njit(cache=True, fastmath=False)
def _fk_newton_steps(
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
    """Newton on IK(pose) = sliders with step halving (the step must keep every rod on its rail and
    lower |r|). Returns (Newton steps, max |r|); steps are negative when it did not converge."""
    pose = guess.copy()
    trial = np.empty(6)
    residual = np.empty(6)
    jacobian = np.empty((6, 6))
    rotation = np.empty((3, 3))
    max_residual, squared_norm = _fk_residual_and_jacobian(
        pose, sliders, joints, rail_y, rail_z, sides, rod_length, residual, jacobian, rotation
    )
    iteration = 0
    while max_residual > tolerance:
        if iteration == max_iterations or not np.isfinite(max_residual):
            pose_out[:] = pose
            return -iteration, max_residual
        step = np.linalg.solve(jacobian, residual)
        iteration += 1
        scale = 1.0
        for _ in range(_FK_MAX_HALVINGS + 1):
            trial[:] = pose - scale * step
            trial_max, trial_norm = _fk_residual_and_jacobian(
                trial, sliders, joints, rail_y, rail_z, sides, rod_length, residual, jacobian, rotation
            )
            if trial_norm < squared_norm:
                break
            scale *= 0.5
        else:
            pose_out[:] = pose
            return -iteration, max_residual
        pose[:] = trial
        max_residual, squared_norm = trial_max, trial_norm
    pose_out[:] = pose
    return iteration, max_residual


# Slider-space continuation used when Newton from the guess fails (a cold start far from the pose):
# walk the sliders from IK(guess) to the target in this many equal steps, then four times as many.
_FK_CONTINUATION_STEPS = (4, 16)


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
    """Newton from `guess`; if that fails, continuation along the straight slider path from IK(guess).
    A pose in another assembly mode than the guess (det J changed sign: a singularity lies between)
    is a failure, never an answer. Returns (total Newton steps, max |r|); negative steps: no convergence."""
    start_sliders = np.empty(6)
    jacobian = np.empty((6, 6))
    start_residual, _ = _fk_residual_and_jacobian(
        guess, np.zeros(6), joints, rail_y, rail_z, sides, rod_length, start_sliders, jacobian, np.empty((3, 3))
    )
    if not np.isfinite(start_residual):  # the guess itself is impossible
        pose_out[:] = guess
        return 0, np.inf
    guess_det_sign = np.sign(np.linalg.det(jacobian))
    iterations, residual = _fk_newton_steps(
        sliders, guess, joints, rail_y, rail_z, sides, rod_length, tolerance, max_iterations, pose_out
    )
    if iterations >= 0 and _same_assembly_mode(pose_out, guess_det_sign, joints, rail_y, rail_z, sides, rod_length):
        return iterations, residual
    more, residual = _fk_continuation(
        sliders, start_sliders, guess, joints, rail_y, rail_z, sides, rod_length, tolerance, max_iterations, pose_out
    )
    iterations = abs(iterations) + abs(more)
    if more >= 0 and _same_assembly_mode(pose_out, guess_det_sign, joints, rail_y, rail_z, sides, rod_length):
        return iterations, residual
    return -max(iterations, 1), residual


@numba.njit(cache=True, fastmath=False)
def _same_assembly_mode(
    pose: np.ndarray,
    det_sign: float,
    joints: np.ndarray,
    rail_y: np.ndarray,
    rail_z: float,
    sides: np.ndarray,
    rod_length: float,
) -> bool:
    residual = np.empty(6)
    jacobian = np.empty((6, 6))
    rotation = np.empty((3, 3))
    _fk_residual_and_jacobian(
        pose, np.zeros(6), joints, rail_y, rail_z, sides, rod_length, residual, jacobian, rotation
    )
    return bool(np.sign(np.linalg.det(jacobian)) == det_sign)


@numba.njit(cache=True, fastmath=False)
def _fk_continuation(
    sliders: np.ndarray,
    start_sliders: np.ndarray,
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
    """Newton along the straight slider path from `start_sliders` = IK(guess) to `sliders`."""
    pose = np.empty(6)
    target = np.empty(6)
    total = 0
    residual = np.inf
    for step_count in _FK_CONTINUATION_STEPS:
        pose[:] = guess
        for step in range(1, step_count + 1):
            target[:] = start_sliders + (sliders - start_sliders) * (step / step_count)
            steps, residual = _fk_newton_steps(
                target, pose, joints, rail_y, rail_z, sides, rod_length, tolerance, max_iterations, pose_out
            )
            total += abs(steps)
            if steps < 0 or not np.isfinite(residual):
                break
            pose[:] = pose_out
        else:
            return total, residual
    pose_out[:] = guess
    return -max(total, 1), residual


@numba.njit(cache=True, fastmath=False)
def _fk_newton_batch(
    sliders: np.ndarray,
    guesses: np.ndarray,
    joints: np.ndarray,
    rail_y: np.ndarray,
    rail_z: float,
    sides: np.ndarray,
    rod_length: float,
    tolerance: float,
    max_iterations: int,
    poses_out: np.ndarray,
    iterations_out: np.ndarray,
    residuals_out: np.ndarray,
) -> None:
    for index in range(sliders.shape[0]):
        iterations, residual = _fk_newton(
            sliders[index],
            guesses[index],
            joints,
            rail_y,
            rail_z,
            sides,
            rod_length,
            tolerance,
            max_iterations,
            poses_out[index],
        )
        iterations_out[index] = iterations
        residuals_out[index] = residual


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

    def solve_batch(
        self, slider_positions_m: np.ndarray, guesses: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Independent solves of (N, 6) slider sets, each from its guess (default: neutral), in one
        compiled loop; does not touch the warm start. Returns poses (N, 6), iterations (N,), residuals (N,) m."""
        sliders = np.ascontiguousarray(np.atleast_2d(np.asarray(slider_positions_m, dtype=float)))
        if sliders.ndim != 2 or sliders.shape[1] != 6 or not np.all(np.isfinite(sliders)):
            raise ValueError(f"slider_positions_m: shape {sliders.shape}, expected (N, 6) finite values (m)")
        start = self.robot.neutral_pose if guesses is None else guesses
        starts = np.ascontiguousarray(np.broadcast_to(np.asarray(start, dtype=float), sliders.shape))
        poses = np.empty_like(sliders)
        iterations = np.empty(len(sliders), dtype=np.int64)
        residuals = np.empty(len(sliders))
        _fk_newton_batch(
            sliders,
            starts,
            self._joints,
            self._rail_y,
            self.robot.rail_z_m,
            self._sides,
            self.robot.rod_length_m,
            self.tolerance_m,
            self.max_iterations,
            poses,
            iterations,
            residuals,
        )
        failed = np.flatnonzero((iterations < 0) | ~np.isfinite(residuals))
        if failed.size:
            first = int(failed[0])
            raise ForwardKinematicsError(abs(int(iterations[first])), float(residuals[first]), first)
        return poses, iterations, residuals


def forward_kinematics(
    robot: SSPRobot,
    slider_positions_m: np.ndarray,
    guesses: np.ndarray | None = None,
    *,
    tolerance_m: float = 1e-12,
    max_iterations: int = 20,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """FK for many slider sets (N, 6), each from its own guess (default: neutral).
    Returns poses (N, 6), iterations (N,) and residuals (N,) in m; raises `ForwardKinematicsError`
    naming the first slider set that does not converge."""
    solver = ForwardKinematics(robot, tolerance_m=tolerance_m, max_iterations=max_iterations)
    return solver.solve_batch(slider_positions_m, guesses)


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
