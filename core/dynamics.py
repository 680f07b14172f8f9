"""Inverse dynamics of one 6-SSP robot and of the twin (paper §3.2, whose Lagrange derivation is not printed).

Method: the principle of virtual work (d'Alembert), exact for rigid bodies and friction neglected as in §3.2.
With slider velocities ẋ = J·t (t = platform twist (v, ω), `core.kinematics.twist_jacobian`):

    F = m_s·ẍ + F_rod,slider + J⁻ᵀ·W

- sliders (mass m_s) move along their rails only: gravity is normal to the rails and does no work;
- a uniform slender rod (mass m_r, zero axial inertia) is affine in its end points A (slider joint) and
  P (platform joint), so its inertia is exactly the "consistent mass" pair m_r·[1/3 1/6; 1/6 1/3]:
  it adds m_r·(a_A/3 + a_P/6 − g/2)·e_x to its slider and the force m_r·(a_A/6 + a_P/3 − g/2) at P;
- the top body (platform + payload, one rigid body) needs the wrench (m·(a_c − g), I·α + ω × I·ω + r_c × f);
- W is the top wrench plus every rod force at P, about the platform origin in the base frame.

Slider accelerations come from differentiating the closed-form IK twice (no Jacobian derivative needed).
Everything runs in numba: one kernel per sample, looped over samples for a batch and called once per tick,
with preallocated scratch, so the per-tick path allocates nothing.

The payload is the patient: mass, centre of mass and inertia from body mass and height (`PayloadModel`).
On the twin the patient stands at the stance origin and each robot carries half of the patient's inertial
wrench (an equal split; the real split is the patient's choice of weight bearing).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numba
import numpy as np

from core.kinematics import (
    IK_CHUNK_POSES,
    _as_poses,
    euler_from_rotation,
    for_each_chunk,
    leg_kernel,
    rotation_matrices,
    stance_origin_world,
    yaw_matrix,
)
from core.physics import GRAVITY_M_S2
from core.robot import DescriptionError, SSPRobot, TwinRobot
from core.rotations import rotation_into

# Anthropometry for a standing adult, as fractions of body height. Centre of mass at 0.55·H above the soles
# (Winter, "Biomechanics and Motor Control of Human Movement", 4th ed., segment tables); whole-body radii of
# gyration about the COM: 0.24·H about horizontal axes and 0.075·H about the vertical axis (sums of the
# segment inertias in the standing posture). These are approximations stated as assumptions.
COM_HEIGHT_FRACTION = 0.55
HORIZONTAL_GYRATION_FRACTION = 0.24
VERTICAL_GYRATION_FRACTION = 0.075
BODY_MASS_RANGE_KG = (10.0, 250.0)  # the top is the paper's rated load (§3.3.1)
BODY_HEIGHT_RANGE_M = (0.8, 2.3)
SCRATCH_SIZE = 128  # floats of per-sample work space for `_robot_forces`


@dataclass(frozen=True)
class PayloadModel:
    """A rigid payload standing on its support point (the platform centre for one robot, the stance origin
    for the twin): mass, centre of mass above the support (support frame), principal inertia about the COM."""

    mass_kg: float = 0.0
    com_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    inertia_kg_m2: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        for name in ("mass_kg", "com_m", "inertia_kg_m2"):
            values = np.atleast_1d(np.asarray(getattr(self, name), dtype=float))
            if not np.all(np.isfinite(values)):
                raise DescriptionError(f"payload.{name}", getattr(self, name), "must be finite")
        if self.mass_kg < 0.0 or min(self.inertia_kg_m2) < 0.0:
            raise DescriptionError("payload", asdict(self), "mass and inertia must be >= 0")

    @classmethod
    def from_body(cls, mass_kg: float, height_m: float) -> PayloadModel:
        """A standing patient of `mass_kg` and `height_m` (anthropometric fractions above)."""
        low_mass, high_mass = BODY_MASS_RANGE_KG
        if not (math.isfinite(mass_kg) and low_mass <= mass_kg <= high_mass):
            raise DescriptionError("body_mass_kg", mass_kg, f"must be in [{low_mass}, {high_mass}] kg")
        low_height, high_height = BODY_HEIGHT_RANGE_M
        if not (math.isfinite(height_m) and low_height <= height_m <= high_height):
            raise DescriptionError("height_m", height_m, f"must be in [{low_height}, {high_height}] m")
        horizontal = mass_kg * (HORIZONTAL_GYRATION_FRACTION * height_m) ** 2
        vertical = mass_kg * (VERTICAL_GYRATION_FRACTION * height_m) ** 2
        return cls(mass_kg, (0.0, 0.0, COM_HEIGHT_FRACTION * height_m), (horizontal, horizontal, vertical))

    def scaled(self, fraction: float) -> PayloadModel:
        """The same body with mass and inertia scaled (the share one robot of the twin carries)."""
        return PayloadModel(self.mass_kg * fraction, self.com_m, tuple(fraction * i for i in self.inertia_kg_m2))  # type: ignore[arg-type]

    def to_dict(self) -> dict[str, Any]:
        return {"mass_kg": self.mass_kg, "com_m": list(self.com_m), "inertia_kg_m2": list(self.inertia_kg_m2)}


@dataclass(frozen=True)
class RigidBody:
    """Mass, centre of mass and inertia (3, 3) about the COM, all in one body-fixed frame."""

    mass_kg: float
    com_m: np.ndarray
    inertia_kg_m2: np.ndarray

    def combined(self, other: RigidBody) -> RigidBody:
        """Two bodies welded together, by the parallel-axis theorem."""
        mass = self.mass_kg + other.mass_kg
        if mass == 0.0:
            return self
        com = (self.mass_kg * self.com_m + other.mass_kg * other.com_m) / mass
        inertia = np.zeros((3, 3))
        for body in (self, other):
            offset = body.com_m - com
            inertia += body.inertia_kg_m2 + body.mass_kg * (offset @ offset * np.eye(3) - np.outer(offset, offset))
        return RigidBody(mass, com, inertia)


def platform_body(robot: SSPRobot) -> RigidBody:
    mass = robot.mass
    return RigidBody(mass.platform_mass_kg, np.asarray(mass.platform_com_m), np.diag(mass.platform_inertia_kg_m2))


def payload_body(payload: PayloadModel, support_m: np.ndarray, rotation: np.ndarray) -> RigidBody:
    """The payload in a platform frame, standing on `support_m` with its axes rotated by `rotation`."""
    return RigidBody(
        payload.mass_kg,
        np.asarray(support_m) + rotation @ np.asarray(payload.com_m),
        rotation @ np.diag(payload.inertia_kg_m2) @ rotation.T,
    )


def _check_rated_load(robot: SSPRobot, payload_mass_kg: float) -> None:
    if payload_mass_kg > robot.mass.rated_payload_kg:
        raise DescriptionError(
            "payload.mass_kg", payload_mass_kg, f"exceeds the rated load {robot.mass.rated_payload_kg} kg per robot"
        )


# --- numba kernels: one sample each ---------------------------------------------------------------------


@numba.njit(cache=True)
def _euler_motion(
    pose: np.ndarray,
    pose_rate: np.ndarray,
    pose_acceleration: np.ndarray,
    rotation: np.ndarray,
    omega: np.ndarray,
    alpha: np.ndarray,
) -> None:
    """R = Rx·Ry·Rz, ω = E·η̇ and α = E·η̈ + Ė·η̇ (base frame) for Euler angles η = (roll, pitch, yaw)."""
    rotation_into(pose[3], pose[4], pose[5], rotation)
    ca, sa = np.cos(pose[3]), np.sin(pose[3])
    cb, sb = np.cos(pose[4]), np.sin(pose[4])
    droll, dpitch, dyaw = pose_rate[3], pose_rate[4], pose_rate[5]
    ddroll, ddpitch, ddyaw = pose_acceleration[3], pose_acceleration[4], pose_acceleration[5]
    omega[0] = droll + sb * dyaw
    omega[1] = ca * dpitch - sa * cb * dyaw
    omega[2] = sa * dpitch + ca * cb * dyaw
    alpha[0] = ddroll + sb * ddyaw + cb * dpitch * dyaw
    alpha[1] = ca * ddpitch - sa * cb * ddyaw - sa * droll * dpitch + (-ca * cb * droll + sa * sb * dpitch) * dyaw
    alpha[2] = sa * ddpitch + ca * cb * ddyaw + ca * droll * dpitch + (-sa * cb * droll - ca * sb * dpitch) * dyaw


@numba.njit(cache=True)
def _cross(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    x = a[1] * b[2] - a[2] * b[1]
    y = a[2] * b[0] - a[0] * b[2]
    z = a[0] * b[1] - a[1] * b[0]
    out[0], out[1], out[2] = x, y, z


@numba.njit(cache=True)
def _leg_motion(
    position: np.ndarray,
    rotation: np.ndarray,
    velocity: np.ndarray,
    omega: np.ndarray,
    acceleration: np.ndarray,
    alpha: np.ndarray,
    geometry: np.ndarray,
    rail_z: float,
    rod_length: float,
    lever: np.ndarray,
    joint_velocity: np.ndarray,
    joint_acceleration: np.ndarray,
    slider: np.ndarray,
    vector: np.ndarray,
) -> bool:
    """Platform joints' lever r = R·B, velocity and acceleration (6, 3), and slider x, ẋ, ẍ (3, 6).

    Closed-form IK x = W_x + side·h, h = √(L² − Δy² − Δz²), differentiated twice. False if a rod cannot reach.
    `geometry` rows are (B_x, B_y, B_z, rail_y, side); `vector` is (3,) scratch."""
    for leg in range(6):
        lx, ly, lz, _, dy, dz, slider_x, reach_sq = leg_kernel(
            geometry[leg, 0],
            geometry[leg, 1],
            geometry[leg, 2],
            geometry[leg, 3],
            geometry[leg, 4],
            rail_z,
            rod_length,
            position[0],
            position[1],
            position[2],
            rotation,
        )
        lever[leg, 0], lever[leg, 1], lever[leg, 2] = lx, ly, lz
        _cross(omega, lever[leg], vector)
        for i in range(3):
            joint_velocity[leg, i] = velocity[i] + vector[i]
        _cross(omega, vector, joint_acceleration[leg])  # ω × (ω × r)
        _cross(alpha, lever[leg], vector)
        for i in range(3):
            joint_acceleration[leg, i] += acceleration[i] + vector[i]
        if reach_sq <= 0.0:
            return False
        along = np.sqrt(reach_sq)
        side = geometry[leg, 4]
        vy, vz = joint_velocity[leg, 1], joint_velocity[leg, 2]
        ay, az = joint_acceleration[leg, 1], joint_acceleration[leg, 2]
        along_rate = -(dy * vy + dz * vz) / along
        slider[0, leg] = slider_x
        slider[1, leg] = joint_velocity[leg, 0] + side * along_rate
        slider[2, leg] = joint_acceleration[leg, 0] - side * (
            (vy * vy + vz * vz + dy * ay + dz * az) / along + along_rate * along_rate / along
        )
    return True


@numba.njit(cache=True)
def _solve6_in_place(matrix: np.ndarray, rhs: np.ndarray) -> bool:
    """Gaussian elimination with partial pivoting; rhs becomes the solution. False when singular."""
    n = 6
    for col in range(n):
        pivot = col
        for row in range(col + 1, n):
            if abs(matrix[row, col]) > abs(matrix[pivot, col]):
                pivot = row
        if abs(matrix[pivot, col]) < 1e-12:
            return False
        if pivot != col:
            for k in range(n):
                matrix[col, k], matrix[pivot, k] = matrix[pivot, k], matrix[col, k]
            rhs[col], rhs[pivot] = rhs[pivot], rhs[col]
        for row in range(col + 1, n):
            factor = matrix[row, col] / matrix[col, col]
            for k in range(col, n):
                matrix[row, k] -= factor * matrix[col, k]
            rhs[row] -= factor * rhs[col]
    for row in range(n - 1, -1, -1):
        total = rhs[row]
        for k in range(row + 1, n):
            total -= matrix[row, k] * rhs[k]
        rhs[row] = total / matrix[row, row]
    return True


@numba.njit(cache=True)
def _robot_forces(
    position: np.ndarray,
    rotation: np.ndarray,
    velocity: np.ndarray,
    omega: np.ndarray,
    acceleration: np.ndarray,
    alpha: np.ndarray,
    geometry: np.ndarray,
    scalars: np.ndarray,
    top_com: np.ndarray,
    top_inertia: np.ndarray,
    gravity: np.ndarray,
    scratch: np.ndarray,
    out: np.ndarray,
) -> bool:
    """Slider forces (6,) along +x of each rail for one sample; False when unreachable or singular.

    `scalars` = (rail_z, rod_length, slider_mass, rod_mass, top_mass); `scratch` is (SCRATCH_SIZE,) preallocated."""
    rail_z, rod_length, slider_mass, rod_mass, top_mass = scalars[0], scalars[1], scalars[2], scalars[3], scalars[4]
    lever = scratch[0:18].reshape((6, 3))
    joint_velocity = scratch[18:36].reshape((6, 3))
    joint_acceleration = scratch[36:54].reshape((6, 3))
    vector = scratch[54:57]
    vector2 = scratch[57:60]
    vector3 = scratch[60:63]
    slider = scratch[63:81].reshape((3, 6))
    jacobian_t = scratch[81:117].reshape((6, 6))
    rhs = scratch[117:123]
    if not _leg_motion(
        position,
        rotation,
        velocity,
        omega,
        acceleration,
        alpha,
        geometry,
        rail_z,
        rod_length,
        lever,
        joint_velocity,
        joint_acceleration,
        slider,
        vector,
    ):
        return False
    # Top body: COM lever r_c = R·c, a_c = a + α×r_c + ω×(ω×r_c); f = m(a_c − g).
    rc0 = rotation[0, 0] * top_com[0] + rotation[0, 1] * top_com[1] + rotation[0, 2] * top_com[2]
    rc1 = rotation[1, 0] * top_com[0] + rotation[1, 1] * top_com[1] + rotation[1, 2] * top_com[2]
    rc2 = rotation[2, 0] * top_com[0] + rotation[2, 1] * top_com[1] + rotation[2, 2] * top_com[2]
    vector[0], vector[1], vector[2] = rc0, rc1, rc2
    _cross(omega, vector, vector2)
    _cross(omega, vector2, vector3)  # ω×(ω×r_c)
    _cross(alpha, vector, vector2)
    force_x = top_mass * (acceleration[0] + vector2[0] + vector3[0] - gravity[0])
    force_y = top_mass * (acceleration[1] + vector2[1] + vector3[1] - gravity[1])
    force_z = top_mass * (acceleration[2] + vector2[2] + vector3[2] - gravity[2])
    # Moment about the platform origin: R·I·Rᵀ·α + ω × (R·I·Rᵀ·ω) + r_c × f.
    moment_x = rc1 * force_z - rc2 * force_y
    moment_y = rc2 * force_x - rc0 * force_z
    moment_z = rc0 * force_y - rc1 * force_x
    for pass_index in range(2):
        source = alpha if pass_index == 0 else omega
        for i in range(3):  # vector = Rᵀ·source
            vector[i] = rotation[0, i] * source[0] + rotation[1, i] * source[1] + rotation[2, i] * source[2]
        for i in range(3):  # vector2 = I·vector
            vector2[i] = top_inertia[i, 0] * vector[0] + top_inertia[i, 1] * vector[1] + top_inertia[i, 2] * vector[2]
        for i in range(3):  # vector = R·vector2
            vector[i] = rotation[i, 0] * vector2[0] + rotation[i, 1] * vector2[1] + rotation[i, 2] * vector2[2]
        if pass_index == 1:
            _cross(omega, vector, vector2)
            vector[0], vector[1], vector[2] = vector2[0], vector2[1], vector2[2]
        moment_x += vector[0]
        moment_y += vector[1]
        moment_z += vector[2]
    for leg in range(6):
        # Slider and the rod's slider end act along the rail directly.
        slider_acceleration = slider[2, leg]
        out[leg] = slider_mass * slider_acceleration + rod_mass * (
            slider_acceleration / 3.0 + joint_acceleration[leg, 0] / 6.0 - 0.5 * gravity[0]
        )
        # The rod's platform end: force m_r(a_A/6 + a_P/3 − g/2) at P_i.
        fx = rod_mass * (slider_acceleration / 6.0 + joint_acceleration[leg, 0] / 3.0 - 0.5 * gravity[0])
        fy = rod_mass * (joint_acceleration[leg, 1] / 3.0 - 0.5 * gravity[1])
        fz = rod_mass * (joint_acceleration[leg, 2] / 3.0 - 0.5 * gravity[2])
        force_x += fx
        force_y += fy
        force_z += fz
        moment_x += lever[leg, 1] * fz - lever[leg, 2] * fy
        moment_y += lever[leg, 2] * fx - lever[leg, 0] * fz
        moment_z += lever[leg, 0] * fy - lever[leg, 1] * fx
        # Jᵀ column for this leg: row (d, r×d)/d_x with rod d = P − A.
        dx = -geometry[leg, 4] * np.sqrt(
            rod_length * rod_length
            - (position[1] + lever[leg, 1] - geometry[leg, 3]) ** 2
            - (position[2] + lever[leg, 2] - rail_z) ** 2
        )
        dy = position[1] + lever[leg, 1] - geometry[leg, 3]
        dz = position[2] + lever[leg, 2] - rail_z
        jacobian_t[0, leg] = 1.0
        jacobian_t[1, leg] = dy / dx
        jacobian_t[2, leg] = dz / dx
        jacobian_t[3, leg] = (lever[leg, 1] * dz - lever[leg, 2] * dy) / dx
        jacobian_t[4, leg] = (lever[leg, 2] * dx - lever[leg, 0] * dz) / dx
        jacobian_t[5, leg] = (lever[leg, 0] * dy - lever[leg, 1] * dx) / dx
    rhs[0], rhs[1], rhs[2], rhs[3], rhs[4], rhs[5] = force_x, force_y, force_z, moment_x, moment_y, moment_z
    if not _solve6_in_place(jacobian_t, rhs):
        return False
    for leg in range(6):
        out[leg] += rhs[leg]
    return True


@numba.njit(cache=True)
def _platform_from_stance(
    stance_pose: np.ndarray,
    stance_rate: np.ndarray,
    stance_acceleration: np.ndarray,
    stance_rotation: np.ndarray,
    stance_omega: np.ndarray,
    stance_alpha: np.ndarray,
    origin: np.ndarray,
    base_rotation: np.ndarray,
    base_origin: np.ndarray,
    lever_world: np.ndarray,
    neutral_rotation: np.ndarray,
    motion: np.ndarray,
) -> None:
    """One robot's platform motion in its base frame for a stance-frame motion (as `twin_platform_poses`).

    `motion` (24,) receives position(3), rotation(9), v(3), ω(3), a(3), α(3); all vectors base frame."""
    lever = motion[12:15]  # borrowed as scratch for S·ℓ until v is written
    for i in range(3):
        lever[i] = stance_rotation[i, 0] * lever_world[0] + stance_rotation[i, 1] * lever_world[1]
        lever[i] += stance_rotation[i, 2] * lever_world[2]
    lx, ly, lz = lever[0], lever[1], lever[2]
    wx, wy, wz = stance_omega[0], stance_omega[1], stance_omega[2]
    ax, ay, az = stance_alpha[0], stance_alpha[1], stance_alpha[2]
    vwx, vwy, vwz = wy * lz - wz * ly, wz * lx - wx * lz, wx * ly - wy * lx  # ω × ℓ
    world_velocity = (stance_rate[0] + vwx, stance_rate[1] + vwy, stance_rate[2] + vwz)
    world_acceleration = (
        stance_acceleration[0] + ay * lz - az * ly + wy * vwz - wz * vwy,
        stance_acceleration[1] + az * lx - ax * lz + wz * vwx - wx * vwz,
        stance_acceleration[2] + ax * ly - ay * lx + wx * vwy - wy * vwx,
    )
    world_position = (
        origin[0] + stance_pose[0] + lx - base_origin[0],
        origin[1] + stance_pose[1] + ly - base_origin[1],
        origin[2] + stance_pose[2] + lz - base_origin[2],
    )
    for i in range(3):  # base frame = Yᵀ · world
        motion[i] = base_rotation[0, i] * world_position[0] + base_rotation[1, i] * world_position[1]
        motion[i] += base_rotation[2, i] * world_position[2]
        motion[12 + i] = base_rotation[0, i] * world_velocity[0] + base_rotation[1, i] * world_velocity[1]
        motion[12 + i] += base_rotation[2, i] * world_velocity[2]
        motion[15 + i] = base_rotation[0, i] * wx + base_rotation[1, i] * wy + base_rotation[2, i] * wz
        motion[18 + i] = base_rotation[0, i] * world_acceleration[0] + base_rotation[1, i] * world_acceleration[1]
        motion[18 + i] += base_rotation[2, i] * world_acceleration[2]
        motion[21 + i] = base_rotation[0, i] * ax + base_rotation[1, i] * ay + base_rotation[2, i] * az
    for i in range(3):  # R = Yᵀ · S · N
        for j in range(3):
            total = 0.0
            for k in range(3):
                s_n = (
                    stance_rotation[k, 0] * neutral_rotation[0, j]
                    + stance_rotation[k, 1] * neutral_rotation[1, j]
                    + stance_rotation[k, 2] * neutral_rotation[2, j]
                )
                total += base_rotation[k, i] * s_n
            motion[3 + 3 * i + j] = total


@numba.njit(cache=True)
def _robot_forces_from_motion(
    motion: np.ndarray,
    geometry: np.ndarray,
    scalars: np.ndarray,
    top_com: np.ndarray,
    top_inertia: np.ndarray,
    gravity: np.ndarray,
    scratch: np.ndarray,
    out: np.ndarray,
) -> bool:
    return _robot_forces(
        motion[0:3],
        motion[3:12].reshape((3, 3)),
        motion[12:15],
        motion[15:18],
        motion[18:21],
        motion[21:24],
        geometry,
        scalars,
        top_com,
        top_inertia,
        gravity,
        scratch,
        out,
    )


@numba.njit(cache=True)
def _euler_to_motion(pose: np.ndarray, rate: np.ndarray, acceleration: np.ndarray, motion: np.ndarray) -> None:
    """Pose and Euler-rate derivatives → `motion` (24,) as in `_platform_from_stance`."""
    _euler_motion(pose, rate, acceleration, motion[3:12].reshape((3, 3)), motion[15:18], motion[21:24])
    for i in range(3):
        motion[i] = pose[i]
        motion[12 + i] = rate[i]
        motion[18 + i] = acceleration[i]


@numba.njit(cache=True)
def _robot_forces_batch(
    poses: np.ndarray,
    rates: np.ndarray,
    accelerations: np.ndarray,
    geometry: np.ndarray,
    scalars: np.ndarray,
    top_com: np.ndarray,
    top_inertia: np.ndarray,
    gravity: np.ndarray,
    motion: np.ndarray,
    scratch: np.ndarray,
    out: np.ndarray,
) -> int:
    """Forces (N, 6) for N samples; returns the first failing sample index, or −1."""
    for n in range(poses.shape[0]):
        _euler_to_motion(poses[n], rates[n], accelerations[n], motion)
        if not _robot_forces_from_motion(motion, geometry, scalars, top_com, top_inertia, gravity, scratch, out[n]):
            return n
    return -1


@numba.njit(cache=True, nogil=True)
def _twin_batch(
    stance_poses: np.ndarray,
    stance_rates: np.ndarray,
    stance_accelerations: np.ndarray,
    origin: np.ndarray,
    base_rotations: np.ndarray,
    base_origins: np.ndarray,
    levers_world: np.ndarray,
    neutral_rotations: np.ndarray,
    geometry: np.ndarray,
    scalars: np.ndarray,
    top_com: np.ndarray,
    top_inertia: np.ndarray,
    gravity: np.ndarray,
    stance_motion: np.ndarray,
    scratch: np.ndarray,
    motions_out: np.ndarray,
    forces_out: np.ndarray,
    with_forces: bool,
) -> int:
    """Both robots' platform motions (N, 2, 24) and, with `with_forces`, forces (N, 12); first failure or −1."""
    for n in range(stance_poses.shape[0]):
        _euler_to_motion(stance_poses[n], stance_rates[n], stance_accelerations[n], stance_motion)
        for robot in range(2):
            _platform_from_stance(
                stance_poses[n],
                stance_rates[n],
                stance_accelerations[n],
                stance_motion[3:12].reshape((3, 3)),
                stance_motion[15:18],
                stance_motion[21:24],
                origin,
                base_rotations[robot],
                base_origins[robot],
                levers_world[robot],
                neutral_rotations[robot],
                motions_out[n, robot],
            )
            if with_forces and not _robot_forces_from_motion(
                motions_out[n, robot],
                geometry[robot],
                scalars[robot],
                top_com[robot],
                top_inertia[robot],
                gravity,
                scratch,
                forces_out[n, 6 * robot : 6 * robot + 6],
            ):
                return n
    return -1


