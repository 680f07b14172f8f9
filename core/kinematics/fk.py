"""Forward kinematics: Newton's method on IK(pose) = sliders with the analytic pose Jacobian, compiled,
warm-started from the last pose (as LinuxCNC's genhexkins); continuation in slider space on a cold start;
a solution in another assembly mode than the guess is refused, never returned."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from core.kinematics.ik import inverse_kinematics
from core.kinematics.legs import LegGeometry, leg_geometry, leg_solution, twist_row
from core.robot import SSPRobot
from core.rotations import rotation_into


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


@dataclass(frozen=True)
class FKResult:
    pose: np.ndarray  # (6,)
    iterations: int
    residual_m: float  # max |IK(pose) − sliders|


@numba.njit(cache=True, fastmath=False)
def _fk_residual_and_jacobian(
    pose: np.ndarray,
    sliders: np.ndarray,
    geometry: LegGeometry,
    residual: np.ndarray,
    jacobian: np.ndarray,
    rotation: np.ndarray,
) -> tuple[float, float]:
    """IK(pose) − sliders into `residual` and the pose Jacobian into `jacobian`; returns (max |r|, |r|²),
    both inf when a rod cannot reach its rail at `pose`."""
    rotation_into(pose[3], pose[4], pose[5], rotation)
    ca, sa = np.cos(pose[3]), np.sin(pose[3])
    cb, sb = np.cos(pose[4]), np.sin(pose[4])
    max_residual = 0.0
    squared_norm = 0.0
    for leg in range(6):
        lx, ly, lz, dx, dy, dz, slider, reach_sq = leg_solution(geometry, leg, pose[0], pose[1], pose[2], rotation)
        if reach_sq <= 0.0:
            return np.inf, np.inf
        value = slider - sliders[leg]
        residual[leg] = value
        max_residual = max(max_residual, abs(value))
        squared_norm += value * value
        row = twist_row(lx, ly, lz, dx, dy, dz)
        for column in range(3):
            jacobian[leg, column] = row[column]
        # ω = E · Euler rates, E = [e_x, Rx·e_y, Rx·Ry·e_z].
        jacobian[leg, 3] = row[3]
        jacobian[leg, 4] = ca * row[4] + sa * row[5]
        jacobian[leg, 5] = sb * row[3] - sa * cb * row[4] + ca * cb * row[5]
    return max_residual, squared_norm


# Step halvings allowed per Newton step before giving up: 2⁻¹⁰ of a Newton step is no progress.
_FK_MAX_HALVINGS = 10


@numba.njit(cache=True, fastmath=False)
def _fk_newton_steps(
    sliders: np.ndarray,
    guess: np.ndarray,
    geometry: LegGeometry,
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
    max_residual, squared_norm = _fk_residual_and_jacobian(pose, sliders, geometry, residual, jacobian, rotation)
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
            trial_max, trial_norm = _fk_residual_and_jacobian(trial, sliders, geometry, residual, jacobian, rotation)
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
    geometry: LegGeometry,
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
        guess, np.zeros(6), geometry, start_sliders, jacobian, np.empty((3, 3))
    )
    if not np.isfinite(start_residual):  # the guess itself is impossible
        pose_out[:] = guess
        return 0, np.inf
    guess_det_sign = np.sign(np.linalg.det(jacobian))
    iterations, residual = _fk_newton_steps(sliders, guess, geometry, tolerance, max_iterations, pose_out)
    if iterations >= 0 and _same_assembly_mode(pose_out, guess_det_sign, geometry):
        return iterations, residual
    more, residual = _fk_continuation(sliders, start_sliders, guess, geometry, tolerance, max_iterations, pose_out)
    iterations = abs(iterations) + abs(more)
    if more >= 0 and _same_assembly_mode(pose_out, guess_det_sign, geometry):
        return iterations, residual
    return -max(iterations, 1), residual


@numba.njit(cache=True, fastmath=False)
def _same_assembly_mode(
    pose: np.ndarray,
    det_sign: float,
    geometry: LegGeometry,
) -> bool:
    residual = np.empty(6)
    jacobian = np.empty((6, 6))
    rotation = np.empty((3, 3))
    _fk_residual_and_jacobian(pose, np.zeros(6), geometry, residual, jacobian, rotation)
    return bool(np.sign(np.linalg.det(jacobian)) == det_sign)


@numba.njit(cache=True, fastmath=False)
def _fk_continuation(
    sliders: np.ndarray,
    start_sliders: np.ndarray,
    guess: np.ndarray,
    geometry: LegGeometry,
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
            steps, residual = _fk_newton_steps(target, pose, geometry, tolerance, max_iterations, pose_out)
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
    geometry: LegGeometry,
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
            geometry,
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
        self._geometry = leg_geometry(robot)
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
            self._geometry,
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
            self._geometry,
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
