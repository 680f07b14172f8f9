"""Closeness to a singularity: the scaled twist Jacobian's condition number and the sign of its determinant.

An exact SVD would cost ~5 µs per pose, so a compiled kernel first bounds cond₂ cheaply
(Guggenheimer–Edelman–Johnson 2/|det J|·(‖J‖_F²/6)³; then ‖·‖₂ bounds from ‖(AᵀA)⁸‖_∞ for J and J⁻¹,
tight to 6^(1/16)) and the caller computes the exact condition number only where the bounds leave the
answer open. `singularity_report` follows a trajectory: worst condition number and when, every change
of assembly mode (det J sign change) and every interval beyond the margin.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numba
import numpy as np

from core.kinematics.legs import LegGeometry, leg_solution, twist_row
from core.rotations import rotation_into


@numba.njit(cache=True, nogil=True)
def fill_scaled_jacobian(
    geometry: LegGeometry, px: float, py: float, pz: float, rotation: np.ndarray, jacobian: np.ndarray
) -> bool:
    """The twist Jacobian with ω columns scaled by 1/platform radius, into `jacobian` (6, 6);
    False (and NaN rows) where a rod cannot reach its rail."""
    reachable = True
    scale = geometry.rotation_scale
    for leg in range(6):
        lx, ly, lz, dx, dy, dz, _, _ = leg_solution(geometry, leg, px, py, pz, rotation)
        row = twist_row(lx, ly, lz, dx, dy, dz)
        for column in range(3):
            jacobian[leg, column] = row[column]
            jacobian[leg, 3 + column] = row[3 + column] * scale
        reachable = reachable and np.isfinite(dx)
    return reachable


@numba.njit(cache=True, fastmath=False, nogil=True)
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
def conditioning_kernel(
    jacobians: np.ndarray,
    reachable: np.ndarray,
    condition_number_max: float,
    bounds_out: np.ndarray,
    det_sign_out: np.ndarray,
) -> None:
    """Per pose: the sign of det J and bounds on cond₂(J) = ‖J‖₂‖J⁻¹‖₂: a cheap one when it already
    clears the limit, else within 6^(1/16) each way (`_spectral_norm_bounds`). bounds_out[:, 0] is the
    lower bound, [:, 1] the upper; NaN where a rod cannot reach (flagged elsewhere), inf where J is singular."""
    lu = np.empty((6, 6))
    inverse = np.empty((6, 6))
    gram = np.empty((6, 6))
    power = np.empty((6, 6))
    permutation = np.empty(6, dtype=np.int64)
    for pose in range(jacobians.shape[0]):
        jacobian = jacobians[pose]
        if not reachable[pose]:
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


def singular_poses(geometry: LegGeometry, jacobians: np.ndarray, reachable: np.ndarray) -> np.ndarray:
    """(n,) True where cond(J) exceeds its limit or det J has left the neutral pose's sign. The exact
    condition number (an SVD) is computed only where the cheap bounds leave the answer open."""
    count = len(jacobians)
    bounds, det_sign = np.empty((count, 2)), np.empty(count)
    conditioning_kernel(jacobians, reachable, geometry.condition_number_max, bounds, det_sign)
    other_mode = det_sign == -geometry.neutral_det_sign
    singular = other_mode | (bounds[:, 0] > geometry.condition_number_max) | (det_sign == 0.0)
    unclear = np.flatnonzero(~singular & (bounds[:, 1] > geometry.condition_number_max))
    if unclear.size:
        singular[unclear] = np.linalg.cond(jacobians[unclear]) > geometry.condition_number_max
    return singular


@numba.njit(cache=True, nogil=True)
def _scaled_jacobians(
    geometry: LegGeometry, positions: np.ndarray, rotations: np.ndarray, jacobians: np.ndarray, reachable: np.ndarray
) -> None:
    for pose in range(positions.shape[0]):
        reachable[pose] = fill_scaled_jacobian(
            geometry, positions[pose, 0], positions[pose, 1], positions[pose, 2], rotations[pose], jacobians[pose]
        )


def scaled_jacobians(
    geometry: LegGeometry, positions: np.ndarray, rotations: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Scaled twist Jacobians (N, 6, 6) and whether every rod reaches (N,)."""
    count = len(positions)
    jacobians, reachable = np.empty((count, 6, 6)), np.empty(count, dtype=np.bool_)
    _scaled_jacobians(
        geometry,
        np.ascontiguousarray(positions, dtype=float),
        np.ascontiguousarray(rotations, dtype=float),
        jacobians,
        reachable,
    )
    return jacobians, reachable