@numba.njit(cache=True)
def _legs_batch(
    motions: np.ndarray, geometry: np.ndarray, scalars: np.ndarray, scratch: np.ndarray, legs_out: np.ndarray
) -> int:
    """Leg kinematics (N, 6, 12) per sample: joint position, velocity, acceleration (9) and slider x, ẋ, ẍ."""
    for n in range(motions.shape[0]):
        motion = motions[n]
        lever = scratch[0:18].reshape((6, 3))
        joint_velocity = scratch[18:36].reshape((6, 3))
        joint_acceleration = scratch[36:54].reshape((6, 3))
        slider = scratch[63:81].reshape((3, 6))
        if not _leg_motion(
            motion[0:3],
            motion[3:12].reshape((3, 3)),
            motion[12:15],
            motion[15:18],
            motion[18:21],
            motion[21:24],
            geometry,
            scalars[0],
            scalars[1],
            lever,
            joint_velocity,
            joint_acceleration,
            slider,
            scratch[54:57],
        ):
            return n
        for leg in range(6):
            for i in range(3):
                legs_out[n, leg, i] = motion[i] + lever[leg, i]
                legs_out[n, leg, 3 + i] = joint_velocity[leg, i]
                legs_out[n, leg, 6 + i] = joint_acceleration[leg, i]
                legs_out[n, leg, 9 + i] = slider[i, leg]
    return -1


