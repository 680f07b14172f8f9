"""Reachable workspace of one 6-SSP robot or of the twin's stance frame (paper §3.1; issue 2, item 7).

A pose is reachable when the closed-form IK (core.kinematics) reports no violation: every rod reaches
its rail, every slider stays in its stroke, every spherical joint in its cone, and the Jacobian stays
well conditioned on the neutral pose's side of every singularity. Ranges are offsets from the neutral
pose (m, rad): per axis by a grid scan then bisection outward from neutral, and jointly by a seeded
uniform 6-DOF cloud. Everything is evaluated as batches.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from core.kinematics import VIOLATION_REASONS, LegViolation, inverse_kinematics, twin_inverse_kinematics
from core.robot import SSPRobot, TwinRobot

AXIS_NAMES = ("x", "y", "z", "roll", "pitch", "yaw")
# How far each axis is searched from neutral: beyond a rod length nothing reaches; Euler pitch stops short of ±90°.
SEARCH_LIMITS = np.array([1.0, 1.0, 1.0, math.pi, math.radians(89.0), math.pi])
SEARCH_LIMIT_REASON = "search limit"

# Offsets from neutral (N, 6) → (reachable (N,), violation flags OR-ed over the legs (N,)).
Reachability = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def robot_reachability(robot: SSPRobot) -> Reachability:
    neutral = np.asarray(robot.neutral_pose, dtype=float)

    def evaluate(offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        flags = np.bitwise_or.reduce(inverse_kinematics(robot, neutral + offsets, check=False).violations, axis=1)
        return flags == 0, flags

    return evaluate


def stance_reachability(twin: TwinRobot, *, clearance_check: bool = True) -> Reachability:
    """Stance-frame poses move both feet as one rigid body: reachable only if both robots can follow and
    no two parts collide (`clearance_check=False` ignores collisions: for layouts that cannot be built)."""

    def evaluate(offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        solutions = twin_inverse_kinematics(twin, offsets, check=False, clearance_check=clearance_check)
        flags = np.bitwise_or.reduce(
            np.concatenate([solution.violations for solution in solutions.values()], axis=1), axis=1
        )
        return flags == 0, flags

    return evaluate


def reasons(flags: int) -> list[str]:
    """The limit names set in a violation bit field."""
    return [text for flag, text in VIOLATION_REASONS.items() if int(flags) & flag]


@dataclass(frozen=True)
class AxisRange:
    """Reach along one axis from neutral, the others held at neutral (m or rad)."""

    axis: str
    minimum: float
    maximum: float
    limited_by_min: str
    limited_by_max: str


def axis_ranges(reachability: Reachability, *, scan_points: int = 2000, bisection_steps: int = 40) -> list[AxisRange]:
    """Per-axis reach: scan each of the 12 half-axes, then bisect between the last reachable and the
    first unreachable scan point (all rays at once). Refuses an unreachable neutral pose."""
    neutral_ok, neutral_flags = reachability(np.zeros((1, 6)))
    if not neutral_ok[0]:
        why = ", ".join(reasons(int(neutral_flags[0])))
        raise ValueError(f"neutral pose: not reachable ({why}), so there is no workspace around it")
    directions = np.concatenate([np.diag(SEARCH_LIMITS), -np.diag(SEARCH_LIMITS)])  # (12, 6) rays to the search limit
    fractions = np.linspace(0.0, 1.0, scan_points + 1)[1:]
    scan = (fractions[None, :, None] * directions[:, None, :]).reshape(-1, 6)
    reachable = reachability(scan)[0].reshape(len(directions), scan_points)
    blocked = ~reachable
    first_blocked = np.where(blocked.any(axis=1), blocked.argmax(axis=1), scan_points)
    low = np.where(first_blocked > 0, fractions[np.maximum(first_blocked - 1, 0)], 0.0)
    high = np.where(first_blocked < scan_points, fractions[np.minimum(first_blocked, scan_points - 1)], 1.0)
    open_ray = first_blocked == scan_points  # reachable all the way to the search limit
    for _ in range(bisection_steps):
        middle = 0.5 * (low + high)
        ok = reachability(middle[:, None] * directions)[0] | open_ray
        low = np.where(ok, middle, low)
        high = np.where(ok, high, middle)
    limit_flags = reachability(high[:, None] * directions)[1]
    limits = [SEARCH_LIMIT_REASON if open_ray[i] else ", ".join(reasons(limit_flags[i])) for i in range(12)]
    reach = low * np.tile(SEARCH_LIMITS, 2)
    return [
        AxisRange(name, -float(reach[axis + 6]), float(reach[axis]), limits[axis + 6], limits[axis])
        for axis, name in enumerate(AXIS_NAMES)
    ]


@dataclass(frozen=True)
class Cloud:
    """A seeded uniform 6-DOF sample of offsets from neutral, and which of them are reachable."""

    offsets: np.ndarray  # (N, 6) m, rad
    reachable: np.ndarray  # (N,) bool
    flags: np.ndarray  # (N,) violation bits OR-ed over the legs

    @property
    def reachable_fraction(self) -> float:
        return float(np.mean(self.reachable))

    def extents(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-axis min and max over the reachable samples (6,) each; NaN if none is reachable."""
        inside = self.offsets[self.reachable]
        if not len(inside):
            return np.full(6, np.nan), np.full(6, np.nan)
        return inside.min(axis=0), inside.max(axis=0)

    def limiting_fractions(self) -> dict[str, float]:
        """Share of the unreachable samples that break each limit (a sample may break several)."""
        blocked = self.flags[~self.reachable]
        total = max(len(blocked), 1)
        return {text: float(np.count_nonzero(blocked & flag)) / total for flag, text in VIOLATION_REASONS.items()}


