"""Multi-objective tuning of the classical washout (paper §4.2, Formulas 16–19) with pymoo's NSGA-II,
the standard successor of the paper's MOGA.

Variables: [ω_a, ω_a′, ω_h] and optionally one damping ξ shared by Formulas 12 and 13 (the paper writes
one ξ). Objectives (both minimised, normalised as in `core.fidelity`): (1) perception error, (2) platform
motion. Constraints (≤ 0 is feasible): (1) rail stroke, the largest excursion of any slider of either
robot beyond its stroke, from the twin's inverse kinematics linearised about neutral (exact IK of 100
candidates × 750 samples costs more than the whole search; the chosen compromise is then checked with
the full IK and the result says whether it passed); (2) the tilt-rate limit, the peak rate of the
commanded tilt before the limiter minus the limit, so the tuned filter itself keeps the tilt
imperceptible and the limiter never distorts it; (3) tilt coordination switched on: the paper's sustained
0.2 g step must tilt at least `tilt_coordination_min_fraction` (default 0.5) of asin(0.2) within its 10 s
(issue 14 §4: on the square wave alone the optimum switched tilt coordination off, ω_h on its bound).
Input (issue 14 §4): a scenario suite (`tuning_suite`: the paper's square wave, its §5 step, a sway sine,
gait and perturbations, each followed by 5 s of rest so that a slow return to neutral is penalised), or
the paper's square wave alone (`tuning_input="paper-square-wave"`, Figure 15). Perception is judged at
the head. The whole population is one stacked design run through `core.washout.run_washout` at once;
its filters run in parallel over rows.

The compromise is the knee of the front (largest distance from the line through the two extremes,
objectives normalised to the front's range), chosen among the front's points that improve on the
baseline in both objectives when there are any.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from pymoo.algorithms.moo.nsga2 import NSGA2
from pymoo.config import Config
from pymoo.core.callback import Callback
from pymoo.core.problem import Problem
from pymoo.optimize import minimize

from core.cues import cue_from_spec
from core.fidelity import OBJECTIVE_NAMES, FidelityMetrics, FidelityScales, fidelity_of_signals
from core.kinematics import IKSolution, LegViolation, twin_inverse_kinematics
from core.perception import DEFAULT_HEAD_HEIGHT_M
from core.physics import GRAVITY_M_S2
from core.robot import TwinRobot, default_twin
from core.shaping import ParameterError, require_finite, require_positive
from core.vestibular import VestibularModel, VestibularParameters
from core.washout import WashoutParameters, WashoutSignals, backward_rate, baseline_parameters, design, run_washout

Config.warnings["not_compiled"] = False

TUNED_FREQUENCIES = ("translational_break_rad_s", "translational_first_order_break_rad_s", "tilt_break_rad_s")
SHARED_DAMPING = ("translational_damping", "tilt_damping")
# Widened (issue 14 §4): the paper-square-wave optimum sat on ω_a′ = 0.02 and ω_h = 0.05; `bounds_hit` still
# reports any optimum on a bound.
DEFAULT_BOUNDS: dict[str, tuple[float, float]] = {
    "translational_break_rad_s": (0.05, 10.0),
    "translational_first_order_break_rad_s": (0.001, 5.0),
    "tilt_break_rad_s": (0.005, 10.0),
    "damping": (0.3, 3.0),
}
CONSTRAINT_NAMES = ("stroke_excess_m", "tilt_rate_excess_rad_s", "tilt_coordination_shortfall")
INPUTS = ("suite", "paper-square-wave")
BOUND_TOLERANCE_FRACTION = 0.01  # of the bound's range in log scale: an optimum this close to a bound "sits on" it
# Tilt coordination counts as switched off when the paper's sustained 0.2 g step (held 10 s) tilts less
# than this fraction of asin(0.2): the sustained cue is then carried by nothing (issue 14 §4).
TILT_COORDINATION_OFF_FRACTION = 0.5
TILT_PROBE_FORCE_G, TILT_PROBE_HOLD_S, TILT_PROBE_SAMPLE_PERIOD_S = 0.2, 10.0, 0.01


def paper_square_wave(
    sample_period_s: float,
    *,
    amplitude_m_s2: float = 2.0,
    period_s: float = 2.0,
    duration_s: float = 10.0,
    rest_s: float = 5.0,
    axis: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """The paper's tuning input (Figure 14): specific force (N, 3) and zero angular velocity (N, 3)."""
    for name, value in (("sample_period_s", sample_period_s), ("period_s", period_s), ("duration_s", duration_s)):
        require_positive(name, value)
    time_s = np.arange(round((duration_s + rest_s) / sample_period_s)) * sample_period_s
    phase = np.floor(2.0 * time_s / period_s + 1e-9)  # half-periods; the epsilon keeps exact edges on the grid
    wave = np.where(phase % 2 == 0, amplitude_m_s2, -amplitude_m_s2)
    force = np.zeros((len(time_s), 3))
    force[:, axis] = np.where(time_s < duration_s - 1e-12, wave, 0.0)
    return force, np.zeros_like(force)