# --- Public API ------------------------------------------------------------------------------------------


class DynamicsError(ValueError):
    """A trajectory sample the dynamics cannot evaluate (unreachable pose or singular Jacobian)."""

    def __init__(self, sample: int, reason: str) -> None:
        self.sample = sample
        super().__init__(f"sample {sample}: {reason}")


def _as_trajectory(poses: np.ndarray, velocities: np.ndarray, accelerations: np.ndarray) -> tuple[np.ndarray, ...]:
    poses = _as_poses(poses)
    result = [poses]
    for name, values in (("velocities", velocities), ("accelerations", accelerations)):
        array = np.ascontiguousarray(np.atleast_2d(np.asarray(values, dtype=float)))
        if array.shape != poses.shape:
            raise ValueError(f"{name}: shape {array.shape}, expected {poses.shape} like the poses")
        if not np.all(np.isfinite(array)):
            raise ValueError(f"{name}: must be finite (no NaN/inf)")
        result.append(array)
    return tuple(np.ascontiguousarray(a) for a in result)


@dataclass(frozen=True)
class RobotDynamicsArrays:
    """The numbers the kernels need for one robot, in its base and platform frames."""

    geometry: np.ndarray  # (6, 5): B_x, B_y, B_z, rail_y, side
    scalars: np.ndarray  # (5,): rail_z, rod_length, slider_mass, rod_mass, top_mass
    top: RigidBody  # platform + payload share, platform frame

    @classmethod
    def build(cls, robot: SSPRobot, payload: RigidBody, *, include_rods: bool) -> RobotDynamicsArrays:
        geometry = np.column_stack([robot.platform_joints_m, robot.rail_y_m, robot.sides])
        top = platform_body(robot).combined(payload)
        rod_mass = robot.mass.rod_mass_kg if include_rods else 0.0
        scalars = np.array([robot.rail_z_m, robot.rod_length_m, robot.mass.slider_mass_kg, rod_mass, top.mass_kg])
        return cls(np.ascontiguousarray(geometry), scalars, top)


