"""Closed-form inverse kinematics of one robot with every leg's limit check (REFERENCE.md §1).

x_i = W_ix + side_i · sqrt(L² − (W_iy − y_rail,i)² − (W_iz − z_rail)²) for N poses, in one compiled loop
per chunk of poses (`core.kinematics.legs.leg_solution` per leg); chunks run on both cores.
"""

from __future__ import annotations

import enum
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numba
import numpy as np

from core.kinematics.conditioning import exact_conditioning, singular_poses
from core.kinematics.legs import LegGeometry, leg_geometry, leg_solution, twist_row
from core.kinematics.rotations import rotation_matrices
from core.robot import SSPRobot


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
    # Two parts of the twin that share no joint come closer than the clearance margin (core.clearance).
    # A property of the whole twin pose: set on all legs of both robots.
    COLLISION = 32


VIOLATION_REASONS = {
    LegViolation.ROD_CANNOT_REACH: "rod cannot reach its rail",
    LegViolation.STROKE: "slider outside its stroke",
    LegViolation.BASE_CONE: "slider joint beyond its cone",
    LegViolation.PLATFORM_CONE: "platform joint beyond its cone",
    LegViolation.SINGULARITY: "too close to or beyond a singularity",
    LegViolation.COLLISION: "collision",
}


@dataclass(frozen=True)
class LimitViolation:
    pose_index: int
    slider: int  # 1-based, REFERENCE.md order; 0 for a limit of the whole platform (singularity, collision)
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


def as_poses(poses: np.ndarray) -> np.ndarray:
    """Poses as a finite (N, 6) float array; refuses anything else naming the shape or the pose."""
    poses = np.asarray(poses, dtype=float)
    if poses.ndim == 1:
        poses = poses[None, :]
    if poses.ndim != 2 or poses.shape[1] != 6:
        raise ValueError(f"poses: shape {poses.shape}, expected (N, 6) as (x, y, z, roll, pitch, yaw)")
    if not np.all(np.isfinite(poses)):
        bad = int(np.argwhere(~np.isfinite(poses))[0, 0])
        raise ValueError(f"poses[{bad}] = {poses[bad].tolist()}: must be finite (no NaN/inf)")
    return poses


_as_poses = as_poses  # the name other modules imported before the split

# Poses are solved in chunks of this many so that every temporary stays in cache.
IK_THREADS = min(2, os.cpu_count() or 1)  # batches of more than one chunk use both cores
IK_CHUNK_POSES = 4096


def for_each_chunk(count: int, solve_chunk: Callable[[slice], None], chunk_size: int = IK_CHUNK_POSES) -> None:
    """`solve_chunk(rows)` for consecutive slices of `count` rows; on both cores when there is more than one
    chunk: callers write disjoint slices, with compiled kernels that release the GIL."""
    chunks = [slice(start, start + chunk_size) for start in range(0, count, chunk_size)]
    if len(chunks) > 1 and IK_THREADS > 1:
        with ThreadPoolExecutor(IK_THREADS) as pool:
            list(pool.map(solve_chunk, chunks))
    else:
        for rows in chunks:
            solve_chunk(rows)


