"""Optimal motion cueing with perfect preview (issue 14 §3; REFERENCE.md §7).

Every cue of a prescription is known before the drives are powered, so the twin's stance trajectory can
be chosen by an optimal control problem over the whole segment instead of by a filter that sees only
the past. The problem, per segment:

    minimise   Σ_k  w_f ‖(perceived specific-force error at the head)_k / threshold‖²
                  + w_ω ‖(perceived angular-velocity error)_k / threshold‖²
                  + platform usage (displacement, angle, velocity) + w_j ‖jerk‖²
    subject to the twin's workspace at every knot: every slider within its stroke, both joint cones,
               the stance tilt, the Jacobian condition number of each robot (singularity margin; the
               IK's fixed working-mode branch keeps the assembly mode), the collision clearance between
               the twin's parts (`core.clearance`, as the IK reports it; by default the robot's margin plus
               the 20 mm stop margin, what the worker's offline check enforces); slider velocity and
               acceleration; the rotation the cue does not ask for below the canal perception threshold
               (|ω_platform − ω_cue| ≤ 3 °/s roll, 3.6 °/s pitch by default); start and end at neutral,
               at rest.

Errors are perceived through the paper's otolith and canal models (`core.vestibular`), discretised at the
knot period and carried as state variables, so the QP stays sparse. The specific force is the one at
the head (`core.perception`), lever-arm terms included; its dependence on the trajectory is nonlinear
(the tilt rotates gravity), as are the slider positions, cones and condition numbers. Each is linearised
around the previous iterate (finite differences of the exact functions) and the QP is solved with OSQP:
a sequential QP with a trust region. Constraint rows enter by an active set (rows near their limit,
plus any the exact evaluation of a step finds violated), and a step is accepted only when the exact
functions satisfy every limit.

Trajectory representation: a uniform cubic B-spline (knot period T, default 40 ms). Knot pose, velocity
and acceleration are exact linear maps of the control points, (c₋ + 4c + c₊)/6, (c₊ − c₋)/2T and
(c₊ − 2c + c₋)/T², and the curve is C², so the 1 kHz trajectory the worker plays is the same curve
sampled finely. Three zero control points at each end make it start and end exactly at neutral with
zero velocity and acceleration. The first natural frequency (9.76 Hz) is kept out by the jerk penalty
(it weighs content by ω⁶: 9.76 Hz costs 10⁶ times more than 1 Hz) instead of a lagging post-filter.

Long segments are planned in receding windows: each window optimises `window_s`, keeps the first
`window_s − overlap_s` and hands its last control points and perception states to the next.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import TYPE_CHECKING, Any

import numpy as np
import osqp
import scipy.sparse as sp

from core.clearance import IK_EXACT_BELOW_M, STOP_CLEARANCE_MARGIN_M, min_clearance
from core.errors import refuse_unknown_fields
from core.kinematics import (
    PoseCollisions,
    euler_from_rotation,
    twin_inverse_kinematics,
    twin_platform_poses,
    twist_jacobian,
)
from core.perception import DEFAULT_HEAD_HEIGHT_M, head_angular_velocity, head_specific_force
from core.robot import MotionLimits, SSPRobot, TwinRobot
from core.shaping import ParameterError, require_finite
from core.vestibular import VestibularModel, VestibularParameters

if TYPE_CHECKING:
    import control

# Stance poses (N, 6) → minimum collision clearance (N,) m; by default the twin's parts (core.clearance).
ClearanceFunction = Callable[[np.ndarray], np.ndarray]

POSITION_SCALE_M = 0.1  # usage is measured in units of the travel budget of one cue
ANGLE_SCALE_RAD = 0.1
VELOCITY_SCALE = 0.1  # m/s and rad/s
JERK_SCALE = 50.0  # m/s³ (and rad/s³): a 1 Hz, 5 cm motion has ~12 m/s³, a 1 mm 9.76 Hz ripple ~230
_USABLE_QP_STATUS = (1, 2, 7)  # OSQP: solved, solved inaccurate, maximum iterations reached
_ROTATION_SAMPLES = 4  # per knot interval, where the exact check looks at the rotation rate
_FD_STEP = 1e-6  # finite-difference step of the exact functions (m, rad, m/s, ...)


class CueingError(ParameterError):
    """An invalid optimal-cueing setting or input; names the field, the value and the limit."""


@dataclass(frozen=True)
class OptimalCueingParameters:
    """Weights, thresholds and solver settings of optimal cueing (SI units)."""

    knot_period_s: float = 0.04
    window_s: float = 12.0
    overlap_s: float = 3.0
    head_height_m: float = DEFAULT_HEAD_HEIGHT_M
    roll_rate_threshold_rad_s: float = math.radians(3.0)  # Reid & Nahon via secondary sources
    pitch_rate_threshold_rad_s: float = math.radians(3.6)
    specific_force_weight: float = 1.0
    angular_velocity_weight: float = 1.0
    displacement_weight: float = 1e-4
    angle_weight: float = 1e-4
    velocity_weight: float = 1e-4
    jerk_weight: float = 1e-2
    # The planner keeps this fraction of each limit: sampling between knots and linearisation need room.
    limit_fraction: float = 0.9
    sqp_iterations: int = 5
    # ADMM iterations per QP: an unfinished QP answer is only a search direction; the SQP's line search
    # accepts a step only after checking the exact functions.
    qp_iterations: int = 700
    trust_region_m: float = 0.2  # per SQP step, on every control point
    trust_region_rad: float = 0.2
    step_tolerance: float = 1e-4  # stop when no control point moves more than this (m or rad)
    cost_tolerance: float = 0.01  # ... or when a full step lowers the exact cost by less than this fraction

    def __post_init__(self) -> None:
        for item in fields(self):
            value = getattr(self, item.name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
                raise CueingError(item.name, value, "must be a finite number")
            if item.name.endswith("_weight"):
                if value < 0.0:
                    raise CueingError(item.name, value, "must be >= 0")
            elif value <= 0.0:
                raise CueingError(item.name, value, "must be > 0")
        if not 0.005 <= self.knot_period_s <= 0.1:
            raise CueingError("knot_period_s", self.knot_period_s, "must be in [0.005, 0.1] s")
        if not self.limit_fraction <= 1.0:
            raise CueingError("limit_fraction", self.limit_fraction, "must be in (0, 1]")
        for name in ("sqp_iterations", "qp_iterations"):
            if not isinstance(getattr(self, name), int):
                raise CueingError(name, getattr(self, name), "must be an integer >= 1")
        if self.overlap_s >= self.window_s or self.window_s - self.overlap_s < 4 * self.knot_period_s:
            raise CueingError("overlap_s", self.overlap_s, f"must leave at least 4 knots of window_s {self.window_s:g}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> OptimalCueingParameters:
        refuse_unknown_fields(cls, data, CueingError, "optimal-cueing parameter")
        return cls(**dict(data))

    @property
    def tilt_rate_thresholds_rad_s(self) -> np.ndarray:
        return np.array([self.roll_rate_threshold_rad_s, self.pitch_rate_threshold_rad_s])


@dataclass(frozen=True)
class CueingWorkspace:
    """What the twin can do: its geometry, the limits normal motion keeps, and the clearance of its parts."""

    twin: TwinRobot
    limits: MotionLimits
    stroke_min_m: np.ndarray  # (12,) right sliders 1–6, then left
    stroke_max_m: np.ndarray
    # None: the twin's own parts (core.clearance), as its IK and the worker's independent check see them.
    clearance_m: ClearanceFunction | None = None
    # None: the twin's margin plus the stop margin of normal motion (what the offline check enforces).
    clearance_min_m: float | None = None

    def __post_init__(self) -> None:
        value = self.clearance_min_m
        if value is not None and (
            isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value)
        ):
            raise CueingError("clearance_min_m", value, "must be a finite number of metres (or None: the twin's)")

    @property
    def minimum_clearance_m(self) -> float:
        """The smallest clearance (m) between parts the plan keeps."""
        if self.clearance_min_m is not None:
            return float(self.clearance_min_m)
        return self.twin.parts.clearance_min_m + STOP_CLEARANCE_MARGIN_M

    def quantity_bounds(self, fraction: float) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of `workspace_quantities`' columns, each limit scaled toward neutral."""
        limits = self.limits
        neutral = workspace_quantities(self, np.zeros((1, 6)))[0]
        low = np.concatenate(
            [
                self.stroke_min_m,
                np.full(25, -np.inf),
                np.full(2, 1.0 / limits.condition_number_max),
                [self.minimum_clearance_m],
            ]
        )
        high = np.concatenate(
            [
                self.stroke_max_m,
                np.full(12, limits.base_joint_cone_rad),
                np.full(12, limits.platform_joint_cone_rad),
                [limits.tilt_max_rad],
                np.full(2, np.inf),
                [np.inf],
            ]
        )
        # Pull each finite bound toward the neutral value: the planner keeps room for what lies between knots.
        low = np.where(np.isfinite(low), neutral + fraction * (low - neutral), low)
        high = np.where(np.isfinite(high), neutral + fraction * (high - neutral), high)
        return low, high