class _TickBuffers:
    """Preallocated (1, 6) inputs and (1, k) output for the per-tick path, with flat views made once."""

    def __init__(self, force_count: int) -> None:
        self.poses, self.rates, self.accelerations = np.zeros((1, 6)), np.zeros((1, 6)), np.zeros((1, 6))
        self._flat = (self.poses[0], self.rates[0], self.accelerations[0])
        self.forces = np.zeros((1, force_count))
        self.forces_flat = self.forces[0]

    def load(self, pose: np.ndarray, rate: np.ndarray, acceleration: np.ndarray) -> _TickBuffers:
        np.copyto(self._flat[0], pose)
        np.copyto(self._flat[1], rate)
        np.copyto(self._flat[2], acceleration)
        return self


GRAVITY_VECTOR = np.array([0.0, 0.0, -GRAVITY_M_S2])  # world and every base frame (bases only yaw about Z)


class InverseDynamics:
    """Slider drive forces (N along +x of each rail) of one robot carrying `payload` on its platform centre.

    `slider_forces` takes a trajectory of poses, pose rates and pose accelerations (Euler-angle rates), each
    (N, 6); `step` does one sample into a preallocated buffer (returns a view of it)."""

    def __init__(self, robot: SSPRobot, payload: PayloadModel | None = None, *, include_rods: bool = True) -> None:
        payload = payload or PayloadModel()
        _check_rated_load(robot, payload.mass_kg)
        self.robot = robot
        self.payload = payload
        self.include_rods = include_rods
        self.arrays = RobotDynamicsArrays.build(
            robot, payload_body(payload, np.zeros(3), np.eye(3)), include_rods=include_rods
        )
        self._top_com = np.ascontiguousarray(self.arrays.top.com_m)
        self._top_inertia = np.ascontiguousarray(self.arrays.top.inertia_kg_m2)
        self._motion = np.zeros(24)
        self._scratch = np.zeros(SCRATCH_SIZE)
        self._tick = _TickBuffers(6)
        self.step(np.asarray(robot.neutral_pose, dtype=float), np.zeros(6), np.zeros(6))  # compile and check

    def slider_forces(self, poses: np.ndarray, velocities: np.ndarray, accelerations: np.ndarray) -> np.ndarray:
        poses, velocities, accelerations = _as_trajectory(poses, velocities, accelerations)
        out = np.empty((poses.shape[0], 6))
        self._run(poses, velocities, accelerations, out)
        return out

    def step(self, pose: np.ndarray, velocity: np.ndarray, acceleration: np.ndarray) -> np.ndarray:
        """One sample, allocation-free: (6,) arrays in, the internal (6,) force buffer out."""
        tick = self._tick.load(pose, velocity, acceleration)
        self._run(tick.poses, tick.rates, tick.accelerations, tick.forces)
        return tick.forces_flat

    def _run(self, poses: np.ndarray, rates: np.ndarray, accelerations: np.ndarray, out: np.ndarray) -> None:
        failed = _robot_forces_batch(
            poses,
            rates,
            accelerations,
            self.arrays.geometry,
            self.arrays.scalars,
            self._top_com,
            self._top_inertia,
            GRAVITY_VECTOR,
            self._motion,
            self._scratch,
            out,
        )
        if failed >= 0:
            raise DynamicsError(failed, f"pose {poses[failed].tolist()} is unreachable or singular")


