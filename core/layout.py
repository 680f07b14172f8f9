"""Layout study of the twin (issue 13 §3): where the two robots stand decides what the patient can feel.

The paper's single-robot geometry is kept; the search varies the placement, symmetric about the world
Z axis (`core.robot.symmetric_placements`): the bases' offset across (y) and stagger along the rails
(x), their yaw, whether the left robot is the mirror image of the right or an identical copy, and the
stance width (each foot plate's offset from its platform centre follows, so that the feet stand side
by side). Rail heights are not a variable: both feet must stand at one height and the paper's IK table
fixes the platform 600 mm above its rails, so raising one robot's rails raises its foot.

Objectives, all from the product's own checks (IK with every limit, the singularity margin and the
clearance of `core.clearance`):

- the stance workspace of the axes balance training uses (surge x, sway y, roll, pitch): each axis's
  reach in both directions from neutral (the smaller of the two, since a clinical motion needs both
  signs), and a volume measure (the reachable share of a fixed 4-D box of those axes);
- the peak drive force in the paper's §3.2 scenarios (5 → 0.5 m/s² steps along +Y and +Z), with a 75 kg,
  1.75 m patient.

Constraints: feet 0.15–0.45 m apart centre to centre; no collision in the reported workspace (every
reported range and box sample is collision-free by construction: COLLISION makes a pose unreachable).
NSGA-II (pymoo) over a small population; the recommended layout maximises the smallest of the four
axes' reach relative to the default's, then the volume.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from pymoo.algorithms.moo.nsga2 import NSGA2
from pymoo.config import Config
from pymoo.core.problem import Problem
from pymoo.optimize import minimize

from core.clearance import min_clearance
from core.dynamics import PayloadModel, TwinInverseDynamics, paper_step_trajectory
from core.errors import InvalidValueError
from core.kinematics import UnreachablePoseError, twin_inverse_kinematics
from core.robot import (
    DEFAULT_BASE_OFFSET_Y_M,
    DEFAULT_FEET_APART_M,
    SSPRobot,
    TwinRobot,
    paper_robot,
    symmetric_placements,
)
from core.tuning import _Progress  # one pymoo progress callback: advance(1) per generation
from core.workspace import axis_ranges, stance_reachability

Config.warnings["not_compiled"] = False

CLINICAL_AXES = ("x", "y", "roll", "pitch")  # surge, sway, roll, pitch
_AXIS_INDEX = {"x": 0, "y": 1, "z": 2, "roll": 3, "pitch": 4, "yaw": 5}
# The 4-D box whose reachable share is the volume measure: ±200 mm surge and sway, ±15° roll and pitch.
VOLUME_BOX = np.array([0.2, 0.2, math.radians(15.0), math.radians(15.0)])
FEET_APART_RANGE_M = (0.15, 0.45)
FORCE_SCENARIOS = ("y", "z")  # paper §3.2
FORCE_DURATION_S, FORCE_PERIOD_S = 0.3, 0.002
UNREACHABLE_FORCE_N = 1e5  # a scenario the layout cannot play counts as this peak force

# Search bounds: (offset across, stagger along the rails, yaw, stance width, mirrored ∈ {0, 1}).
VARIABLE_NAMES = ("base_offset_y_m", "stagger_x_m", "base_yaw_rad", "feet_apart_m", "mirrored")
LOWER = np.array([0.3, 0.0, -math.radians(20.0), FEET_APART_RANGE_M[0], 0.0])
UPPER = np.array([1.2, 0.6, math.radians(20.0), FEET_APART_RANGE_M[1], 1.0])
STAGGER_MAX_M = UPPER[1]
# The foot plate's arm from its platform centre: longer is a structural problem (and loads the drives with
# the patient's moment); a stated assumption, not from the paper.
CANTILEVER_MAX_M = 0.75
# Every gap at neutral at least this wide: the sessions keep the clearance margin plus a 20 mm stop margin
# (25 mm) everywhere, and gaps that never change (sliders on neighbouring rails) need assembly tolerance.
NEUTRAL_CLEARANCE_MIN_M = 0.05


class LayoutSearchError(InvalidValueError):
    """An invalid layout-search setting."""


@dataclass(frozen=True)
class LayoutCandidate:
    base_offset_y_m: float
    stagger_x_m: float
    base_yaw_rad: float
    feet_apart_m: float
    mirrored: bool = True

    @classmethod
    def from_vector(cls, x: np.ndarray) -> LayoutCandidate:
        return cls(float(x[0]), float(x[1]), float(x[2]), float(x[3]), bool(round(float(x[4]))))

    def twin(self, robot: SSPRobot | None = None) -> TwinRobot:
        right, left = symmetric_placements(
            self.base_offset_y_m,
            self.stagger_x_m,
            self.feet_apart_m,
            base_yaw_rad=self.base_yaw_rad,
            mirrored=self.mirrored,
        )
        return TwinRobot(robot=robot or paper_robot(), right=right, left=left)

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["base_yaw_deg"] = math.degrees(self.base_yaw_rad)
        return data

    def vector(self) -> np.ndarray:
        return np.array(
            [self.base_offset_y_m, self.stagger_x_m, self.base_yaw_rad, self.feet_apart_m, float(self.mirrored)]
        )


DEFAULT_LAYOUT = LayoutCandidate(DEFAULT_BASE_OFFSET_Y_M, 0.0, 0.0, DEFAULT_FEET_APART_M, True)


@dataclass(frozen=True)
class LayoutMetrics:
    """What a layout gives the patient, in SI (m, rad, N)."""

    ranges: dict[str, tuple[float, float]]  # per stance axis (all six): reach from neutral, (min, max)
    limited_by: dict[str, tuple[str, str]]
    volume_fraction: float  # reachable share of VOLUME_BOX
    peak_force_n: float  # §3.2 scenarios
    neutral_clearance_m: float
    closest_parts: str
    feet_apart_m: float
    cantilever_m: float  # foot-plate offset from its platform centre

    def symmetric_reach(self, axis: str) -> float:
        low, high = self.ranges[axis]
        return max(0.0, min(-low, high))

    def to_dict(self) -> dict[str, Any]:
        def shown(axis: str, value: float) -> float:
            return value * 1e3 if axis in ("x", "y", "z") else math.degrees(value)

        return {
            "ranges": {
                axis: {
                    "min": shown(axis, low),
                    "max": shown(axis, high),
                    "unit": "mm" if axis in ("x", "y", "z") else "deg",
                    "limited_by": list(self.limited_by[axis]),
                }
                for axis, (low, high) in self.ranges.items()
            },
            "symmetric_reach": {axis: shown(axis, self.symmetric_reach(axis)) for axis in CLINICAL_AXES},
            "volume_fraction": self.volume_fraction,
            "volume_box": {"surge_sway_mm": VOLUME_BOX[0] * 1e3, "roll_pitch_deg": math.degrees(VOLUME_BOX[2])},
            "peak_force_n": self.peak_force_n,
            "neutral_clearance_mm": self.neutral_clearance_m * 1e3,
            "closest_parts": self.closest_parts,
            "feet_apart_mm": self.feet_apart_m * 1e3,
            "cantilever_mm": self.cantilever_m * 1e3,
        }


def feet_apart_m(twin: TwinRobot) -> float:
    from core.kinematics import foot_plate_neutral_world

    return float(np.linalg.norm(foot_plate_neutral_world(twin, "right") - foot_plate_neutral_world(twin, "left")))


def peak_scenario_force_n(twin: TwinRobot) -> float:
    payload = PayloadModel.from_body(75.0, 1.75)
    dynamics = TwinInverseDynamics(twin, payload)
    peak = 0.0
    for axis in FORCE_SCENARIOS:
        trajectory = paper_step_trajectory(axis, FORCE_DURATION_S, FORCE_PERIOD_S)
        try:
            twin_inverse_kinematics(twin, trajectory.poses)
        except UnreachablePoseError:
            return UNREACHABLE_FORCE_N
        forces = dynamics.slider_forces(trajectory.poses, trajectory.velocities, trajectory.accelerations)
        peak = max(peak, float(np.max(np.abs(forces))))
    return peak


def volume_samples(count: int, seed: int = 0) -> np.ndarray:
    """Seeded uniform stance offsets (count, 6) in VOLUME_BOX (other axes at neutral)."""
    offsets = np.zeros((count, 6))
    box = np.random.default_rng(seed).uniform(-1.0, 1.0, (count, 4)) * VOLUME_BOX
    offsets[:, [_AXIS_INDEX[a] for a in CLINICAL_AXES]] = box
    return offsets


def evaluate_layout(
    twin: TwinRobot, *, scan_points: int = 400, bisection_steps: int = 20, volume_sample_count: int = 2000
) -> LayoutMetrics | None:
    """The layout's metrics, or None when it collides (or breaks a limit) at neutral."""
    clearance = min_clearance(twin, np.zeros((1, 6)))
    reachability = stance_reachability(twin)
    if not reachability(np.zeros((1, 6)))[0][0]:
        return None
    ranges = axis_ranges(reachability, scan_points=scan_points, bisection_steps=bisection_steps)
    inside = reachability(volume_samples(volume_sample_count))[0]
    foot = np.asarray(twin.right.foot_plate_offset_m)
    return LayoutMetrics(
        ranges={r.axis: (r.minimum, r.maximum) for r in ranges},
        limited_by={r.axis: (r.limited_by_min, r.limited_by_max) for r in ranges},
        volume_fraction=float(np.mean(inside)),
        peak_force_n=peak_scenario_force_n(twin),
        neutral_clearance_m=float(clearance.clearance_m[0]),
        closest_parts=clearance.closest(0),
        feet_apart_m=feet_apart_m(twin),
        cantilever_m=float(np.hypot(foot[0], foot[1])),
    )


