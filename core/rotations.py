"""Platform orientation: R = Rx(roll)·Ry(pitch)·Rz(yaw), the paper's Formula (9) with its printed element
(2,3) "−cβ·sβ" corrected to −cβ·sα (REFERENCE.md §1). One compiled kernel that every per-tick path shares."""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def rotation_into(roll: float, pitch: float, yaw: float, out: np.ndarray) -> None:
    """Write R = Rx(roll)·Ry(pitch)·Rz(yaw) into the (3, 3) array `out`; allocates nothing."""
    ca, sa = math.cos(roll), math.sin(roll)
    cb, sb = math.cos(pitch), math.sin(pitch)
    cc, sc = math.cos(yaw), math.sin(yaw)
    out[0, 0] = cb * cc
    out[0, 1] = -cb * sc
    out[0, 2] = sb
    out[1, 0] = ca * sc + sa * sb * cc
    out[1, 1] = ca * cc - sa * sb * sc
    out[1, 2] = -sa * cb
    out[2, 0] = sa * sc - ca * sb * cc
    out[2, 1] = sa * cc + ca * sb * sc
    out[2, 2] = ca * cb


def rotation_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rx(roll)·Ry(pitch)·Rz(yaw) as a new (3, 3) array."""
    out = np.empty((3, 3))
    rotation_into(roll, pitch, yaw, out)
    return out