@dataclass(frozen=True)
class PoseCollisions:
    """The twin's closest pair of parts per pose (core.clearance), attached to each robot's solution."""

    # (N,) smallest clearance between parts that share no joint; exact below clearance_min_m + 0.1 m,
    # else that bound (core.clearance.IK_EXACT_BELOW_M); `core.clearance.min_clearance` is exact everywhere.
    clearance_m: np.ndarray
    closest_pair: np.ndarray  # (N,) index into `pair_names`
    pair_names: tuple[str, ...]  # "right rod 3 – left rod 3"
    clearance_min_m: float  # the margin: closer than this is a collision


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
    collisions: PoseCollisions | None = None  # set by the twin IK, which checks clearance

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
            pose = int(pose_index)
            if LegViolation.ROD_CANNOT_REACH in flags:
                reach = _rod_reach_distance(self.robot, self.poses[pose : pose + 1])[0, leg]
                found.append(
                    LimitViolation(
                        pose,
                        slider,
                        VIOLATION_REASONS[LegViolation.ROD_CANNOT_REACH],
                        reach,
                        self.robot.rod_length_m,
                        "m",
                    )
                )
            if LegViolation.STROKE in flags:
                position = float(self.slider_positions_m[pose, leg])
                low, high = self.robot.stroke_min_m[leg], self.robot.stroke_max_m[leg]
                found.append(
                    LimitViolation(
                        pose,
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
                        pose,
                        slider,
                        VIOLATION_REASONS[LegViolation.BASE_CONE],
                        float(self.base_cone_rad[pose, leg]),
                        limits.base_joint_cone_rad,
                        "rad",
                    )
                )
            if LegViolation.PLATFORM_CONE in flags:
                found.append(
                    LimitViolation(
                        pose,
                        slider,
                        VIOLATION_REASONS[LegViolation.PLATFORM_CONE],
                        float(self.platform_cone_rad[pose, leg]),
                        limits.platform_joint_cone_rad,
                        "rad",
                    )
                )
            first_leg = leg == np.flatnonzero(self.violations[pose])[0]
            if LegViolation.SINGULARITY in flags and first_leg:
                found.append(
                    LimitViolation(
                        pose,
                        0,
                        VIOLATION_REASONS[LegViolation.SINGULARITY],
                        _singularity_figure(self.robot, self.poses[pose]),
                        limits.condition_number_max,
                        "",
                    )
                )
            if LegViolation.COLLISION in flags and first_leg and self.collisions is not None:
                pair = self.collisions.pair_names[int(self.collisions.closest_pair[pose])]
                found.append(
                    LimitViolation(
                        pose,
                        0,
                        f"{VIOLATION_REASONS[LegViolation.COLLISION]} {pair}: clearance",
                        float(self.collisions.clearance_m[pose]),
                        self.collisions.clearance_min_m,
                        "m",
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


def _singularity_figure(robot: SSPRobot, pose: np.ndarray) -> float:
    """cond(J) of one pose, or inf when the pose lies beyond a singularity (det J changed sign)."""
    geometry = leg_geometry(robot)
    condition, sign = exact_conditioning(geometry, pose[None, :3], rotation_matrices(pose[None, 3:]))
    return np.inf if sign[0] == -geometry.neutral_det_sign else float(condition[0])


@numba.njit(cache=True, nogil=True)
def _ik_chunk_kernel(
    geometry: LegGeometry,
    positions: np.ndarray,
    rotations: np.ndarray,
    with_jacobians: bool,
    sliders_out: np.ndarray,
    violations_out: np.ndarray,
    base_cone_out: np.ndarray,
    platform_cone_out: np.ndarray,
    jacobians_out: np.ndarray,
    reachable_out: np.ndarray,
) -> None:
    """Closed-form IK, stroke and cone checks of n poses; with `with_jacobians`, the scaled twist
    Jacobians too (for the singularity screen)."""
    inverse_length = 1.0 / geometry.rod_length
    scale = geometry.rotation_scale
    for pose in range(positions.shape[0]):
        rotation = rotations[pose]
        reachable = True
        for leg in range(6):
            lx, ly, lz, dx, dy, dz, slider, _ = leg_solution(
                geometry, leg, positions[pose, 0], positions[pose, 1], positions[pose, 2], rotation
            )
            sliders_out[pose, leg] = slider
            flags = np.uint8(0)
            if np.isnan(dx):
                flags |= np.uint8(1)  # ROD_CANNOT_REACH
                reachable = False
            if slider < geometry.stroke_min[leg] or slider > geometry.stroke_max[leg]:
                flags |= np.uint8(2)  # STROKE
            # Cone angles of d/L against the neutral direction: at the slider in the base frame, and
            # at the platform in the (rotating) platform frame.
            ax, ay, az = geometry.cone_axes[leg, 0], geometry.cone_axes[leg, 1], geometry.cone_axes[leg, 2]
            base_cos = (dx * ax + dy * ay + dz * az) * inverse_length
            qx = rotation[0, 0] * ax + rotation[0, 1] * ay + rotation[0, 2] * az
            qy = rotation[1, 0] * ax + rotation[1, 1] * ay + rotation[1, 2] * az
            qz = rotation[2, 0] * ax + rotation[2, 1] * ay + rotation[2, 2] * az
            platform_cos = (dx * qx + dy * qy + dz * qz) * inverse_length
            base_cone = np.arccos(min(1.0, max(-1.0, base_cos))) if not np.isnan(base_cos) else np.nan
            platform_cone = np.arccos(min(1.0, max(-1.0, platform_cos))) if not np.isnan(platform_cos) else np.nan
            base_cone_out[pose, leg] = base_cone
            platform_cone_out[pose, leg] = platform_cone
            if base_cone > geometry.base_cone_limit:
                flags |= np.uint8(4)  # BASE_CONE
            if platform_cone > geometry.platform_cone_limit:
                flags |= np.uint8(8)  # PLATFORM_CONE
            violations_out[pose, leg] = flags
            if with_jacobians:
                row = twist_row(lx, ly, lz, dx, dy, dz)
                for column in range(3):
                    jacobians_out[pose, leg, column] = row[column]
                    jacobians_out[pose, leg, 3 + column] = row[3 + column] * scale
        reachable_out[pose] = reachable


def _solve_chunk(
    geometry: LegGeometry,
    positions: np.ndarray,
    rotations: np.ndarray,
    sliders_out: np.ndarray,
    violations_out: np.ndarray,
    base_cone_out: np.ndarray,
    platform_cone_out: np.ndarray,
    singularity_check: bool,
) -> None:
    count = len(positions)
    jacobians = np.empty((count if singularity_check else 0, 6, 6))
    reachable = np.empty(count, dtype=np.bool_)
    _ik_chunk_kernel(
        geometry,
        np.ascontiguousarray(positions),
        np.ascontiguousarray(rotations),
        singularity_check,
        sliders_out,
        violations_out,
        base_cone_out,
        platform_cone_out,
        jacobians,
        reachable,
    )
    if singularity_check:
        violations_out[singular_poses(geometry, jacobians, reachable)] |= np.uint8(LegViolation.SINGULARITY)


def _solve(
    robot: SSPRobot,
    positions: np.ndarray,
    rotations: np.ndarray | None,
    poses: np.ndarray,
    singularity_check: bool = True,
) -> IKSolution:
    """IK for all poses, chunk by chunk; rotations are built per chunk from `poses` when not given."""
    geometry = leg_geometry(robot)
    count = len(positions)
    sliders = np.empty((count, 6))
    violations = np.empty((count, 6), dtype=np.uint8)
    base_cone = np.empty((count, 6))
    platform_cone = np.empty((count, 6))

    def solve_chunk(chunk: slice) -> None:
        chunk_rotations = rotation_matrices(poses[chunk, 3:]) if rotations is None else rotations[chunk]
        _solve_chunk(
            geometry,
            positions[chunk],
            chunk_rotations,
            sliders[chunk],
            violations[chunk],
            base_cone[chunk],
            platform_cone[chunk],
            singularity_check,
        )

    for_each_chunk(count, solve_chunk)
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
    poses = as_poses(poses)
    solution = _solve(robot, poses[:, :3], None, poses, singularity_check)
    if check:
        solution.raise_if_unreachable()
    return solution
