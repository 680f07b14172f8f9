"""Rotations of the pose convention, batch forms: R = Rx(roll)·Ry(pitch)·Rz(yaw) (Formula 9, typo corrected).

The matrix itself is written once, in the compiled `core.rotations.rotation_into`; the batch form here
loops that kernel over the poses, so IK, FK, dynamics, the clearance check and the tick share one formula.
"""

from __future__ import annotations

import numba
import numpy as np

from core.rotations import rotation_into, rotation_matrix

__all__ = [
    "euler_from_rotation",
    "euler_rate_matrices",
    "rotation_into",
    "rotation_matrices",
    "rotation_matrix",
    "yaw_matrix",
]


@numba.njit(cache=True, nogil=True)
def _rotations_into(angles: np.ndarray, out: np.ndarray) -> None:
    for index in range(angles.shape[0]):
        rotation_into(angles[index, 0], angles[index, 1], angles[index, 2], out[index])


def rotation_matrices(angles: np.ndarray) -> np.ndarray:
    """(..., 3) roll, pitch, yaw → (..., 3, 3) rotations."""
    angles = np.asarray(angles, dtype=float)
    flat = np.ascontiguousarray(angles.reshape(-1, 3))
    out = np.empty((flat.shape[0], 3, 3))
    _rotations_into(flat, out)
    return out.reshape(*angles.shape[:-1], 3, 3)


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


def yaw_matrix(yaw: float) -> np.ndarray:
    """Rz(yaw): how a base frame stands in the world (bases only turn about Z)."""
    return rotation_matrix(0.0, 0.0, yaw)