def tuning_suite(sample_period_s: float, rest_s: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """The scenario suite the washout is tuned on, one after the other with `rest_s` of rest after each:
    the paper's square wave (§4.2), its sustained lateral step (§5: 0.2 g for 10 s), a lateral sway sine,
    a gait cue and seeded perturbation pulses. Specific force and angular velocity (N, 3) each."""
    specs: list[tuple[dict[str, Any], float]] = [
        ({"kind": "square_wave", "axis": "x", "amplitude_m_s2": 2.0, "period_s": 2.0}, 10.0),
        ({"kind": "step", "axis": "y", "final_m_s2": TILT_PROBE_FORCE_G * GRAVITY_M_S2}, 10.0),
        ({"kind": "sine", "axis": "y", "amplitude_m_s2": 0.5, "frequency_hz": 0.25}, 12.0),
        ({"kind": "gait", "cadence_steps_per_min": 100.0, "vertical_amplitude_m_s2": 0.6,
          "forward_amplitude_m_s2": 0.4, "lateral_amplitude_m_s2": 0.3}, 10.0),
        ({"kind": "perturbations", "translation_m_s2": 1.5, "tilt_rate_rad_s": 0.1, "first_onset_s": 1.0}, 12.0),
    ]  # fmt: skip
    forces, rates = [], []
    rest = np.zeros((round(rest_s / sample_period_s), 3))
    for seed, (spec, duration_s) in enumerate(specs):
        force, angular = cue_from_spec(spec, sample_period_s, seed).generate(duration_s)
        forces += [force, rest]
        rates += [angular, rest]
    return np.concatenate(forces), np.concatenate(rates)


class WashoutTuningProblem(Problem):
    """The paper's two objectives and three constraints over a whole population per call."""

    def __init__(
        self,
        *,
        baseline: WashoutParameters | None = None,
        twin: TwinRobot | None = None,
        sample_period_s: float = 0.02,
        tune_damping: bool = False,
        vestibular: VestibularParameters | None = None,
        scales: FidelityScales | None = None,
        bounds: dict[str, tuple[float, float]] | None = None,
        head_height_m: float = DEFAULT_HEAD_HEIGHT_M,
        tuning_input: str = "suite",
        tilt_coordination_min_fraction: float = TILT_COORDINATION_OFF_FRACTION,
    ) -> None:
        if tuning_input not in INPUTS:
            raise ParameterError("tuning_input", tuning_input, f"must be one of {list(INPUTS)}")
        require_finite("tilt_coordination_min_fraction", tilt_coordination_min_fraction)
        # 0 disables the constraint (the paper's problem); the default keeps tilt coordination switched on.
        self.tilt_coordination_min_fraction = float(tilt_coordination_min_fraction)
        self.tuning_input = tuning_input
        self.head_height_m = float(head_height_m)  # perception is judged at the head (core.perception)
        self.baseline = baseline or baseline_parameters()
        self.twin = twin or default_twin()
        self.sample_period_s = float(sample_period_s)
        self.tune_damping = tune_damping
        self.variable_names = (*TUNED_FREQUENCIES, "damping") if tune_damping else TUNED_FREQUENCIES
        limits = {**DEFAULT_BOUNDS, **(bounds or {})}
        require_positive("sample_period_s", self.sample_period_s)
        # The discretised filters exist only below a tenth of Nyquist (`core.washout.design`): a break
        # frequency bound above that is refused here, not by the first generation that samples it.
        frequency_cap = 0.1 * math.pi / self.sample_period_s
        self.frequency_cap_rad_s = frequency_cap
        for name in self.variable_names:
            low, high = limits[name]
            require_positive(f"bounds.{name}", [low, high])
            if not low < high:
                raise ParameterError(f"bounds.{name}", [low, high], "lower bound must be < upper bound")
            if name in TUNED_FREQUENCIES and high >= frequency_cap:
                raise ParameterError(
                    f"bounds.{name}",
                    [low, high],
                    f"upper bound must be below a tenth of Nyquist, {frequency_cap:.4g} rad/s at sample_period_s "
                    f"{self.sample_period_s:g} s (a smaller sample period allows more)",
                )
        self.vestibular = VestibularModel(vestibular, self.sample_period_s)
        self.scales = scales or FidelityScales()
        make_input = tuning_suite if tuning_input == "suite" else paper_square_wave
        self.specific_force, self.angular_velocity = make_input(self.sample_period_s)
        # The tilt probe runs at least as finely as the suite, so it accepts every break frequency the suite does.
        self._probe_period_s = min(TILT_PROBE_SAMPLE_PERIOD_S, self.sample_period_s)
        probe = np.zeros((round(TILT_PROBE_HOLD_S / self._probe_period_s), 3))
        probe[:, 1] = TILT_PROBE_FORCE_G * GRAVITY_M_S2
        self._tilt_probe = probe
        self._neutral_sliders_m, self._stroke_jacobian = _linearised_twin_ik(self.twin)
        robots = [self.twin.robot_for(side) for side in self.twin.sides]
        self._stroke_min_m = np.concatenate([robot.stroke_min_m for robot in robots])
        self._stroke_max_m = np.concatenate([robot.stroke_max_m for robot in robots])
        super().__init__(
            n_var=len(self.variable_names),
            n_obj=len(OBJECTIVE_NAMES),
            n_ieq_constr=len(CONSTRAINT_NAMES),
            xl=np.array([limits[n][0] for n in self.variable_names]),
            xu=np.array([limits[n][1] for n in self.variable_names]),
        )

    def variables_of(self, params: WashoutParameters) -> np.ndarray:
        values = [getattr(params, name) for name in TUNED_FREQUENCIES]
        return np.array([*values, params.translational_damping] if self.tune_damping else values)

    def parameters(self, x: np.ndarray) -> list[WashoutParameters]:
        """One validated parameter set per row of x (P, n_var)."""
        result = []
        for row in np.atleast_2d(x):
            changes: dict[str, Any] = dict(zip(TUNED_FREQUENCIES, map(float, row[:3]), strict=True))
            if self.tune_damping:
                changes.update(dict.fromkeys(SHARED_DAMPING, float(row[3])))
            result.append(replace(self.baseline, **changes))
        return result

    def run(self, x: np.ndarray) -> tuple[WashoutSignals, FidelityMetrics]:
        """Washout and metrics of the whole population, stacked (P, ..., N)."""
        stacked = design(self.parameters(x), self.sample_period_s)
        signals = run_washout(stacked, self.specific_force.T, self.angular_velocity.T)
        metrics = fidelity_of_signals(
            signals.pose,
            signals.velocity,
            signals.acceleration,
            self.specific_force.T,
            self.angular_velocity.T,
            self.vestibular,
            self.scales,
            self.head_height_m,
        )
        return signals, metrics

    def objectives_and_constraints(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        signals, metrics = self.run(x)
        objectives = np.stack([getattr(metrics, name) for name in OBJECTIVE_NAMES], axis=-1)
        constraints = np.stack(
            [self._stroke_excess_m(signals.pose), self._tilt_rate_excess(signals), self._tilt_shortfall(x)], axis=-1
        )
        return objectives, constraints

    def _tilt_shortfall(self, x: np.ndarray) -> np.ndarray:
        """Required tilt-coordination fraction minus the one each candidate reaches (≤ 0 is feasible)."""
        stacked = design(self.parameters(x), self._probe_period_s)
        signals = run_washout(stacked, self._tilt_probe.T, np.zeros_like(self._tilt_probe).T)
        fraction = signals.tilt[:, 0, -1] / np.arcsin(TILT_PROBE_FORCE_G)
        return self.tilt_coordination_min_fraction - fraction

    def _evaluate(self, x: np.ndarray, out: dict[str, Any], *args: Any, **kwargs: Any) -> None:
        out["F"], out["G"] = self.objectives_and_constraints(x)

    def _stroke_excess_m(self, poses: np.ndarray) -> np.ndarray:
        """Linearised twin IK about neutral: slider excursion beyond the stroke, (P,) m."""
        sliders = self._neutral_sliders_m[:, None] + np.einsum("jk,pkn->pjn", self._stroke_jacobian, poses)
        beyond = np.maximum(self._stroke_min_m[:, None] - sliders, sliders - self._stroke_max_m[:, None])
        return np.max(beyond, axis=(-2, -1))

    def exact_limit_check(self, params: WashoutParameters) -> tuple[bool, bool]:
        """Full twin IK over the whole run: (within stroke and rod reach, within every IK limit)."""
        signals, _ = self.run(self.variables_of(params)[None, :])
        solutions = twin_inverse_kinematics(self.twin, signals.pose[0].T, check=False)
        return within_stroke(solutions), all(bool(np.all(solution.reachable)) for solution in solutions.values())

    def _tilt_rate_excess(self, signals: WashoutSignals) -> np.ndarray:
        rate = backward_rate(signals.tilt_command, self.sample_period_s)
        return np.max(np.abs(rate), axis=(-2, -1)) - self.baseline.tilt_rate_limit_rad_s


# Why an optimum would sit on each bound: what moving that break frequency (or ξ) does to the washout.
BOUND_REASONS: dict[tuple[str, str], str] = {
    ("translational_break_rad_s", "upper"): (
        "ω_a is the break of the translational high-pass (Formula 12): a higher ω_a washes the translation out "
        "sooner, so less stroke and platform motion and less of each onset delivered. On the upper bound the "
        "knee asks for as little translation as the bound allows."
    ),
    ("translational_break_rad_s", "lower"): (
        "a lower ω_a keeps translating longer: more stroke and platform motion (the stroke constraint binds)."
    ),
    ("translational_first_order_break_rad_s", "upper"): (
        "ω_a′ is the extra first-order high-pass of Formula 12: a higher ω_a′ also washes the translation out "
        "sooner (less drift after a sustained cue, less platform motion). On the upper bound the knee asks for "
        "as little translation as the bound allows."
    ),
    ("translational_first_order_break_rad_s", "lower"): (
        "a lower ω_a′ lets the platform drift after a sustained cue: more stroke and platform motion."
    ),
    ("tilt_break_rad_s", "upper"): (
        "ω_h is the tilt low-pass of Formula 13: a higher ω_h tilts sooner and faster (the tilt-rate constraint binds)."
    ),
    ("tilt_break_rad_s", "lower"): (
        "a lower ω_h tilts later and less within a cue: tilt coordination fades (its constraint binds)."
    ),
    ("damping", "upper"): "a higher ξ slows both channels' responses: less overshoot, slower cues.",
    ("damping", "lower"): "a lower ξ gives faster responses with overshoot (more motion, a wrong-sign rebound).",
}
BEYOND_BOUND_FACTOR = 2.0  # how far past a bound `bounds_hit` looks: × 2 beyond an upper, ÷ 2 below a lower


def bounds_hit(problem: WashoutTuningProblem, params: WashoutParameters) -> dict[str, dict[str, Any]]:
    """The tuned variables of `params` that sit on a bound of `problem` (within 1 % of its log range), each with
    its side, the bound, its value, why a bound of that side binds (`BOUND_REASONS`), and the objectives and
    feasibility with only that variable moved `BEYOND_BOUND_FACTOR` past the bound: whether widening it
    would trade one objective for the other (the bound shapes the knee) or change nothing (it does not)."""
    x = problem.variables_of(params)
    objectives, _ = problem.objectives_and_constraints(x[None, :])
    at_knee = dict(zip(OBJECTIVE_NAMES, map(float, objectives[0]), strict=True))
    hits: dict[str, dict[str, Any]] = {}
    for index, name in enumerate(problem.variable_names):
        low, high = float(problem.xl[index]), float(problem.xu[index])
        # In decades: the widened bounds span 3–4 of them, where 1 % of the linear range would call ω_h =
        # 0.37 rad/s "on" a lower bound of 0.005 rad/s.
        tolerance = BOUND_TOLERANCE_FRACTION * math.log(high / low)
        if math.log(x[index] / low) <= tolerance:
            side, bound, past = "lower", low, low / BEYOND_BOUND_FACTOR
        elif math.log(high / x[index]) <= tolerance:
            side, bound, past = "upper", high, high * BEYOND_BOUND_FACTOR
        else:
            continue
        hit: dict[str, Any] = {"side": side, "bound": bound, "value": float(x[index])}
        hit["why"] = BOUND_REASONS[(name, side)]
        hit["at_knee"] = at_knee
        if name in TUNED_FREQUENCIES and past >= problem.frequency_cap_rad_s:
            past = 0.999 * problem.frequency_cap_rad_s  # the discretised filter's limit (a tenth of Nyquist)
        if past <= bound and side == "upper":
            hit["beyond_bound"] = None
            hit["why"] += (
                f" The bound is at the limit of the filters at sample_period_s {problem.sample_period_s:g} s "
                f"({problem.frequency_cap_rad_s:.4g} rad/s): a smaller sample period is needed to look beyond."
            )
        else:
            moved = x.copy()
            moved[index] = past
            beyond_f, beyond_g = problem.objectives_and_constraints(moved[None, :])
            hit["beyond_bound"] = {
                "value": past,
                **dict(zip(OBJECTIVE_NAMES, map(float, beyond_f[0]), strict=True)),
                "constraints": dict(zip(CONSTRAINT_NAMES, map(float, beyond_g[0]), strict=True)),
                "feasible": bool(np.all(beyond_g[0] <= 0.0)),
            }
            hit["verdict"] = _bound_verdict(objectives[0], beyond_f[0], beyond_g[0], side)
        hits[name] = hit
    return hits


SATURATED_FRACTION = 0.005  # beyond the bound both objectives change by less than this: the bound does not matter


def _bound_verdict(at_knee: np.ndarray, beyond: np.ndarray, constraints: np.ndarray, side: str) -> str:
    """What moving past the bound does: a constraint takes over, both objectives improve (widen it), they
    saturate (the optimum is the limit 0 or ∞), or one improves as the other worsens (a trade)."""
    if np.any(constraints > 0.0):
        broken = ", ".join(name for name, value in zip(CONSTRAINT_NAMES, constraints, strict=True) if value > 0.0)
        return f"infeasible beyond the bound ({broken}): that constraint, not the bound, limits the optimum"
    change = (beyond - at_knee) / np.abs(at_knee)
    if np.all(np.abs(change) < SATURATED_FRACTION):
        limit = "∞" if side == "upper" else "0"
        return (
            f"saturated: beyond the bound both objectives change by less than {100 * SATURATED_FRACTION:g} % "
            f"({100 * change[0]:+.2f} %, {100 * change[1]:+.2f} %); the optimum is the limit {limit}, where the "
            "channel no longer acts, so no finite bound keeps it inside"
        )
    if np.all(change < 0.0):
        return (
            f"both objectives improve beyond the bound ({100 * change[0]:+.2f} %, {100 * change[1]:+.2f} %): widen it"
        )
    return (
        f"a trade beyond the bound ({100 * change[0]:+.2f} %, {100 * change[1]:+.2f} %): the knee of a wider "
        "front may lie beyond it"
    )


def tilt_coordination_fraction(params: WashoutParameters, sample_period_s: float = TILT_PROBE_SAMPLE_PERIOD_S) -> float:
    """Tilt reached at the end of the paper's sustained step (0.2 g along y, held 10 s), over asin(0.2)."""
    dt = sample_period_s
    force = np.zeros((round(TILT_PROBE_HOLD_S / dt), 3))
    force[:, 1] = TILT_PROBE_FORCE_G * GRAVITY_M_S2
    signals = run_washout(design(params, dt), force.T, np.zeros_like(force).T)
    return float(signals.tilt[0, -1] / np.arcsin(TILT_PROBE_FORCE_G))


def within_stroke(solutions: dict[str, IKSolution]) -> bool:
    """No slider leaves its stroke and every rod reaches its rail (cones and conditioning not included)."""
    flags = LegViolation.STROKE | LegViolation.ROD_CANNOT_REACH
    return all(not np.any(solution.violations & flags) for solution in solutions.values())


def _linearised_twin_ik(twin: TwinRobot, step: float = 1e-5) -> tuple[np.ndarray, np.ndarray]:
    """Twin slider positions (12,) at neutral and d(sliders)/d(stance pose) (12, 6) by central differences."""

    def sliders(poses: np.ndarray) -> np.ndarray:
        solutions = twin_inverse_kinematics(twin, poses)
        return np.concatenate([solutions[side].slider_positions_m for side in twin.sides], axis=1)

    offsets = np.concatenate([np.eye(6), -np.eye(6)]) * step
    moved = sliders(offsets)
    return sliders(np.zeros((1, 6)))[0], ((moved[:6] - moved[6:]) / (2.0 * step)).T


def knee_index(objectives: np.ndarray) -> int:
    """Index of the knee of a two-objective front: farthest from the line through its extremes."""
    objectives = np.asarray(objectives, dtype=float)
    if len(objectives) <= 2:
        return int(np.argmin(objectives.sum(axis=1)))
    span = np.ptp(objectives, axis=0)
    normal = (objectives - objectives.min(axis=0)) / np.where(span > 0, span, 1.0)
    first, second = normal[np.argmin(normal[:, 0])], normal[np.argmin(normal[:, 1])]
    direction = second - first
    length = np.hypot(*direction)
    if length == 0.0:
        return int(np.argmin(normal.sum(axis=1)))
    distance = np.abs(direction[0] * (normal[:, 1] - first[1]) - direction[1] * (normal[:, 0] - first[0])) / length
    return int(np.argmax(distance))


@dataclass(frozen=True)
class TuningResult:
    baseline: WashoutParameters
    baseline_objectives: dict[str, float]
    optimized: WashoutParameters
    optimized_objectives: dict[str, float]
    improves_on_baseline: bool  # the compromise is better than the baseline in both objectives
    optimized_within_stroke: bool  # full twin IK of the compromise: in stroke, every rod reaches its rail
    optimized_reachable: bool  # ... and within every other IK limit too (joint cones, conditioning)
    bounds_hit: dict[str, dict[str, Any]]  # tuned variables of the compromise on a bound, and why (`bounds_hit`)
    tilt_coordination_fraction: float  # sustained-step tilt over asin(f/g) (`tilt_coordination_fraction`)
    pareto_parameters: list[WashoutParameters]
    pareto_objectives: np.ndarray  # (M, 2)
    wall_s: float
    seed: int
    generations: int
    population: int

    @property
    def tilt_coordination_off(self) -> bool:
        return self.tilt_coordination_fraction < TILT_COORDINATION_OFF_FRACTION

    def to_dict(self) -> dict[str, Any]:
        def summary(objectives: dict[str, float], params: WashoutParameters) -> dict[str, Any]:
            return {**objectives, "params": params.to_dict()}

        return {
            "baseline": summary(self.baseline_objectives, self.baseline),
            "optimized": summary(self.optimized_objectives, self.optimized),
            "improves_on_baseline": self.improves_on_baseline,
            "optimized_within_stroke": self.optimized_within_stroke,
            "optimized_reachable": self.optimized_reachable,
            "bounds_hit": self.bounds_hit,
            "tilt_coordination_fraction": self.tilt_coordination_fraction,
            "tilt_coordination_off": self.tilt_coordination_off,
            "pareto_size": len(self.pareto_parameters),
            "pareto_front": self.pareto_objectives.tolist(),
            "wall_s": self.wall_s,
            "seed": self.seed,
            "generations": self.generations,
            "population": self.population,
        }


class _Progress(Callback):
    def __init__(self, advance: Callable[[int], None]) -> None:
        super().__init__()
        self._advance = advance

    def notify(self, algorithm: Any) -> None:
        self._advance(1)


def tune(
    *,
    seed: int = 1,
    generations: int = 100,
    population: int = 100,
    problem: WashoutTuningProblem | None = None,
    progress: Callable[[int], None] | None = None,
) -> TuningResult:
    """Run NSGA-II on `problem` (default: the paper's) and pick the knee of the feasible front."""
    for name, value in (("generations", generations), ("population", population)):
        if not isinstance(value, int) or value < 1:
            raise ParameterError(name, value, "must be an integer >= 1")
    problem = problem or WashoutTuningProblem()
    started = time.perf_counter()
    result = minimize(
        problem,
        NSGA2(pop_size=population, eliminate_duplicates=True),
        ("n_gen", generations),
        seed=seed,
        callback=_Progress(progress or (lambda _steps: None)),
        verbose=False,
    )
    wall_s = time.perf_counter() - started
    if result.opt is None:
        raise RuntimeError(
            "NSGA-II found no feasible washout parameters (stroke, tilt-rate or tilt-coordination constraint); "
            "try more generations or a larger population"
        )
    front_x = np.atleast_2d(result.opt.get("X"))
    front_f = np.atleast_2d(result.opt.get("F"))
    feasible = np.all(np.atleast_2d(result.opt.get("G")) <= 0.0, axis=1)
    if not np.any(feasible):
        raise RuntimeError("NSGA-II found no feasible washout parameters (stroke or tilt-rate constraint)")
    front_x, front_f = front_x[feasible], front_f[feasible]
    order = np.argsort(front_f[:, 0])
    front_x, front_f = front_x[order], front_f[order]

    baseline_f, _ = problem.objectives_and_constraints(problem.variables_of(problem.baseline)[None, :])
    better = np.all(front_f < baseline_f[0], axis=1)
    candidates = np.flatnonzero(better) if np.any(better) else np.arange(len(front_f))
    chosen = int(candidates[knee_index(front_f[candidates])])
    optimized = problem.parameters(front_x[chosen])[0]
    in_stroke, reachable = problem.exact_limit_check(optimized)
    return TuningResult(
        baseline=problem.baseline,
        baseline_objectives=dict(zip(OBJECTIVE_NAMES, map(float, baseline_f[0]), strict=True)),
        optimized=optimized,
        optimized_objectives=dict(zip(OBJECTIVE_NAMES, map(float, front_f[chosen]), strict=True)),
        improves_on_baseline=bool(better[chosen]),
        optimized_within_stroke=in_stroke,
        optimized_reachable=reachable,
        bounds_hit=bounds_hit(problem, optimized),
        tilt_coordination_fraction=tilt_coordination_fraction(optimized, problem._probe_period_s),
        pareto_parameters=problem.parameters(front_x),
        pareto_objectives=front_f,
        wall_s=wall_s,
        seed=seed,
        generations=generations,
        population=population,
    )