@dataclass(frozen=True)
class PlatformMotion:
    """One robot's platform motion in its base frame; each (N, 3) except rotations (N, 3, 3)."""

    positions_m: np.ndarray
    rotations: np.ndarray
    velocities_m_s: np.ndarray
    angular_velocities_rad_s: np.ndarray
    accelerations_m_s2: np.ndarray
    angular_accelerations_rad_s2: np.ndarray

    @property
    def poses(self) -> np.ndarray:
        return np.concatenate([self.positions_m, euler_from_rotation(self.rotations)], axis=1)


@dataclass(frozen=True)
class LegMotion:
    """Each leg's platform joint P and slider, base frame: joints (N, 6, 3) and sliders (N, 6)."""

    joint_positions_m: np.ndarray
    joint_velocities_m_s: np.ndarray
    joint_accelerations_m_s2: np.ndarray
    slider_positions_m: np.ndarray
    slider_velocities_m_s: np.ndarray
    slider_accelerations_m_s2: np.ndarray


class TwinInverseDynamics:
    """Slider drive forces (N, 12: right 1–6, left 1–6) of the twin for a stance-frame trajectory.

    The patient (`payload`) moves rigidly with the stance frame, half of the body on each foot plate: half the
    mass and half the inertia, its centre of mass above that foot. Total mass and centre of mass are exact; a
    static centre of pressure falls under each ankle; roll and yaw inertia are overstated by m·(w/2)² for a
    stance width w (4.7 kg·m² for 75 kg and 0.5 m), a stated simplification of how a person shares load."""

    def __init__(self, twin: TwinRobot, payload: PayloadModel | None = None, *, include_rods: bool = True) -> None:
        payload = payload or PayloadModel()
        self.twin = twin
        self.payload = payload
        self.include_rods = include_rods
        self.origin = stance_origin_world(twin)
        base_rotations, base_origins, levers, neutral_rotations, arrays = [], [], [], [], []
        share = payload.scaled(0.5)
        for side in twin.sides:
            placement, robot = twin.placement(side), twin.robot_for(side)
            _check_rated_load(robot, share.mass_kg)
            yaw = placement.base_yaw_rad
            base_rotation = yaw_matrix(yaw)
            neutral = np.asarray(robot.neutral_pose, dtype=float)
            neutral_world = base_rotation @ rotation_matrices(neutral[None, 3:])[0]
            platform_world = np.asarray(placement.base_origin_m) + base_rotation @ neutral[:3]
            # Half of the patient stands on this foot plate, its axes those of the world at neutral.
            support = np.asarray(placement.foot_plate_offset_m, dtype=float)
            arrays.append(
                RobotDynamicsArrays.build(
                    robot, payload_body(share, support, neutral_world.T), include_rods=include_rods
                )
            )
            base_rotations.append(base_rotation)
            base_origins.append(np.asarray(placement.base_origin_m, dtype=float))
            levers.append(platform_world - self.origin)
            neutral_rotations.append(neutral_world)
        self.robot_arrays = tuple(arrays)
        self._base_rotations = np.ascontiguousarray(base_rotations)
        self._base_origins = np.ascontiguousarray(base_origins)
        self._levers = np.ascontiguousarray(levers)
        self._neutral_rotations = np.ascontiguousarray(neutral_rotations)
        self._geometry = np.ascontiguousarray([a.geometry for a in arrays])
        self._scalars = np.ascontiguousarray([a.scalars for a in arrays])
        self._top_com = np.ascontiguousarray([a.top.com_m for a in arrays])
        self._top_inertia = np.ascontiguousarray([a.top.inertia_kg_m2 for a in arrays])
        self._stance_motion = np.zeros(24)
        self._scratch = np.zeros(SCRATCH_SIZE)
        self._tick_motions = np.zeros((1, 2, 24))
        self._tick = _TickBuffers(12)
        self.step(np.zeros(6), np.zeros(6), np.zeros(6))  # compile and check

    def slider_forces(
        self, stance_poses: np.ndarray, stance_velocities: np.ndarray, stance_accelerations: np.ndarray
    ) -> np.ndarray:
        poses, rates, accelerations = _as_trajectory(stance_poses, stance_velocities, stance_accelerations)
        out = np.empty((poses.shape[0], 12))
        motions = np.empty((poses.shape[0], 2, 24))
        self._run(poses, rates, accelerations, motions, out, with_forces=True)
        return out

    def step(self, stance_pose: np.ndarray, stance_velocity: np.ndarray, stance_acceleration: np.ndarray) -> np.ndarray:
        """One sample, allocation-free: (6,) stance arrays in, the internal (12,) force buffer out."""
        tick = self._tick.load(stance_pose, stance_velocity, stance_acceleration)
        self._run(tick.poses, tick.rates, tick.accelerations, self._tick_motions, tick.forces, with_forces=True)
        return tick.forces_flat

    def platform_motion(
        self, stance_poses: np.ndarray, stance_velocities: np.ndarray, stance_accelerations: np.ndarray
    ) -> dict[str, tuple[PlatformMotion, LegMotion]]:
        """Each robot's platform and leg motion (base frame) for a stance trajectory; keys 'right', 'left'."""
        poses, rates, accelerations = _as_trajectory(stance_poses, stance_velocities, stance_accelerations)
        count = poses.shape[0]
        motions = np.empty((count, 2, 24))
        self._run(poses, rates, accelerations, motions, np.empty((count, 12)), with_forces=False)
        result = {}
        for index, side in enumerate(self.twin.sides):
            motion = np.ascontiguousarray(motions[:, index])
            legs = np.empty((count, 6, 12))
            failed = _legs_batch(motion, self._geometry[index], self._scalars[index], self._scratch, legs)
            if failed >= 0:
                raise DynamicsError(failed, f"{side} robot: stance pose {poses[failed].tolist()} is unreachable")
            platform = PlatformMotion(
                motion[:, 0:3],
                motion[:, 3:12].reshape(count, 3, 3),
                motion[:, 12:15],
                motion[:, 15:18],
                motion[:, 18:21],
                motion[:, 21:24],
            )
            leg = LegMotion(legs[..., 0:3], legs[..., 3:6], legs[..., 6:9], legs[..., 9], legs[..., 10], legs[..., 11])
            result[side] = (platform, leg)
        return result

    def _run(
        self,
        poses: np.ndarray,
        rates: np.ndarray,
        accelerations: np.ndarray,
        motions: np.ndarray,
        out: np.ndarray,
        *,
        with_forces: bool,
    ) -> None:
        count = poses.shape[0]
        if count <= IK_CHUNK_POSES:  # the tick and short batches: one call, the preallocated scratch
            failed = self._batch(
                poses, rates, accelerations, motions, out, with_forces, self._stance_motion, self._scratch
            )
        else:  # chunks on both cores, each with its own scratch; the earliest failure counts
            failures: list[int] = []

            def run_chunk(rows: slice) -> None:
                arrays = (poses[rows], rates[rows], accelerations[rows], motions[rows], out[rows])
                failed = self._batch(*arrays, with_forces, np.zeros(24), np.zeros(SCRATCH_SIZE))
                failures.append(failed if failed < 0 else failed + rows.start)

            for_each_chunk(count, run_chunk)
            failed = min((f for f in failures if f >= 0), default=-1)
        if failed >= 0:
            raise DynamicsError(failed, f"stance pose {poses[failed].tolist()} is unreachable or singular")

    def _batch(
        self,
        poses: np.ndarray,
        rates: np.ndarray,
        accelerations: np.ndarray,
        motions: np.ndarray,
        out: np.ndarray,
        with_forces: bool,
        stance_motion: np.ndarray,
        scratch: np.ndarray,
    ) -> int:
        """`_twin_batch` over these samples with this scratch; the first failing sample or −1."""
        return int(
            _twin_batch(
                poses,
                rates,
                accelerations,
                self.origin,
                self._base_rotations,
                self._base_origins,
                self._levers,
                self._neutral_rotations,
                self._geometry,
                self._scalars,
                self._top_com,
                self._top_inertia,
                GRAVITY_VECTOR,
                stance_motion,
                scratch,
                motions,
                out,
                with_forces,
            )
        )