def _inverse_condition_number(robot: SSPRobot, poses: np.ndarray) -> np.ndarray:
    """1 / `core.kinematics.condition_number`, from the eigenvalues of JᵀJ (cheaper than an SVD)."""
    jacobian = twist_jacobian(robot, poses)
    jacobian[..., 3:] /= robot.platform_radius_m
    eigenvalues = np.linalg.eigvalsh(np.swapaxes(jacobian, -1, -2) @ jacobian)
    return np.sqrt(np.maximum(eigenvalues[..., 0], 0.0) / eigenvalues[..., -1])


def _twin_sliders(twin: TwinRobot, poses: np.ndarray) -> np.ndarray:
    solutions = twin_inverse_kinematics(twin, poses, check=False, clearance_check=False)
    return np.concatenate([solutions[side].slider_positions_m for side in twin.sides], axis=1)


def workspace_quantities(workspace: CueingWorkspace, poses: np.ndarray) -> np.ndarray:
    """Every constrained quantity of the twin for stance poses (N, 6): sliders (12, m), base cones (12),
    platform cones (12), stance tilt (1, rad), inverse condition number of each robot (2; it falls to 0
    nearly linearly toward a singularity, where the condition number itself explodes), the smallest
    clearance between parts (1, m). NaN where a rod cannot reach its rail."""
    twin = workspace.twin
    # The IK's own collision check gives the clearance (exact up to the margin + IK_EXACT_BELOW_M, the
    # bound beyond): the same number the worker's check reads, at no second cost.
    solutions = twin_inverse_kinematics(twin, poses, check=False)
    sides = [solutions[side] for side in twin.sides]
    sliders = np.concatenate([s.slider_positions_m for s in sides], axis=1)
    reachable = np.all(np.isfinite(sliders), axis=1)
    conditions = np.full((len(poses), 2), np.nan)
    for index, (side, (positions, rotations)) in enumerate(twin_platform_poses(twin, poses).items()):
        robot_poses = np.concatenate([positions, euler_from_rotation(rotations)], axis=1)
        conditions[reachable, index] = _inverse_condition_number(twin.robot_for(side), robot_poses[reachable])
    tilt = np.arccos(np.clip(np.cos(poses[:, 3]) * np.cos(poses[:, 4]), -1.0, 1.0))
    columns = [
        sliders,
        np.concatenate([s.base_cone_rad for s in sides], axis=1),
        np.concatenate([s.platform_cone_rad for s in sides], axis=1),
        tilt[:, None],
        conditions,
    ]
    columns.append(_clearance(workspace, poses, sides[0].collisions)[:, None])
    quantities = np.concatenate(columns, axis=1)
    quantities[~reachable] = np.nan
    return quantities