OBJECTIVE_NAMES = ("-surge_reach_m", "-sway_reach_m", "-roll_reach_rad", "-pitch_reach_rad", "-volume", "force_n")
# Workspace axes are scaled so that 1 is about the paper robot's reach (objectives of similar size).
_OBJECTIVE_SCALE = np.array([0.6, 0.15, math.radians(11.0), math.radians(15.0), 1.0, 1000.0])


def objectives_of(metrics: LayoutMetrics | None) -> np.ndarray:
    if metrics is None:  # collides or breaks a limit at neutral: worst in every objective
        return np.array([0.0, 0.0, 0.0, 0.0, 0.0, UNREACHABLE_FORCE_N]) / _OBJECTIVE_SCALE
    reach = [-metrics.symmetric_reach(axis) for axis in CLINICAL_AXES]
    return np.array([*reach, -metrics.volume_fraction, metrics.peak_force_n]) / _OBJECTIVE_SCALE


class LayoutProblem(Problem):
    """pymoo problem over `VARIABLE_NAMES`; constraints: every gap at neutral at least
    NEUTRAL_CLEARANCE_MIN_M, the foot plates within CANTILEVER_MAX_M of their platform centres.
    `stagger_max_m` = 0 keeps the layouts symmetric about the sagittal plane."""

    def __init__(
        self, robot: SSPRobot, evaluate: Callable[[TwinRobot], LayoutMetrics | None], stagger_max_m: float = 0.0
    ) -> None:
        upper = UPPER.copy()
        upper[1] = stagger_max_m
        super().__init__(n_var=len(VARIABLE_NAMES), n_obj=len(OBJECTIVE_NAMES), n_ieq_constr=2, xl=LOWER, xu=upper)
        self.robot = robot
        self._evaluate_layout = evaluate
        self.evaluated: list[tuple[LayoutCandidate, LayoutMetrics | None]] = []

    def _evaluate(self, x: np.ndarray, out: dict[str, Any], *args: Any, **kwargs: Any) -> None:
        objectives, constraints = [], []
        for row in np.atleast_2d(x):
            candidate = LayoutCandidate.from_vector(row)
            metrics = self._evaluate_layout(candidate.twin(self.robot))
            self.evaluated.append((candidate, metrics))
            objectives.append(objectives_of(metrics))
            if metrics is None:
                constraints.append([1.0, 1.0])
            else:
                constraints.append(
                    [
                        NEUTRAL_CLEARANCE_MIN_M - metrics.neutral_clearance_m,
                        metrics.cantilever_m - CANTILEVER_MAX_M,
                    ]
                )
        out["F"] = np.array(objectives)
        out["G"] = np.array(constraints)


