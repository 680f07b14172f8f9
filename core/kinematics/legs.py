"""One leg of the 6-SSP robot, compiled once for every caller: IK, FK, dynamics, clearance and the tick.

Closed form (REFERENCE.md §1): with the lever ℓ = R·B_i and W_i = p + ℓ, the rod vector from the slider
joint A_i = (x_i, y_rail, z_rail) to W_i is d = (−side·h, W_y − y_rail, W_z − z_rail),
h = √(L² − d_y² − d_z²), and the slider sits at x_i = W_x − d_x. Its twist-Jacobian row is
(d, ℓ × d) / d_x (slider velocity = row · (v, ω), ω in the base frame).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numba
import numpy as np

from core.robot import SSPRobot
from core.rotations import rotation_into


class LegGeometry(NamedTuple):
    """One robot's legs and limits as arrays, in a form numba accepts as one argument."""

    joints: np.ndarray  # (6, 3) B_i, platform frame
    rail_y: np.ndarray  # (6,)
    sides: np.ndarray  # (6,) ±1
    stroke_min: np.ndarray  # (6,)
    stroke_max: np.ndarray  # (6,)
    cone_axes: np.ndarray  # (6, 3) unit rod directions at the neutral pose
    rail_z: float
    rod_length: float
    base_cone_limit: float
    platform_cone_limit: float
    rotation_scale: float  # 1 / platform radius: makes the ω columns of J dimensionless
    condition_number_max: float
    neutral_det_sign: float  # sign of det J at neutral: the assembly mode the robot works in


@numba.njit(cache=True, nogil=True)
def leg_kernel(
    bx: float,
    by: float,
    bz: float,
    rail_y: float,
    side: float,
    rail_z: float,
    rod_length: float,
    px: float,
    py: float,
    pz: float,
    rotation: np.ndarray,
) -> tuple[float, float, float, float, float, float, float, float]:
    """(ℓx, ℓy, ℓz, dx, dy, dz, slider x, h²) for one leg at platform position p and rotation R.
    Where the rod cannot reach its rail (h² < 0), dx and the slider are NaN; h² tells by how much."""
    lx = rotation[0, 0] * bx + rotation[0, 1] * by + rotation[0, 2] * bz
    ly = rotation[1, 0] * bx + rotation[1, 1] * by + rotation[1, 2] * bz
    lz = rotation[2, 0] * bx + rotation[2, 1] * by + rotation[2, 2] * bz
    dy = ly + (py - rail_y)
    dz = lz + (pz - rail_z)
    reach_sq = rod_length * rod_length - dy * dy - dz * dz
    along = math.sqrt(reach_sq) if reach_sq >= 0.0 else np.nan
    dx = -side * along
    return lx, ly, lz, dx, dy, dz, lx + px - dx, reach_sq


@numba.njit(cache=True, nogil=True)
def leg_solution(
    geometry: LegGeometry, leg: int, px: float, py: float, pz: float, rotation: np.ndarray
) -> tuple[float, float, float, float, float, float, float, float]:
    """`leg_kernel` for leg `leg` of a robot described by `geometry`."""
    joint = geometry.joints[leg]
    return leg_kernel(
        joint[0],
        joint[1],
        joint[2],
        geometry.rail_y[leg],
        geometry.sides[leg],
        geometry.rail_z,
        geometry.rod_length,
        px,
        py,
        pz,
        rotation,
    )


@numba.njit(cache=True, nogil=True)
def twist_row(
    lx: float, ly: float, lz: float, dx: float, dy: float, dz: float
) -> tuple[float, float, float, float, float, float]:
    """The leg's twist-Jacobian row (d, ℓ × d) / d_x."""
    return (
        1.0,
        dy / dx,
        dz / dx,
        (ly * dz - lz * dy) / dx,
        (lz * dx - lx * dz) / dx,
        (lx * dy - ly * dx) / dx,
    )


def neutral_rod_directions(robot: SSPRobot) -> np.ndarray:
    """Unit rod vectors, slider joint → platform joint, at the neutral pose: the cone axes. (6, 3)."""
    neutral = np.asarray(robot.neutral_pose, dtype=float)
    rotation = np.empty((3, 3))
    rotation_into(neutral[3], neutral[4], neutral[5], rotation)
    directions = np.empty((6, 3))
    for leg, (joint, rail_y, side) in enumerate(zip(robot.platform_joints_m, robot.rail_y_m, robot.sides, strict=True)):
        _, _, _, dx, dy, dz, _, _ = leg_kernel(
            joint[0],
            joint[1],
            joint[2],
            rail_y,
            side,
            robot.rail_z_m,
            robot.rod_length_m,
            neutral[0],
            neutral[1],
            neutral[2],
            rotation,
        )
        directions[leg] = (dx, dy, dz)
    return directions / robot.rod_length_m


def geometry_without_mode(robot: SSPRobot) -> LegGeometry:
    """The robot's `LegGeometry` with a provisional assembly-mode sign (+1)."""
    return LegGeometry(
        joints=np.ascontiguousarray(robot.platform_joints_m),
        rail_y=np.ascontiguousarray(robot.rail_y_m),
        sides=np.ascontiguousarray(robot.sides),
        stroke_min=np.ascontiguousarray(robot.stroke_min_m),
        stroke_max=np.ascontiguousarray(robot.stroke_max_m),
        cone_axes=np.ascontiguousarray(neutral_rod_directions(robot)),
        rail_z=float(robot.rail_z_m),
        rod_length=float(robot.rod_length_m),
        base_cone_limit=float(robot.limits.base_joint_cone_rad),
        platform_cone_limit=float(robot.limits.platform_joint_cone_rad),
        rotation_scale=1.0 / robot.platform_radius_m,
        condition_number_max=float(robot.limits.condition_number_max),
        neutral_det_sign=1.0,
    )


@functools.lru_cache(maxsize=64)
def leg_geometry(robot: SSPRobot) -> LegGeometry:
    """The robot's `LegGeometry`, built once per robot (the description is immutable), with the sign of
    det J at its neutral pose (solved against a provisional +1: the sign found is the reference)."""
    from core.kinematics.conditioning import det_sign_of

    provisional = geometry_without_mode(robot)
    return provisional._replace(neutral_det_sign=det_sign_of(provisional, np.asarray(robot.neutral_pose, dtype=float)))