# --- The paper's dynamics scenarios (§3.2.1–3.2.2) ---------------------------------------------------------

PAPER_STEP_TIME_S = 0.1
PAPER_ACCELERATION_BEFORE_M_S2 = 5.0
PAPER_ACCELERATION_AFTER_M_S2 = 0.5
PAPER_FORCE_BAND_N = (500.0, 3000.0)


@dataclass(frozen=True)
class StanceTrajectory:
    times_s: np.ndarray  # (N,)
    poses: np.ndarray  # (N, 6) relative to neutral
    velocities: np.ndarray
    accelerations: np.ndarray


def paper_step_trajectory(axis: str, duration_s: float, sample_period_s: float) -> StanceTrajectory:
    """From rest at neutral: acceleration 5 m/s² along +`axis` ('x', 'y' or 'z') until 0.1 s, then 0.5 m/s².
    Velocity and position are the exact integrals of the piecewise-constant acceleration."""
    axes = {"x": 0, "y": 1, "z": 2}
    if axis not in axes:
        raise ValueError(f"axis = {axis!r}: must be one of {sorted(axes)}")
    if not (0.0 < sample_period_s <= duration_s):
        raise ValueError(f"sample_period_s = {sample_period_s}: must be in (0, duration_s = {duration_s}]")
    times = np.arange(round(duration_s / sample_period_s) + 1) * sample_period_s
    first, second, switch = PAPER_ACCELERATION_BEFORE_M_S2, PAPER_ACCELERATION_AFTER_M_S2, PAPER_STEP_TIME_S
    before = times < switch
    late = np.maximum(times - switch, 0.0)
    acceleration = np.where(before, first, second)
    velocity = np.where(before, first * times, first * switch + second * late)
    position = np.where(
        before, 0.5 * first * times**2, 0.5 * first * switch**2 + first * switch * late + 0.5 * second * late**2
    )
    poses, velocities, accelerations = (np.zeros((times.size, 6)) for _ in range(3))
    poses[:, axes[axis]], velocities[:, axes[axis]], accelerations[:, axes[axis]] = position, velocity, acceleration
    return StanceTrajectory(times, poses, velocities, accelerations)


def force_summary(forces_n: np.ndarray) -> dict[str, Any]:
    """Each joint's peak |force| over the motion — what its drive must deliver — and whether every joint's peak
    lies in the paper's band (§3.2: "the driving force on each linear joint is between 500 N and 3000 N").
    `forces_n` is (N samples, joints)."""
    magnitudes = np.abs(np.atleast_2d(forces_n))
    peaks = magnitudes.max(axis=0)
    low, high = PAPER_FORCE_BAND_N
    return {
        "max_abs_force_n": float(peaks.max()),
        "min_abs_force_n": float(peaks.min()),
        "in_paper_band": bool(peaks.min() >= low and peaks.max() <= high),
        "paper_band_n": [low, high],
        "per_joint_peak_abs_force_n": peaks.tolist(),
        "min_instantaneous_abs_force_n": float(magnitudes.min()),
    }