def _clearance(workspace: CueingWorkspace, poses: np.ndarray, collisions: PoseCollisions | None) -> np.ndarray:
    """(N,) smallest clearance (m): the workspace's function, else the twin's parts as the IK reported them
    (exact wherever it can matter), else (a margin beyond the IK's exact range) computed exactly."""
    if workspace.clearance_m is not None:
        return np.asarray(workspace.clearance_m(poses), dtype=float)
    exact_up_to = workspace.twin.parts.clearance_min_m + IK_EXACT_BELOW_M
    if collisions is not None and workspace.minimum_clearance_m < exact_up_to:
        return np.asarray(collisions.clearance_m, dtype=float)
    return min_clearance(workspace.twin, poses).clearance_m


# --- The cubic B-spline ------------------------------------------------------------------------------


def _spline_operators(count: int, period: float) -> tuple[sp.csr_matrix, ...]:
    """Maps from control points to pose, velocity and acceleration at `count` consecutive knots k0 … and to
    jerk on the intervals [k, k + 1] that start there: each (count, count + 3) over c_{k0−1} … c_{k0+count+1}."""
    rows = np.arange(count)

    def banded(weights: list[float]) -> sp.csr_matrix:
        data = np.concatenate([np.full(count, w) for w in weights])
        cols = np.concatenate([rows + offset for offset in range(len(weights))])
        return sp.csr_matrix((data, (np.tile(rows, len(weights)), cols)), shape=(count, count + 3))

    return (
        banded([1 / 6, 4 / 6, 1 / 6]),
        banded([-0.5 / period, 0.0, 0.5 / period]),
        banded([1 / period**2, -2 / period**2, 1 / period**2]),
        banded([-1 / period**3, 3 / period**3, -3 / period**3, 1 / period**3]),
    )


def evaluate_spline(control_points: np.ndarray, knot_period_s: float, times_s: np.ndarray) -> np.ndarray:
    """Pose (N, 6) of the uniform cubic B-spline whose control point c_k (row k + 1) sits at knot k·T; beyond
    the last full interval the last cubic is continued (zero when its control points are)."""
    return _spline_pose_and_velocity(control_points, knot_period_s, times_s)[0]