@dataclass(frozen=True)
class LayoutResult:
    pareto: list[tuple[LayoutCandidate, LayoutMetrics]]
    recommended: int  # index into `pareto`
    reference: LayoutMetrics | None  # today's default layout
    reference_layout: LayoutCandidate | None
    evaluations: int
    wall_s: float
    seed: int
    population: int
    generations: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "pareto": [{"layout": c.to_dict(), "metrics": m.to_dict()} for c, m in self.pareto],
            "recommended": self.recommended,
            "reference": None
            if self.reference is None or self.reference_layout is None
            else {"layout": self.reference_layout.to_dict(), "metrics": self.reference.to_dict()},
            "evaluations": self.evaluations,
            "wall_s": self.wall_s,
            "seed": self.seed,
            "population": self.population,
            "generations": self.generations,
        }


def recommend(pareto: list[tuple[LayoutCandidate, LayoutMetrics]], reference: LayoutMetrics | None) -> int:
    """The layout whose worst clinical axis (reach relative to the reference, or to the objective scale)
    is best; ties by volume, then by the smaller peak force."""

    def key(item: tuple[LayoutCandidate, LayoutMetrics]) -> tuple[float, float, float]:
        metrics = item[1]
        scale = [
            (reference.symmetric_reach(axis) if reference is not None else 0.0) or _OBJECTIVE_SCALE[i]
            for i, axis in enumerate(CLINICAL_AXES)
        ]
        worst = min(metrics.symmetric_reach(axis) / s for axis, s in zip(CLINICAL_AXES, scale, strict=True))
        return (round(worst, 2), round(metrics.volume_fraction, 2), -metrics.peak_force_n)  # 1 % resolution

    return max(range(len(pareto)), key=lambda index: key(pareto[index]))