def sample_cloud(
    reachability: Reachability,
    ranges: list[AxisRange],
    samples: int,
    *,
    seed: int = 0,
    margin: float = 1.25,
    batch: int = 50_000,
    progress: Callable[[int], None] | None = None,
) -> Cloud:
    """Uniform samples in the per-axis box widened by `margin` (combined motions can reach beyond the
    single-axis ranges), evaluated in batches so that `progress(n)` can report."""
    if samples < 1:
        raise ValueError(f"samples = {samples}: must be >= 1")
    low = np.array([r.minimum for r in ranges]) * margin
    high = np.array([r.maximum for r in ranges]) * margin
    offsets = np.random.default_rng(seed).uniform(low, high, (samples, 6))
    reachable = np.empty(samples, dtype=bool)
    flags = np.empty(samples, dtype=np.uint8)
    for start in range(0, samples, batch):
        chunk = slice(start, start + batch)
        reachable[chunk], flags[chunk] = reachability(offsets[chunk])
        if progress is not None:
            progress(len(offsets[chunk]))
    return Cloud(offsets, reachable, flags)


def slice_grid(
    reachability: Reachability,
    axes: tuple[int, int],
    extents: tuple[tuple[float, float], tuple[float, float]],
    points: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 2-D slice through neutral along two axes: values (points,), values (points,) and the
    violation flags (points, points) with rows along the second axis."""
    first = np.linspace(*extents[0], points)
    second = np.linspace(*extents[1], points)
    grid_first, grid_second = np.meshgrid(first, second)
    offsets = np.zeros((grid_first.size, 6))
    offsets[:, axes[0]] = grid_first.ravel()
    offsets[:, axes[1]] = grid_second.ravel()
    return first, second, reachability(offsets)[1].reshape(points, points)


__all__ = [
    "AXIS_NAMES",
    "AxisRange",
    "Cloud",
    "LegViolation",
    "Reachability",
    "axis_ranges",
    "reasons",
    "robot_reachability",
    "sample_cloud",
    "slice_grid",
    "stance_reachability",
]