def det_sign_of(geometry: LegGeometry, pose: np.ndarray) -> float:
    """Sign of det J at one pose (x, y, z, roll, pitch, yaw)."""
    rotation = np.empty((1, 3, 3))
    rotation_into(pose[3], pose[4], pose[5], rotation[0])
    jacobians, reachable = scaled_jacobians(geometry, np.asarray(pose[None, :3], dtype=float), rotation)
    bounds, det_sign = np.empty((1, 2)), np.empty(1)
    conditioning_kernel(jacobians, reachable, geometry.condition_number_max, bounds, det_sign)
    return float(det_sign[0])


def exact_conditioning(
    geometry: LegGeometry, positions: np.ndarray, rotations: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Exact cond₂ of the scaled Jacobians (N,) and sign of det J (N,); NaN where a rod cannot reach."""
    jacobians, reachable = scaled_jacobians(geometry, positions, rotations)
    condition = np.full(len(jacobians), np.nan)
    sign = np.full(len(jacobians), np.nan)
    if np.any(reachable):
        condition[reachable] = np.linalg.cond(jacobians[reachable])
        sign[reachable] = np.sign(np.linalg.det(jacobians[reachable]))
    return condition, sign


# --- Reporting a trajectory -------------------------------------------------------------------------


@dataclass(frozen=True)
class SingularityReport:
    """How one robot's trajectory stands to its singularities. Times in s (sample index × period)."""

    worst_condition_number: float  # inf when J is exactly singular on a sample
    worst_condition_number_time_s: float
    condition_number_max: float  # the margin
    samples_beyond_margin: int  # cond(J) above the margin or in the other assembly mode
    # Each change of sign of det J: (last sample before, first sample after), s.
    det_sign_changes: list[tuple[float, float]] = field(default_factory=list)
    # Each stretch spent in another assembly mode than at neutral: (first, last sample), s.
    other_assembly_mode: list[tuple[float, float]] = field(default_factory=list)
    # Each stretch beyond the margin (either reason): (first, last sample), s.
    beyond_margin: list[tuple[float, float]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        def stretch(pairs: list[tuple[float, float]]) -> list[dict[str, float]]:
            return [{"from_s": a, "to_s": b} for a, b in pairs]

        return {
            "worst_condition_number": self.worst_condition_number,
            "worst_condition_number_time_s": self.worst_condition_number_time_s,
            "condition_number_max": self.condition_number_max,
            "samples_beyond_margin": self.samples_beyond_margin,
            "det_sign_changes": stretch(self.det_sign_changes),
            "other_assembly_mode": stretch(self.other_assembly_mode),
            "beyond_margin": stretch(self.beyond_margin),
        }

    def summary(self) -> str:
        crossings = ", ".join(f"{a:.3f}–{b:.3f} s" for a, b in self.other_assembly_mode) or "none"
        return (
            f"worst condition number {self.worst_condition_number:.4g} "
            f"at t = {self.worst_condition_number_time_s:.3f} s "
            f"(margin {self.condition_number_max:g}); {self.samples_beyond_margin} samples beyond the margin; "
            f"other assembly mode (det J sign changed): {crossings}"
        )


def stretches(flags: np.ndarray, times: np.ndarray) -> list[tuple[float, float]]:
    """(first, last) time of each run of True in `flags`."""
    edges = np.diff(np.concatenate([[0], flags.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    return [(float(times[a]), float(times[b])) for a, b in zip(starts, ends, strict=True)]


def singularity_report(
    geometry: LegGeometry, positions: np.ndarray, rotations: np.ndarray, times_s: np.ndarray
) -> SingularityReport:
    """Follow a trajectory (N poses at `times_s`) through the conditioning of its Jacobian."""
    condition, sign = exact_conditioning(geometry, positions, rotations)
    other_mode = sign == -geometry.neutral_det_sign
    # Beyond a sign change the condition number falls again: the other mode counts as infinitely bad.
    figure = np.where(other_mode | (sign == 0.0), np.inf, condition)
    beyond = (figure > geometry.condition_number_max) | np.isnan(figure)
    worst = int(np.nanargmax(np.where(np.isnan(condition), -np.inf, condition))) if len(condition) else 0
    known = np.flatnonzero(~np.isnan(sign))
    changes = known[:-1][np.diff(sign[known]) != 0]
    following = known[1:][np.diff(sign[known]) != 0]
    return SingularityReport(
        worst_condition_number=float(condition[worst]) if len(condition) else float("nan"),
        worst_condition_number_time_s=float(times_s[worst]) if len(condition) else float("nan"),
        condition_number_max=geometry.condition_number_max,
        samples_beyond_margin=int(np.sum(beyond)),
        det_sign_changes=[(float(times_s[a]), float(times_s[b])) for a, b in zip(changes, following, strict=True)],
        other_assembly_mode=stretches(other_mode, times_s),
        beyond_margin=stretches(beyond, times_s),
    )