def _spline_pose_and_velocity(
    control_points: np.ndarray, knot_period_s: float, times_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pose and its time derivative (N, 6) each, from the same cubic basis as `evaluate_spline`."""
    u = np.asarray(times_s, dtype=float) / knot_period_s
    knot = np.clip(np.floor(u).astype(int), 0, len(control_points) - 4)
    s = (u - knot)[:, None]
    weights = ((1 - s) ** 3 / 6, (3 * s**3 - 6 * s**2 + 4) / 6, (-3 * s**3 + 3 * s**2 + 3 * s + 1) / 6, s**3 / 6)
    slopes = (-((1 - s) ** 2) / 2, (3 * s**2 - 4 * s) / 2, (-3 * s**2 + 2 * s + 1) / 2, s**2 / 2)
    pose, velocity = np.zeros((len(u), 6)), np.zeros((len(u), 6))
    for offset, (weight, slope) in enumerate(zip(weights, slopes, strict=True)):
        pose += weight * control_points[knot + offset]
        velocity += slope * control_points[knot + offset] / knot_period_s
    return pose, velocity


# --- Perception as state space --------------------------------------------------------------------------


@dataclass(frozen=True)
class _StateSpace:
    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    d: np.ndarray

    @property
    def states(self) -> int:
        return self.a.shape[0]


def _perception_state_space(systems: list[control.TransferFunction], period: float) -> _StateSpace:
    """Block-diagonal discrete (Tustin) state space of one transfer function per axis."""
    import control  # here: it loads matplotlib and scipy.signal (core.vestibular)

    blocks = [control.sample_system(control.ss(system), period, method="tustin") for system in systems]
    return _StateSpace(
        a=np.asarray(sp.block_diag([b.A for b in blocks]).toarray()),
        b=np.asarray(sp.block_diag([b.B for b in blocks]).toarray()),
        c=np.asarray(sp.block_diag([b.C for b in blocks]).toarray()),
        d=np.asarray(sp.block_diag([b.D for b in blocks]).toarray()),
    )


def _advance(model: _StateSpace, state: np.ndarray, inputs: np.ndarray) -> np.ndarray:
    """The state after `inputs` (K, m), from `state`."""
    for value in inputs:
        state = model.a @ state + model.b @ value
    return state


def _simulate(model: _StateSpace, state: np.ndarray, inputs: np.ndarray) -> np.ndarray:
    """Outputs (K, p) for `inputs` (K, m) from `state`."""
    outputs = np.empty((len(inputs), model.c.shape[0]))
    for index, value in enumerate(inputs):
        outputs[index] = model.c @ state + model.d @ value
        state = model.a @ state + model.b @ value
    return outputs


# --- Linearisation -------------------------------------------------------------------------------------


def _force_and_rate(pose: np.ndarray, velocity: np.ndarray, acceleration: np.ndarray, head_m: float) -> np.ndarray:
    """(K, 6) each → head specific force and angular velocity (K, 6)."""
    force = head_specific_force(pose.T, velocity.T, acceleration.T, head_m).T
    return np.concatenate([force, head_angular_velocity(pose.T, velocity.T).T], axis=1)


def _perception_jacobians(
    pose: np.ndarray, velocity: np.ndarray, acceleration: np.ndarray, head_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Values (K, 6) and d(values)/d(pose, velocity, acceleration) (3, K, 6, 6), by central differences."""
    value = _force_and_rate(pose, velocity, acceleration, head_m)
    jacobians = np.zeros((3, len(pose), 6, 6))
    for which in range(3):
        for coordinate in range(6):
            args_plus = [pose.copy(), velocity.copy(), acceleration.copy()]
            args_minus = [pose.copy(), velocity.copy(), acceleration.copy()]
            args_plus[which][:, coordinate] += _FD_STEP
            args_minus[which][:, coordinate] -= _FD_STEP
            plus = _force_and_rate(args_plus[0], args_plus[1], args_plus[2], head_m)
            minus = _force_and_rate(args_minus[0], args_minus[1], args_minus[2], head_m)
            jacobians[which, :, :, coordinate] = (plus - minus) / (2 * _FD_STEP)
    return value, jacobians


def _workspace_jacobians(
    workspace: CueingWorkspace, pose: np.ndarray, velocity: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quantities (K, Q), d(quantities)/d(pose) (K, Q, 6) and the sliders' second derivative along the
    velocity (K, 12): s̈ = J p̈ + h, h = ṗᵀ (∂²s/∂p²) ṗ. One IK call over every perturbed pose."""
    count = len(pose)
    speed = np.max(np.abs(velocity), axis=1, keepdims=True)
    tau = np.where(speed > 1e-9, 1e-4 / np.maximum(speed, 1e-9), 0.0)
    perturbed = [pose] + [pose + _FD_STEP * np.eye(6)[j] for j in range(6)]
    values = workspace_quantities(workspace, np.concatenate(perturbed))
    base = values[:count]
    jacobian = np.stack([(values[(j + 1) * count : (j + 2) * count] - base) / _FD_STEP for j in range(6)], axis=-1)
    along = _twin_sliders(workspace.twin, np.concatenate([pose + tau * velocity, pose - tau * velocity]))
    forward, backward = along[:count], along[count:]
    second = np.divide(forward - 2.0 * base[:, :12] + backward, tau**2, out=np.zeros_like(forward), where=tau > 0.0)
    return base, jacobian, second


def _block_rows(blocks: np.ndarray) -> sp.csr_matrix:
    """Block-diagonal sparse matrix from blocks (K, r, c)."""
    count, rows, cols = blocks.shape
    row_index = (np.arange(count)[:, None, None] * rows + np.arange(rows)[None, :, None]).repeat(cols, axis=2)
    col_index = (np.arange(count)[:, None, None] * cols + np.arange(cols)[None, None, :]).repeat(rows, axis=1)
    return sp.csr_matrix((blocks.ravel(), (row_index.ravel(), col_index.ravel())), shape=(count * rows, count * cols))


# --- The plan --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class WindowReport:
    start_s: float
    knots: int
    iterations: int
    accepted_steps: int
    converged: bool
    qp_status: str
    cost: float


@dataclass(frozen=True)
class OptimalCueingPlan:
    """A planned segment: the stance trajectory at the control rate and how it was found."""

    sample_period_s: float
    pose: np.ndarray  # (N, 6) stance pose relative to neutral, m and rad
    control_points: np.ndarray  # (M + 3, 6) cubic B-spline control points c_{-1} … c_{M+1}
    knot_period_s: float
    windows: list[WindowReport] = field(default_factory=list)
    wall_s: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "samples": len(self.pose),
            "knot_period_s": self.knot_period_s,
            "windows": [vars(w) for w in self.windows],
            "wall_s": self.wall_s,
        }


class _Window:
    """One SQP over control points [first, last] with every other control point fixed."""

    def __init__(
        self,
        planner: OptimalCueingPlanner,
        control_points: np.ndarray,
        first: int,
        last: int,
        cue: np.ndarray,
        otolith_state: np.ndarray,
        canal_state: np.ndarray,
    ) -> None:
        self.p = planner
        self.c = control_points  # (M + 3, 6), row k + 1 holds c_k; edited in place
        self.first, self.last = first, last
        # Knots whose pose depends on a free control point: first − 1 … last + 1.
        self.knot0 = first - 1
        self.knots = last - first + 3
        self.cue = cue[self.knot0 : self.knot0 + self.knots]  # (K, 6) force and rate at the knots
        self.otolith_state, self.canal_state = otolith_state, canal_state
        period = planner.params.knot_period_s
        self.ops = _spline_operators(self.knots, period)
        self.free_columns = slice(2, 2 + (last - first + 1))  # c_first is the operators' third column
        self.free = last - first + 1
        # Rotation the starting iterate already has beyond the thresholds is tolerated (never made worse):
        # a step must not fail just because the window starts from a committed state.
        self.tolerated_rotation = self.uncued_rotation(control_points)

    def rows(self) -> slice:
        """Rows of `self.c` the operators' columns map to: c_{knot0 − 1} … c_{knot0 + knots}."""
        return slice(self.knot0, self.knot0 + self.knots + 3)

    def kinematics(self, control_points: np.ndarray) -> tuple[np.ndarray, ...]:
        local = control_points[self.rows()]
        return tuple(op @ local for op in self.ops)

    def exact_ok(self, control_points: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
        """Knots (K,) where every exact workspace quantity and slider rate is within the acceptance bounds."""
        pose, velocity, acceleration, _ = self.kinematics(control_points)
        quantities, jacobian, second = _workspace_jacobians(self.p.workspace, pose, velocity)
        thresholds = self.p.params.tilt_rate_thresholds_rad_s * self.p.acceptance_fraction
        # Between knots too: a zig-zag of control points would hide rotation from the knots.
        rotation_ok = np.all(
            self.uncued_rotation(control_points) <= np.maximum(thresholds, self.tolerated_rotation), axis=2
        )
        return self._within(quantities, jacobian, second, velocity, acceleration, low, high, 1.0) & np.all(
            rotation_ok, axis=1
        )

    def uncued_rotation(self, control_points: np.ndarray) -> np.ndarray:
        """|platform roll/pitch rate − cued rate| at 4 points per knot interval, (K, 4, 2)."""
        period = self.p.params.knot_period_s
        times = (self.knot0 + np.arange(self.knots * _ROTATION_SAMPLES) / _ROTATION_SAMPLES) * period
        pose, velocity = _spline_pose_and_velocity(control_points, period, times)
        rates = head_angular_velocity(pose.T, velocity.T).T[:, :2]
        knot_times = (self.knot0 + np.arange(self.knots)) * period
        cued = np.stack([np.interp(times, knot_times, self.cue[:, 3 + axis]) for axis in range(2)], axis=1)
        return np.abs(rates - cued).reshape(self.knots, _ROTATION_SAMPLES, 2)

    def _within(
        self,
        quantities: np.ndarray,
        jacobian: np.ndarray,
        second: np.ndarray,
        velocity: np.ndarray,
        acceleration: np.ndarray,
        low: np.ndarray,
        high: np.ndarray,
        slack: float,
    ) -> np.ndarray:
        limits = self.p.workspace.limits
        slider_velocity = np.einsum("kqj,kj->kq", jacobian[:, :12], velocity)
        slider_acceleration = np.einsum("kqj,kj->kq", jacobian[:, :12], acceleration) + second
        fraction = self.p.acceptance_fraction * slack
        finite = np.all(np.isfinite(quantities), axis=1)
        inside = np.all((quantities >= low) & (quantities <= high), axis=1, where=finite[:, None])
        return (
            finite
            & inside
            & np.all(np.abs(slider_velocity) <= fraction * limits.slider_velocity_max_m_s, axis=1)
            & np.all(np.abs(slider_acceleration) <= fraction * limits.slider_acceleration_max_m_s2, axis=1)
        )

    def exact_cost(self, control_points: np.ndarray) -> float:
        """The QP's objective with the exact (nonlinear) head force and rate: the SQP's merit function."""
        params, planner = self.p.params, self.p
        pose, velocity, acceleration, jerk = self.kinematics(control_points)
        error = _force_and_rate(pose, velocity, acceleration, params.head_height_m) - self.cue
        total = 0.0
        for model, state, inputs, thresholds, weight in (
            (planner.otolith, self.otolith_state, error[:, :3], planner.force_thresholds, params.specific_force_weight),
            (planner.canal, self.canal_state, error[:, 3:], planner.rate_thresholds, params.angular_velocity_weight),
        ):
            perceived = _simulate(model, state, inputs)
            total += weight * float(np.sum((perceived / thresholds) ** 2))
        usage = np.concatenate([pose[:, :3] / POSITION_SCALE_M, pose[:, 3:] / ANGLE_SCALE_RAD], axis=1) ** 2
        total += float(np.sum(usage * np.array([params.displacement_weight] * 3 + [params.angle_weight] * 3)))
        total += params.velocity_weight * float(np.sum((velocity / VELOCITY_SCALE) ** 2))
        total += params.jerk_weight * float(np.sum((jerk / JERK_SCALE) ** 2))
        return total / self.knots

    def _line_search(
        self,
        step: np.ndarray,
        cost: float,
        low: np.ndarray,
        high: np.ndarray,
        extra_rows: set[tuple[int, int]],
    ) -> tuple[float, float] | None:
        """Take the longest of step, step/2, step/4 that keeps every exact limit and lowers the exact cost.
        Knots a trial breaches join the next QP's rows. Returns (new cost, length) or None."""
        for length in (1.0, 0.5, 0.25):
            candidate = self.c.copy()
            candidate[self.first + 1 : self.last + 2] += length * step
            ok = self.exact_ok(candidate, low, high)
            if not np.all(ok):
                extra_rows.update((int(knot), -1) for knot in np.flatnonzero(~ok))
                continue
            candidate_cost = self.exact_cost(candidate)
            if candidate_cost <= cost * (1.0 + 1e-9):
                self.c[:] = candidate
                return candidate_cost, length
        return None

    def solve(self) -> WindowReport:
        """SQP with a trust region: a step is taken only if the exact functions keep every limit and the
        exact objective does not rise; otherwise the trust region halves (and breached knots join the QP)."""
        params = self.p.params
        plan_low, plan_high = self.p.plan_bounds
        accept_low, accept_high = self.p.accept_bounds
        accepted, status, converged = 0, "not run", False
        extra_rows: set[tuple[int, int]] = set()
        iterations = 0
        trust_scale = 1.0
        cost = self.exact_cost(self.c)
        for _ in range(params.sqp_iterations):
            iterations += 1
            pose, velocity, acceleration, jerk = self.kinematics(self.c)
            values, perception_jacobians = _perception_jacobians(pose, velocity, acceleration, params.head_height_m)
            quantities, q_jacobian, second = _workspace_jacobians(self.p.workspace, pose, velocity)
            step, status = self._qp_step(
                pose, velocity, acceleration, jerk, values, perception_jacobians,
                quantities, q_jacobian, second, plan_low, plan_high, extra_rows, trust_scale,
            )  # fmt: skip
            if step is None:
                trust_scale *= 0.5
                continue
            taken = self._line_search(step, cost, accept_low, accept_high, extra_rows)
            if taken is None:
                trust_scale *= 0.5
                continue
            previous_cost, (cost, length) = cost, taken
            accepted += 1
            if length == 1.0:
                trust_scale = min(1.0, 2.0 * trust_scale)
            small_gain = length == 1.0 and previous_cost - cost < params.cost_tolerance * previous_cost
            if small_gain or length * np.max(np.abs(step)) < params.step_tolerance:
                converged = True
                break
        return WindowReport(
            start_s=self.first * params.knot_period_s,
            knots=self.knots,
            iterations=iterations,
            accepted_steps=accepted,
            converged=converged,
            qp_status=status,
            cost=cost,
        )

    def _qp_step(
        self,
        pose: np.ndarray,
        velocity: np.ndarray,
        acceleration: np.ndarray,
        jerk: np.ndarray,
        values: np.ndarray,
        perception_jacobians: np.ndarray,
        quantities: np.ndarray,
        q_jacobian: np.ndarray,
        second: np.ndarray,
        low: np.ndarray,
        high: np.ndarray,
        extra_rows: set[tuple[int, int]],
        trust_scale: float,
    ) -> tuple[np.ndarray | None, str]:
        """One QP in the step Δc of the free control points; returns Δc (F, 6) or None."""
        params, planner = self.p.params, self.p
        count, free = self.knots, self.free
        oto, canal = planner.otolith, planner.canal
        n_c, n_o, n_w = 6 * free, oto.states * count, canal.states * count
        # Variable blocks: Δc, force error e_f (3K), otolith states (K·n), rate error e_w (3K), canal states.
        offsets = np.cumsum([0, n_c, 3 * count, n_o, 3 * count, n_w])
        total = int(offsets[-1])
        identity6 = sp.identity(6, format="csr")
        pose_op, velocity_op, acceleration_op, jerk_op = (
            sp.kron(op[:, self.free_columns], identity6, format="csr") for op in self.ops
        )
        # Linearised head force and rate: values + Σ J · (Δpose, Δvelocity, Δacceleration).
        sensitivity = sum(
            _block_rows(perception_jacobians[which]) @ op
            for which, op in enumerate((pose_op, velocity_op, acceleration_op))
        )
        force_rows = sp.csr_matrix(sensitivity)[np.ravel(np.arange(count)[:, None] * 6 + np.arange(3)), :]
        rate_rows = sp.csr_matrix(sensitivity)[np.ravel(np.arange(count)[:, None] * 6 + np.arange(3, 6)), :]
        error0 = values - self.cue  # (K, 6)

        def block(matrix: sp.spmatrix, start: int) -> sp.csr_matrix:
            """`matrix` placed at variable column `start` of a full-width row block."""
            matrix = sp.csr_matrix(matrix)
            left = sp.csr_matrix((matrix.shape[0], start))
            right = sp.csr_matrix((matrix.shape[0], total - start - matrix.shape[1]))
            return sp.hstack([left, matrix, right], format="csr")

        equality_rows, equality_values = [], []
        # e_f − J_f Δc = error0 (force); e_w − J_w Δc = error0 (rate).
        for rows, column, error in ((force_rows, offsets[1], error0[:, :3]), (rate_rows, offsets[3], error0[:, 3:])):
            equality_rows.append(block(-rows, 0) + block(sp.identity(3 * count), column))
            equality_values.append(error.ravel())
        # Perception dynamics x_{k+1} = A x_k + B e_k, x_0 given.
        for model, state_column, error_column, initial in (
            (oto, offsets[2], offsets[1], self.otolith_state),
            (canal, offsets[4], offsets[3], self.canal_state),
        ):
            n = model.states
            shift = sp.eye(count, count, k=-1, format="csr")
            dynamics = sp.identity(count * n) - sp.kron(shift, model.a)
            inputs = -sp.kron(shift, model.b)
            equality_rows.append(block(dynamics, state_column) + block(inputs, error_column))
            rhs = np.zeros(count * n)
            rhs[:n] = initial
            equality_values.append(rhs)

        # Cost: perceived errors y = C x + D e (normalised by the thresholds), usage and jerk.
        thresholds_f = np.asarray(planner.vestibular.specific_force_thresholds_m_s2)
        thresholds_w = np.asarray(planner.vestibular.angular_velocity_thresholds_rad_s)
        residuals: list[tuple[sp.csr_matrix, np.ndarray, float]] = []
        for model, state_column, error_column, thresholds, weight in (
            (oto, offsets[2], offsets[1], thresholds_f, params.specific_force_weight),
            (canal, offsets[4], offsets[3], thresholds_w, params.angular_velocity_weight),
        ):
            scale = sp.diags(np.tile(1.0 / thresholds, count))
            perceived = scale @ (
                block(sp.kron(sp.identity(count), model.c), state_column)
                + block(sp.kron(sp.identity(count), model.d), error_column)
            )
            residuals.append((perceived, np.zeros(3 * count), weight))
        usage_scale = np.tile([1 / POSITION_SCALE_M] * 3 + [1 / ANGLE_SCALE_RAD] * 3, count)
        usage_weight = np.tile([params.displacement_weight] * 3 + [params.angle_weight] * 3, count)
        residuals.append(
            (
                block(sp.diags(usage_scale * np.sqrt(usage_weight)) @ pose_op, 0),
                (pose.ravel() * usage_scale * np.sqrt(usage_weight)),
                1.0,
            )
        )
        residuals.append(
            (block(velocity_op / VELOCITY_SCALE, 0), velocity.ravel() / VELOCITY_SCALE, params.velocity_weight)
        )
        residuals.append((block(jerk_op / JERK_SCALE, 0), jerk.ravel() / JERK_SCALE, params.jerk_weight))
        hessian = sp.csr_matrix((total, total))
        linear = np.zeros(total)
        for matrix, constant, weight in residuals:
            if weight == 0.0:
                continue
            hessian = hessian + 2.0 * weight / count * (matrix.T @ matrix)
            linear += 2.0 * weight / count * (matrix.T @ constant)

        # Inequalities: trust region on Δc, the rotation the cue does not ask for, and the active workspace rows.
        inequality_rows, lows, highs = [], [], []
        radius = trust_scale * np.tile([params.trust_region_m] * 3 + [params.trust_region_rad] * 3, free)
        inequality_rows.append(block(sp.identity(n_c), 0))
        lows.append(-radius)
        highs.append(radius)
        # Uncued rotation: the Euler-rate curve is a quadratic B-spline over the control-point differences
        # (c_{k+1} − c_k)/T, so bounding those differences bounds the roll and pitch rates everywhere.
        local = self.c[self.rows()]
        differences = (local[1:] - local[:-1]) / params.knot_period_s  # (count + 2, 6)
        cue_rate = self.cue[np.clip(np.arange(count + 2) - 1, 0, count - 1), 3:5]
        cue_rate = 0.5 * (cue_rate + self.cue[np.clip(np.arange(count + 2), 0, count - 1), 3:5])
        difference_op = sp.csr_matrix(sp.eye(count + 2, count + 3, k=1) - sp.eye(count + 2, count + 3))
        rotation_op = sp.kron(difference_op[:, self.free_columns], sp.identity(6), format="csr") / params.knot_period_s
        rotation_rows = np.ravel(np.arange(count + 2)[:, None] * 6 + np.arange(3, 5))
        limit = np.tile(params.tilt_rate_thresholds_rad_s * params.limit_fraction, count + 2)
        current = (differences[:, 3:5] - cue_rate).ravel()
        inequality_rows.append(block(rotation_op[rotation_rows], 0))
        lows.append(np.minimum(-limit - current, 0.0))
        highs.append(np.maximum(limit - current, 0.0))
        self._workspace_rows(
            quantities, q_jacobian, second, velocity, acceleration, low, high,
            pose_op, velocity_op, acceleration_op, extra_rows, inequality_rows, lows, highs, block,
        )  # fmt: skip

        constraint_matrix = sp.vstack(equality_rows + inequality_rows, format="csc")
        equality = np.concatenate(equality_values)
        lower = np.concatenate([equality, *lows])
        upper = np.concatenate([equality, *highs])
        solver = osqp.OSQP()
        solver.setup(
            sp.triu(hessian + 1e-9 * sp.identity(total), format="csc"),
            linear,
            constraint_matrix,
            lower,
            upper,
            verbose=False,
            # Loose ADMM tolerances, then polishing: an exact solve on the active set ADMM found.
            eps_abs=1e-2,
            eps_rel=1e-2,
            max_iter=self.p.params.qp_iterations,
            polishing=True,
            rho=1.0,  # measured on the suite: converges where the default 0.1 stalls on these problems
        )
        if self.p.warm_start is not None and len(self.p.warm_start) == total:
            solver.warm_start(x=self.p.warm_start)
        result = solver.solve()
        status = str(result.info.status)
        # An inaccurate QP answer is still only a proposal: the SQP accepts it after the exact checks.
        if result.x is None or not np.all(np.isfinite(result.x)) or result.info.status_val not in _USABLE_QP_STATUS:
            return None, status
        self.p.warm_start = result.x
        return result.x[:n_c].reshape(free, 6), status

    def _workspace_rows(
        self,
        quantities: np.ndarray,
        q_jacobian: np.ndarray,
        second: np.ndarray,
        velocity: np.ndarray,
        acceleration: np.ndarray,
        low: np.ndarray,
        high: np.ndarray,
        pose_op: sp.csr_matrix,
        velocity_op: sp.csr_matrix,
        acceleration_op: sp.csr_matrix,
        extra_rows: set[tuple[int, int]],
        rows_out: list[sp.csr_matrix],
        lows: list[np.ndarray],
        highs: list[np.ndarray],
        block: Callable[[sp.spmatrix, int], sp.csr_matrix],
    ) -> None:
        """Linearised workspace rows for the knots and quantities near a limit (or breached by a rejected step).

        A row's bounds never exclude the current value, so the QP is always feasible (Δc = 0 satisfies it)."""
        limits = self.p.workspace.limits
        fraction = self.p.params.limit_fraction
        neutral = self.p.neutral_quantities
        forced_knots = {knot for knot, _ in extra_rows}
        span_high = np.where(np.isfinite(high), high - neutral, np.inf)
        span_low = np.where(np.isfinite(low), neutral - low, np.inf)
        use = np.maximum((quantities - neutral) / span_high, (neutral - quantities) / span_low)
        active = (use > self.p.activation_fraction) | self.p.always_active
        if forced_knots:
            active[sorted(forced_knots)] = True
        active &= np.isfinite(low) | np.isfinite(high)
        # A row whose quantity does not move with the pose (e.g. the clearance of sliders on parallel rails,
        # the default twin's closest pair) constrains nothing: left out, it does not burden the ADMM.
        active &= np.any(q_jacobian != 0.0, axis=2)
        knots, columns = np.nonzero(active)
        if knots.size:
            gradient = q_jacobian[knots, columns]  # (R, 6)
            matrix = sp.csr_matrix(
                (gradient.ravel(), (np.repeat(np.arange(len(knots)), 6), (knots[:, None] * 6 + np.arange(6)).ravel())),
                shape=(len(knots), 6 * self.knots),
            )
            value = quantities[knots, columns]
            rows_out.append(block(matrix @ pose_op, 0))
            lows.append(np.minimum(low[columns] - value, 0.0))
            highs.append(np.maximum(high[columns] - value, 0.0))
        # Slider velocity and acceleration: ṡ = J ṗ, s̈ = J p̈ + h.
        slider_jacobian = q_jacobian[:, :12]
        slider_velocity = np.einsum("kqj,kj->kq", slider_jacobian, velocity)
        slider_acceleration = np.einsum("kqj,kj->kq", slider_jacobian, acceleration) + second
        for rate_value, operator, limit in (
            (slider_velocity, velocity_op, limits.slider_velocity_max_m_s * fraction),
            (slider_acceleration, acceleration_op, limits.slider_acceleration_max_m_s2 * fraction),
        ):
            near = np.abs(rate_value) > self.p.activation_fraction * limit
            if forced_knots:
                near[sorted(forced_knots)] = True
            knots, legs = np.nonzero(near)
            if not knots.size:
                continue
            gradient = slider_jacobian[knots, legs]
            matrix = sp.csr_matrix(
                (gradient.ravel(), (np.repeat(np.arange(len(knots)), 6), (knots[:, None] * 6 + np.arange(6)).ravel())),
                shape=(len(knots), 6 * self.knots),
            )
            value = rate_value[knots, legs]
            rows_out.append(block(matrix @ operator, 0))
            lows.append(np.minimum(-limit - value, 0.0))
            highs.append(np.maximum(limit - value, 0.0))


class OptimalCueingPlanner:
    """Plans segments for one twin workspace with one parameter set (models built once)."""

    activation_fraction = 0.5  # workspace rows join the QP once a quantity uses half of its range
    acceptance_fraction = 0.97  # an SQP step is taken only if the exact functions keep within this of each limit

    def __init__(
        self,
        workspace: CueingWorkspace,
        params: OptimalCueingParameters | None = None,
        vestibular: VestibularParameters | None = None,
    ) -> None:
        self.workspace = workspace
        self.params = params or OptimalCueingParameters()
        period = self.params.knot_period_s
        self.vestibular = VestibularModel(vestibular, period)
        self.otolith = _perception_state_space(self.vestibular.otolith_systems, period)
        self.canal = _perception_state_space(self.vestibular.canal_systems, period)
        self.force_thresholds = self.vestibular.specific_force_thresholds_m_s2
        self.rate_thresholds = self.vestibular.angular_velocity_thresholds_rad_s
        self.neutral_quantities = workspace_quantities(workspace, np.zeros((1, 6)))[0]
        # The singularity margin is the least linear: its rows are always in the QP. Clearance rows join, like
        # the others, near their limit (on the default twin they never do, and idle rows slow the ADMM).
        self.always_active = np.isin(np.arange(len(self.neutral_quantities)), (37, 38))
        self.plan_bounds = workspace.quantity_bounds(self.params.limit_fraction)
        self.accept_bounds = workspace.quantity_bounds(self.acceptance_fraction)
        self.warm_start: np.ndarray | None = None

    def plan(
        self, specific_force_m_s2: np.ndarray, angular_velocity_rad_s: np.ndarray, sample_period_s: float
    ) -> OptimalCueingPlan:
        """The stance trajectory (N, 6) at `sample_period_s` for a cue (N, 3) ×2 that starts and ends at rest."""
        started = time.perf_counter()
        force = np.asarray(specific_force_m_s2, dtype=float)
        rates = np.asarray(angular_velocity_rad_s, dtype=float)
        for name, value in (("specific_force_m_s2", force), ("angular_velocity_rad_s", rates)):
            if value.ndim != 2 or value.shape[1] != 3:
                raise CueingError(name, list(value.shape), "shape must be (N, 3)")
            require_finite(name, value)
        if len(force) != len(rates):
            raise CueingError("angular_velocity_rad_s", len(rates), f"must have {len(force)} samples like the force")
        params = self.params
        period = params.knot_period_s
        count = len(force)
        # M knots: the curve is zero (at rest, neutral) from knot M on, and M·T is within the segment.
        knots = math.floor((count - 1) * sample_period_s / period + 1e-9)
        if knots < 4:
            raise CueingError("duration_s", (count - 1) * sample_period_s, f"must be at least {4 * period:g} s")
        cue = _cue_at_knots(force, rates, sample_period_s, period, knots + 1)
        # Rows hold c_{-1} … c_{M+2}; c_{-1..1} (start at rest) and c_{M−1..M+2} (end at rest) stay 0.
        control_points = np.zeros((knots + 4, 6))
        window = max(4, round(params.window_s / period))
        keep = max(4, round((params.window_s - params.overlap_s) / period))
        otolith_state, canal_state = np.zeros(self.otolith.states), np.zeros(self.canal.states)
        first, final_knot = 2, 0  # the perception states hold the inputs of knots 0 … final_knot − 1
        reports = []
        while first <= knots - 2:
            # Knots before first − 1 depend on committed control points only: advance the states over them.
            pose, velocity, acceleration, _ = _knot_kinematics(control_points, final_knot, first - 1, period)
            error = _force_and_rate(pose, velocity, acceleration, params.head_height_m) - cue[final_knot : first - 1]
            otolith_state = _advance(self.otolith, otolith_state, error[:, :3])
            canal_state = _advance(self.canal, canal_state, error[:, 3:])
            final_knot = first - 1
            last = min(first + window - 1, knots - 2)
            # Every window ends at rest at neutral (its control points beyond `last` are 0): if a later window
            # cannot improve, the committed trajectory plus this window's tail is still a feasible plan.
            control_points[last + 2 :] = 0.0
            self.warm_start = None
            reports.append(_Window(self, control_points, first, last, cue, otolith_state, canal_state).solve())
            first = last + 1 if last == knots - 2 else first + keep
        times = np.arange(count) * sample_period_s
        pose = evaluate_spline(control_points, period, times)
        return OptimalCueingPlan(
            sample_period_s=float(sample_period_s),
            pose=pose,
            control_points=control_points,
            knot_period_s=period,
            windows=reports,
            wall_s=time.perf_counter() - started,
        )


def _knot_kinematics(control_points: np.ndarray, start: int, stop: int, period: float) -> tuple[np.ndarray, ...]:
    """Pose, velocity, acceleration, jerk at knots start … stop − 1 (control point c_k in row k + 1)."""
    count = stop - start
    operators = _spline_operators(count, period)
    local = control_points[start : start + count + 3]
    return tuple(op @ local for op in operators)


def _cue_at_knots(force: np.ndarray, rates: np.ndarray, dt: float, period: float, knots: int) -> np.ndarray:
    """Force and rate (knots, 6) averaged over each knot's interval [kT − T/2, kT + T/2) (anti-aliasing)."""
    signal = np.concatenate([force, rates], axis=1)
    cumulative = np.concatenate([np.zeros((1, 6)), np.cumsum(signal, axis=0)])
    centre = np.arange(knots) * period / dt
    start = np.clip(np.round(centre - 0.5 * period / dt).astype(int), 0, len(signal))
    stop = np.clip(np.round(centre + 0.5 * period / dt).astype(int), 0, len(signal))
    width = np.maximum(stop - start, 1)[:, None]
    averaged = (cumulative[stop] - cumulative[start]) / width
    averaged[stop <= start] = 0.0
    return averaged
