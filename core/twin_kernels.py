"""Per-tick twin kinematics, compiled: stance pose → twelve slider set-points with every limit check,
and measured sliders → stance pose.

The batch paths (`core.kinematics.twin_inverse_kinematics`, used by the offline prescription check)
stay the reference; this is the same closed-form IK (REFERENCE.md §1) and the same cone definitions,
fused into one allocation-free call so that a tick costs microseconds. The tests compare the two.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from core.clearance import PartArrays, TwinClearance, min_clearance_kernel, twin_clearance, twin_segments_into
from core.kinematics import (
    ForwardKinematicsError,
    LegGeometry,
    leg_geometry,
    leg_solution,
    rotation_matrices,
    stance_origin_world,
    yaw_matrix,
)
from core.kinematics.fk import _fk_newton
from core.robot import TwinRobot
from core.rotations import rotation_into

# Row layout of the (4,) violation output: code, axis (0..11, −1 for the whole body), value, limit.
VIOLATION_FIELDS = 4
# Violation codes; core.plan.limits.LimitCode names the same numbers (a test checks).
ROD_REACH, STROKE, BASE_JOINT_CONE, PLATFORM_JOINT_CONE, TILT, SLIDER_VELOCITY, SLIDER_ACCELERATION = range(1, 8)
COLLISION = 10
# The limits vector the command kernel reads (core.plan.limits.SessionLimits builds it): base cone, platform cone,
# tilt, slider velocity, slider acceleration, drive force, clearance.
LIMITS_VECTOR_SIZE = 7
# Every limit open: infinite bounds, no clearance required (start-up states are not checked).
UNCHECKED_LIMITS = np.array([np.inf] * (LIMITS_VECTOR_SIZE - 1) + [-np.inf])


@numba.njit(cache=True)
def _set_violation(violation: np.ndarray, code: int, axis: int, value: float, limit: float) -> None:
    if violation[0] == 0:  # keep the first one found
        violation[0] = code
        violation[1] = axis
        violation[2] = value
        violation[3] = limit


class ClearanceParts(NamedTuple):
    """The twin's capsules (core.clearance) and the tick's scratch for them, as one numba argument."""

    arrays: PartArrays
    pairs: np.ndarray  # the pairs that can come near the margin (`TwinClearance.near_pair_count`)
    platform_clearance: float  # pose-invariant (both platforms move with the stance frame)
    positions: np.ndarray  # (2, 3) scratch: this tick's platform positions, base frames
    rotations: np.ndarray  # (2, 3, 3)
    joints_world: np.ndarray  # (2, 6, 3)
    sliders: np.ndarray  # (2, 6)
    segments: np.ndarray  # (P, 2, 3)
    boxes: np.ndarray  # (P, 6)

    @classmethod
    def build(cls, model: TwinClearance) -> ClearanceParts:
        count = len(model.table.names)
        return cls(
            model.arrays,
            model.table.pairs[: model.near_pair_count],  # the tick checks a breach of at most the margin + 0.1 m
            model.platform_clearance_m,
            np.zeros((2, 3)),
            np.zeros((2, 3, 3)),
            np.zeros((2, 6, 3)),
            np.zeros((2, 6)),
            np.zeros((count, 2, 3)),
            np.zeros((count, 6)),
        )


@numba.njit(cache=True)
def _check_clearance(parts: ClearanceParts, clearance_min: float, violation: np.ndarray) -> None:
    """COLLISION (code 10, axis = the pair's index in `pairs`, or −2 for the platforms) when two parts come
    closer than `clearance_min`."""
    twin_segments_into(
        parts.arrays, parts.positions, parts.rotations, parts.joints_world, parts.sliders, parts.segments
    )
    # Only a breach matters here: exact below the margin, skipping every pair that cannot be that close.
    clearance, pair = min_clearance_kernel(parts.segments, parts.arrays.radius, parts.pairs, parts.boxes, clearance_min)
    if parts.platform_clearance < clearance:
        clearance, pair = parts.platform_clearance, -2
    if clearance < clearance_min:
        _set_violation(violation, COLLISION, pair, clearance, clearance_min)


@numba.njit(cache=True)
def twin_command_kernel(
    stance_pose: np.ndarray,  # (6,)
    period_s: float,
    previous_sliders: np.ndarray,  # (12,) last commanded
    previous_velocity: np.ndarray,  # (12,)
    stance_origin: np.ndarray,  # (3,)
    base_yaw: np.ndarray,  # (2, 3, 3)
    base_origin: np.ndarray,  # (2, 3)
    lever_world: np.ndarray,  # (2, 3)
    neutral_rotation_world: np.ndarray,  # (2, 3, 3)
    geometries: tuple[LegGeometry, LegGeometry],  # right, left
    stroke_min: np.ndarray,  # (12,)
    stroke_max: np.ndarray,  # (12,)
    limits: np.ndarray,  # (7,) base cone, platform cone, tilt, velocity, acceleration, (unused), clearance
    scratch: np.ndarray,  # (4, 3, 3)
    parts: ClearanceParts,
    sliders_out: np.ndarray,  # (12,)
    velocity_out: np.ndarray,  # (12,)
    acceleration_out: np.ndarray,  # (12,)
    violation: np.ndarray,  # (4,)
) -> None:
    violation[:] = 0.0
    every_rod_reaches = True
    stance_rotation = scratch[0]
    world_rotation = scratch[1]
    platform_rotation = scratch[2]
    rotation_into(stance_pose[3], stance_pose[4], stance_pose[5], stance_rotation)
    tilt = math.acos(min(1.0, max(-1.0, math.cos(stance_pose[3]) * math.cos(stance_pose[4]))))
    if tilt > limits[2]:
        _set_violation(violation, TILT, -1, tilt, limits[2])
    for side in range(2):
        # Platform rotation and position in this robot's base frame (core.kinematics.twin_platform_poses).
        for i in range(3):
            for j in range(3):
                total = 0.0
                for k in range(3):
                    total += stance_rotation[i, k] * neutral_rotation_world[side, k, j]
                world_rotation[i, j] = total
        for i in range(3):
            for j in range(3):
                total = 0.0
                for k in range(3):
                    total += base_yaw[side, k, i] * world_rotation[k, j]
                platform_rotation[i, j] = total
        # world = o_s + t + R_s·lever − o_b, then p = Yᵀ·world (scalars: no allocation in the tick)
        world_x = stance_origin[0] + stance_pose[0] - base_origin[side, 0]
        world_y = stance_origin[1] + stance_pose[1] - base_origin[side, 1]
        world_z = stance_origin[2] + stance_pose[2] - base_origin[side, 2]
        for k in range(3):
            world_x += stance_rotation[0, k] * lever_world[side, k]
            world_y += stance_rotation[1, k] * lever_world[side, k]
            world_z += stance_rotation[2, k] * lever_world[side, k]
        px = base_yaw[side, 0, 0] * world_x + base_yaw[side, 1, 0] * world_y + base_yaw[side, 2, 0] * world_z
        py = base_yaw[side, 0, 1] * world_x + base_yaw[side, 1, 1] * world_y + base_yaw[side, 2, 1] * world_z
        pz = base_yaw[side, 0, 2] * world_x + base_yaw[side, 1, 2] * world_y + base_yaw[side, 2, 2] * world_z
        parts.positions[side, 0], parts.positions[side, 1], parts.positions[side, 2] = px, py, pz
        parts.rotations[side, :, :] = platform_rotation
        geometry = geometries[side]
        rod_length = geometry.rod_length
        for leg in range(6):
            axis = 6 * side + leg
            lx, ly, lz, dx, dy, dz, slider, reach_sq = leg_solution(geometry, leg, px, py, pz, platform_rotation)
            if reach_sq < 0.0:
                _set_violation(violation, ROD_REACH, axis, math.sqrt(dy * dy + dz * dz), rod_length)
                sliders_out[axis] = previous_sliders[axis]
                every_rod_reaches = False
                continue
            sliders_out[axis] = slider
            parts.sliders[side, leg] = slider
            parts.joints_world[side, leg, 0] = px + lx
            parts.joints_world[side, leg, 1] = py + ly
            parts.joints_world[side, leg, 2] = pz + lz
            if slider < stroke_min[axis]:
                _set_violation(violation, STROKE, axis, slider, stroke_min[axis])
            elif slider > stroke_max[axis]:
                _set_violation(violation, STROKE, axis, slider, stroke_max[axis])
            # Rod direction d/L against the neutral axis, at the slider (base frame) and at the platform
            # (axis carried along by the platform rotation).
            rx, ry, rz = dx / rod_length, dy / rod_length, dz / rod_length
            axes = geometry.cone_axes
            ax, ay, az = axes[leg, 0], axes[leg, 1], axes[leg, 2]
            base_cone = math.acos(min(1.0, max(-1.0, rx * ax + ry * ay + rz * az)))
            if base_cone > limits[0]:
                _set_violation(violation, BASE_JOINT_CONE, axis, base_cone, limits[0])
            qx = platform_rotation[0, 0] * ax + platform_rotation[0, 1] * ay + platform_rotation[0, 2] * az
            qy = platform_rotation[1, 0] * ax + platform_rotation[1, 1] * ay + platform_rotation[1, 2] * az
            qz = platform_rotation[2, 0] * ax + platform_rotation[2, 1] * ay + platform_rotation[2, 2] * az
            platform_cone = math.acos(min(1.0, max(-1.0, rx * qx + ry * qy + rz * qz)))
            if platform_cone > limits[1]:
                _set_violation(violation, PLATFORM_JOINT_CONE, axis, platform_cone, limits[1])
    if every_rod_reaches:
        _check_clearance(parts, limits[6], violation)
    for axis in range(12):
        velocity = (sliders_out[axis] - previous_sliders[axis]) / period_s
        acceleration = (velocity - previous_velocity[axis]) / period_s
        velocity_out[axis] = velocity
        acceleration_out[axis] = acceleration
        if abs(velocity) > limits[3]:
            _set_violation(violation, SLIDER_VELOCITY, axis, velocity, limits[3])
        if abs(acceleration) > limits[4]:
            _set_violation(violation, SLIDER_ACCELERATION, axis, acceleration, limits[4])


@numba.njit(cache=True)
def stance_from_platform_kernel(
    platform_pose: np.ndarray,  # (6,) right robot, its base frame
    stance_origin: np.ndarray,
    base_yaw: np.ndarray,  # (3, 3)
    base_origin: np.ndarray,  # (3,)
    lever_world: np.ndarray,  # (3,)
    neutral_rotation_world: np.ndarray,  # (3, 3)
    scratch: np.ndarray,  # (2, 3, 3)
    stance_out: np.ndarray,  # (6,)
) -> None:
    """Invert the stance → platform map: R_s = Y·R_p·N_wᵀ, t = Y·p + o_b − o_s − R_s·lever."""
    platform_rotation = scratch[0]
    stance_rotation = scratch[1]
    rotation_into(platform_pose[3], platform_pose[4], platform_pose[5], platform_rotation)
    for i in range(3):
        for j in range(3):
            total = 0.0
            for k in range(3):
                for m in range(3):
                    total += base_yaw[i, k] * platform_rotation[k, m] * neutral_rotation_world[j, m]
            stance_rotation[i, j] = total
    for i in range(3):
        total = base_origin[i] - stance_origin[i]
        for k in range(3):
            total += base_yaw[i, k] * platform_pose[k] - stance_rotation[i, k] * lever_world[k]
        stance_out[i] = total
    stance_out[3] = math.atan2(-stance_rotation[1, 2], stance_rotation[2, 2])
    stance_out[4] = math.asin(min(1.0, max(-1.0, stance_rotation[0, 2])))
    stance_out[5] = math.atan2(-stance_rotation[0, 1], stance_rotation[0, 0])


@numba.njit(cache=True)
def measured_stance_kernel(
    sliders: np.ndarray,  # (6,) right robot
    warm_pose: np.ndarray,  # (6,) last platform pose: Newton's start, updated on success
    geometry: LegGeometry,
    tolerance: float,
    max_iterations: int,
    platform_out: np.ndarray,  # (6,)
    stance_origin: np.ndarray,
    base_yaw: np.ndarray,
    base_origin: np.ndarray,
    lever_world: np.ndarray,
    neutral_rotation_world: np.ndarray,
    scratch: np.ndarray,
    stance_out: np.ndarray,
) -> tuple[int, float]:
    """Newton FK of the right robot (core.kinematics) warm-started from the last pose, then its stance pose."""
    iterations, residual = _fk_newton(sliders, warm_pose, geometry, tolerance, max_iterations, platform_out)
    if iterations < 0 or not np.isfinite(residual):
        return iterations, residual
    warm_pose[:] = platform_out
    stance_from_platform_kernel(
        platform_out, stance_origin, base_yaw, base_origin, lever_world, neutral_rotation_world, scratch, stance_out
    )
    return iterations, residual


class TwinKernels:
    """The twin's geometry packed for the compiled kernels, plus their preallocated outputs."""

    def __init__(self, twin: TwinRobot, period_s: float) -> None:
        self.twin, self.period_s = twin, period_s
        robots = [twin.robot_for(side) for side in twin.sides]
        self.stance_origin = stance_origin_world(twin)
        self.base_yaw = np.stack([yaw_matrix(twin.placement(side).base_yaw_rad) for side in twin.sides])
        self.base_origin = np.array([twin.placement(side).base_origin_m for side in twin.sides], dtype=float)
        neutral = np.array([robot.neutral_pose for robot in robots], dtype=float)
        self.neutral_rotation_world = np.einsum("sij,sjk->sik", self.base_yaw, rotation_matrices(neutral[:, 3:]))
        self.lever_world = (
            self.base_origin + np.einsum("sij,sj->si", self.base_yaw, neutral[:, :3]) - self.stance_origin
        )
        self.geometries = (leg_geometry(robots[0]), leg_geometry(robots[1]))
        self.clearance = twin_clearance(twin)
        self._parts = ClearanceParts.build(self.clearance)
        self._scratch = np.zeros((4, 3, 3))
        self._right = robots[0]
        self._fk_warm_pose = np.asarray(robots[0].neutral_pose, dtype=float).copy()
        self._fk_pose = np.zeros(6)

    def command(
        self,
        stance_pose: np.ndarray,
        previous_sliders: np.ndarray,
        previous_velocity: np.ndarray,
        stroke_min: np.ndarray,
        stroke_max: np.ndarray,
        limits: np.ndarray,
        sliders_out: np.ndarray,
        velocity_out: np.ndarray,
        acceleration_out: np.ndarray,
        violation: np.ndarray,
        elapsed_s: float | None = None,
    ) -> None:
        """Slider set-points (12) for a stance pose, their finite-difference velocity and acceleration over
        `elapsed_s` since the previous set-point (one period unless a late tick skipped ahead), and the first
        broken limit in `violation` (code, axis, value, limit; code 0 when none)."""
        twin_command_kernel(
            stance_pose,
            self.period_s if elapsed_s is None else elapsed_s,
            previous_sliders,
            previous_velocity,
            self.stance_origin,
            self.base_yaw,
            self.base_origin,
            self.lever_world,
            self.neutral_rotation_world,
            self.geometries,
            stroke_min,
            stroke_max,
            limits,
            self._scratch,
            self._parts,
            sliders_out,
            velocity_out,
            acceleration_out,
            violation,
        )

    def collision_pair_name(self, axis: int) -> str:
        """The two parts a COLLISION violation's axis names."""
        return self.clearance.platform_pair_name if axis == -2 else self.clearance.table.pair_names[axis]

    def measured_stance_pose(self, right_sliders_m: np.ndarray, stance_out: np.ndarray) -> int:
        """Stance pose from the right robot's measured sliders (Newton FK warm-started from the last
        call); returns the iterations, raises `ForwardKinematicsError` when Newton fails."""
        iterations, residual = measured_stance_kernel(
            right_sliders_m,
            self._fk_warm_pose,
            self.geometries[0],
            1e-12,
            20,
            self._fk_pose,
            self.stance_origin,
            self.base_yaw[0],
            self.base_origin[0],
            self.lever_world[0],
            self.neutral_rotation_world[0],
            self._scratch[:2],
            stance_out,
        )
        if iterations < 0 or not np.isfinite(residual):
            self._fk_warm_pose[:] = self._right.neutral_pose
            raise ForwardKinematicsError(abs(iterations), residual)
        return iterations

    def sliders_for(self, stance_pose: np.ndarray, sliders_out: np.ndarray) -> np.ndarray:
        """The twelve slider positions of a stance pose, without limit checks (for start-up states)."""
        scratch_velocity, scratch_acceleration = np.zeros(12), np.zeros(12)
        violation = np.zeros(VIOLATION_FIELDS)
        self.command(
            stance_pose,
            sliders_out,
            scratch_velocity,
            np.full(12, -np.inf),
            np.full(12, np.inf),
            UNCHECKED_LIMITS,
            sliders_out,
            scratch_velocity,
            scratch_acceleration,
            violation,
        )
        return sliders_out

    def neutral_sliders(self) -> np.ndarray:
        """The twelve slider positions at the neutral stance."""
        return self.sliders_for(np.zeros(6), np.zeros(12))