def layout_search(
    *,
    robot: SSPRobot | None = None,
    reference: LayoutCandidate | None = DEFAULT_LAYOUT,
    population: int = 24,
    generations: int = 8,
    seed: int = 1,
    stagger_max_m: float = 0.0,
    progress: Callable[[int], None] | None = None,
    evaluate: Callable[[TwinRobot], LayoutMetrics | None] = evaluate_layout,
) -> LayoutResult:
    """NSGA-II over the placement; returns the feasible Pareto set and the recommended layout. The first
    generation holds the `reference` layout (today's default), so that the set contains it or better."""
    for name, value in (("population", population), ("generations", generations)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 2:
            raise LayoutSearchError(name, value, "must be an integer >= 2")
    if not 0.0 <= stagger_max_m <= STAGGER_MAX_M:
        raise LayoutSearchError("stagger_max_m", stagger_max_m, f"must be in [0, {STAGGER_MAX_M:g}] m")
    robot = robot or paper_robot()
    problem = LayoutProblem(robot, evaluate, stagger_max_m)
    rng = np.random.default_rng(seed)
    first = problem.xl + rng.uniform(0.0, 1.0, (population, len(VARIABLE_NAMES))) * (problem.xu - problem.xl)
    if reference is not None:
        first[0] = np.clip(reference.vector(), problem.xl, problem.xu)
    started = time.perf_counter()
    result = minimize(
        problem,
        NSGA2(pop_size=population, sampling=first, eliminate_duplicates=True),
        ("n_gen", generations),
        seed=seed,
        callback=_Progress(progress or (lambda _steps: None)),
        verbose=False,
    )
    wall_s = time.perf_counter() - started
    front = np.atleast_2d(result.opt.get("X"))
    feasible = np.all(np.atleast_2d(result.opt.get("G")) <= 0.0, axis=1)
    pareto = []
    seen = set()
    for row in front[feasible]:
        candidate = LayoutCandidate.from_vector(row)
        metrics = next((m for c, m in problem.evaluated if c == candidate), None)
        if metrics is None or candidate in seen:
            continue
        seen.add(candidate)
        pareto.append((candidate, metrics))
    if not pareto:
        raise RuntimeError("the layout search found no collision-free layout; raise --population or --generations")
    pareto.sort(key=lambda item: (item[0].base_offset_y_m, item[0].stagger_x_m))
    reference_metrics = evaluate(reference.twin(robot)) if reference is not None else None
    return LayoutResult(
        pareto=pareto,
        recommended=recommend(pareto, reference_metrics),
        reference=reference_metrics,
        reference_layout=reference,
        evaluations=len(problem.evaluated),
        wall_s=wall_s,
        seed=seed,
        population=population,
        generations=generations,
    )
