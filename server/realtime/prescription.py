"""Prescriptions: parse and validate them, and check them offline through the batch pipeline.

A prescription is a JSON-able dict `{"segments": [{"cue", "duration_s", "washout"?, "shaping"?,
"limits"?}], "seed"?, "cueing"?}`. With `"cueing": "classical"` (the default) the worker plays each
segment as: cue × gain (soft start, full, fade out) → washout → command shaping → stance pose; with
`"optimal"` the stance trajectory of each segment is planned here, at load time, from the whole cue
(`core.optimal_cueing`), and the worker plays it. Either way a quintic return to neutral (`ramps`)
follows. Before any motion, `check_prescription` runs exactly that timeline through the batch front
ends (`washout_batch`, `shape_batch`, `twin_inverse_kinematics`, `TwinInverseDynamics`) and refuses the
prescription at the first sample that breaks a limit, naming the segment, the time in it, the limit and the value.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from core.cues import CueSpecError, cue_from_spec
from core.dynamics import PayloadModel, TwinInverseDynamics
from core.errors import InvalidValueError
from core.falls import FallDetectorConfig
from core.kinematics import LegViolation, twin_inverse_kinematics, twin_singularity_report, violation_stretches
from core.optimal_cueing import CueingWorkspace, OptimalCueingParameters, OptimalCueingPlanner
from core.patient import PatientParameters
from core.perception import head_height_m
from core.robot import TwinRobot
from core.shaping import CommandShaper, ShapingParameters
from core.washout import WashoutParameters, paper_tilt_parameters, washout_batch
from server.realtime.limits import LimitOverrideError, SessionLimits
from server.realtime.loop import DEFAULT_CONTROL_RATE_HZ, validate_control_rate
from server.realtime.ramps import PoseRamp, cue_gains, return_duration_s, start_velocity
from server.realtime.supervisor import SupervisorConfig
from server.realtime.telemetry import LIMIT_UNITS, LimitCode

SEGMENT_COUNT_MAX = 100
CUEING_ALGORITHMS = ("classical", "optimal")
SEGMENT_DURATION_MAX_S = 3600.0


class PrescriptionError(InvalidValueError):
    """A malformed prescription or patient; names the field, the value and the rule it broke."""


class PrescriptionRejected(ValueError):  # noqa: N818 — the agreed interface name
    """The prescription would exceed a limit: where (segment, time in it) and which limit."""

    def __init__(
        self, segment: int, time_s: float, limit: str, value: float, message: str, details: dict[str, Any] | None = None
    ) -> None:
        self.segment, self.time_s, self.limit, self.value = segment, time_s, limit, value
        # Beyond the first breach: every kinematic limit broken in the segment (by reason, with its stretches)
        # and each robot's singularity report (worst cond(J) and when, every det J sign change).
        self.details = details or {}
        super().__init__(message)

    def to_dict(self) -> dict[str, Any]:
        return {
            "segment": self.segment,
            "time_s": self.time_s,
            "limit": self.limit,
            "value": self.value,
            "message": str(self),
            **self.details,
        }


@dataclass(frozen=True)
class PatientSetup:
    """Who stands on the platforms: drives the payload in the dynamics, the simulated patient of the
    sim and kinematic backends, and the fall detectors' thresholds."""

    body_mass_kg: float
    height_m: float
    parameters: PatientParameters
    fall_detectors: FallDetectorConfig
    seed: int = 0

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> PatientSetup:
        """`{"body_mass_kg", "height_m", "preset"?: "healthy"|"impaired", "seed"?, "fall_detectors"?: {...},
        any PatientParameters field as an override}`."""
        if not isinstance(data, Mapping):
            raise PrescriptionError("patient", data, "must be an object")
        values = dict(data)
        try:
            mass, height = values.pop("body_mass_kg"), values.pop("height_m")
        except KeyError as missing:
            raise PrescriptionError(f"patient.{missing.args[0]}", None, "required") from None
        preset = values.pop("preset", "healthy")
        seed = values.pop("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise PrescriptionError("patient.seed", seed, "must be an integer")
        detector_overrides = values.pop("fall_detectors", None)
        try:
            parameters = PatientParameters.preset(preset, mass, height, **values)
            detectors = FallDetectorConfig.for_patient(mass, height)
            if detector_overrides is not None:
                detectors = FallDetectorConfig.from_dict(
                    {**detectors.to_dict(), **detector_overrides, "body_mass_kg": mass}
                )
        except (ValueError, TypeError) as error:
            raise PrescriptionError("patient", dict(data), str(error)) from None
        return cls(float(mass), float(height), parameters, detectors, seed)

    def payload(self) -> PayloadModel:
        return PayloadModel.from_body(self.body_mass_kg, self.height_m)


@dataclass(frozen=True)
class SegmentPlan:
    index: int
    cue_spec: Mapping[str, Any]
    duration_s: float
    washout: WashoutParameters
    shaping: ShapingParameters
    limits: SessionLimits  # the robot's, tightened by the prescription
    motion_limits: SessionLimits  # `limits` less the stop margin: what normal motion must respect
    seed: int
    cue_samples: int  # duration plus fade out, in ticks
    cueing: str = "classical"
    planned_poses: np.ndarray | None = None  # optimal cueing: the stance trajectory (cue_samples, 6)


@dataclass(frozen=True)
class PrescriptionPlan:
    segments: tuple[SegmentPlan, ...]
    control_rate_hz: int
    config: SupervisorConfig
    patient: PatientSetup | None = None

    @property
    def sample_period_s(self) -> float:
        return 1.0 / self.control_rate_hz


@dataclass(frozen=True)
class PrescriptionReport:
    """What the offline check found: every limit's peak use (fraction of the limit) and the timeline."""

    duration_s: float
    samples: int
    segment_start_s: list[float]
    peak_use: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "duration_s": self.duration_s,
            "samples": self.samples,
            "segment_start_s": self.segment_start_s,
            "peak_use": self.peak_use,
        }


def _parameters(cls: Any, data: Any, field_name: str, default: Any) -> Any:
    if data is None:
        return default
    if not isinstance(data, Mapping):
        raise PrescriptionError(field_name, data, "must be an object")
    try:
        return cls.from_dict(dict(data))
    except (ValueError, TypeError) as error:
        if hasattr(error, "field"):  # the models' own errors name field, value and limit
            named: Any = error
            raise PrescriptionError(f"{field_name}.{named.field}", named.value, named.limit) from None
        raise PrescriptionError(field_name, data, str(error)) from None


def plan_prescription(
    prescription: Mapping[str, Any],
    twin: TwinRobot,
    *,
    control_rate_hz: int = DEFAULT_CONTROL_RATE_HZ,
    config: SupervisorConfig | None = None,
    patient: Mapping[str, Any] | None = None,
) -> PrescriptionPlan:
    """Validate every field and build the plan the worker plays; refuses with `PrescriptionError`."""
    config = config or SupervisorConfig()
    control_rate_hz = validate_control_rate(control_rate_hz)
    period = 1.0 / control_rate_hz
    if not isinstance(prescription, Mapping):
        raise PrescriptionError("prescription", prescription, "must be an object with 'segments'")
    unknown = sorted(set(prescription) - {"segments", "seed", "name", "notes", "cueing"})
    if unknown:
        raise PrescriptionError(unknown[0], prescription[unknown[0]], "unknown prescription field")
    seed = prescription.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise PrescriptionError("seed", seed, "must be an integer")
    cueing = prescription.get("cueing", "classical")
    if cueing not in CUEING_ALGORITHMS:
        raise PrescriptionError("cueing", cueing, f"must be one of {list(CUEING_ALGORITHMS)}")
    segments = prescription.get("segments")
    if not isinstance(segments, list) or not 1 <= len(segments) <= SEGMENT_COUNT_MAX:
        raise PrescriptionError("segments", segments, f"must be a list of 1 to {SEGMENT_COUNT_MAX} segments")
    plans = []
    for index, segment in enumerate(segments):
        prefix = f"segments[{index}]"
        if not isinstance(segment, Mapping):
            raise PrescriptionError(prefix, segment, "must be an object")
        extra = sorted(set(segment) - {"cue", "duration_s", "washout", "shaping", "limits"})
        if extra:
            raise PrescriptionError(f"{prefix}.{extra[0]}", segment[extra[0]], "unknown segment field")
        duration = segment.get("duration_s")
        if isinstance(duration, bool) or not isinstance(duration, int | float) or not math.isfinite(duration):
            raise PrescriptionError(f"{prefix}.duration_s", duration, "must be a number of seconds")
        if not config.soft_start_s <= duration <= SEGMENT_DURATION_MAX_S:
            raise PrescriptionError(
                f"{prefix}.duration_s",
                duration,
                f"must be in [{config.soft_start_s:g} (soft start), {SEGMENT_DURATION_MAX_S:g}] s",
            )
        try:
            cue_from_spec(segment.get("cue", {}), period, seed + index)
        except CueSpecError as error:
            raise PrescriptionError(f"{prefix}.cue.{error.field}", error.value, error.limit) from None
        try:
            limits = SessionLimits.for_twin(twin, segment.get("limits"), f"{prefix}.limits")
        except LimitOverrideError as error:
            raise PrescriptionError(error.field, error.value, error.limit) from None
        plans.append(
            SegmentPlan(
                index=index,
                cue_spec=segment["cue"],
                duration_s=float(duration),
                washout=_parameters(
                    WashoutParameters, segment.get("washout"), f"{prefix}.washout", paper_tilt_parameters()
                ),
                shaping=_parameters(
                    ShapingParameters, segment.get("shaping"), f"{prefix}.shaping", ShapingParameters()
                ),
                limits=limits,
                motion_limits=limits.with_margin(
                    config.limit_margin_fraction, config.stroke_margin_m, config.clearance_margin_m
                ),
                seed=seed + index,
                cue_samples=round((float(duration) + config.fade_out_s) * control_rate_hz),
                cueing=cueing,
            )
        )
    setup = None if patient is None else PatientSetup.from_dict(patient)
    if cueing == "optimal":
        plans = _optimal_segments(plans, twin, period, config, setup)
    return PrescriptionPlan(tuple(plans), control_rate_hz, config, setup)


def _optimal_segments(
    segments: list[SegmentPlan], twin: TwinRobot, period: float, config: SupervisorConfig, patient: PatientSetup | None
) -> list[SegmentPlan]:
    """Plan every segment's stance trajectory from its whole cue (as played: × soft-start/fade gains), within
    the limits normal motion keeps, perceived at this patient's head."""
    params = OptimalCueingParameters(head_height_m=head_height_m(patient.height_m if patient else None))
    planned = []
    for segment in segments:
        force, angular = segment_cue(segment, period, config)
        limits = segment.motion_limits
        workspace = CueingWorkspace(twin, limits.motion, limits.stroke_min_m, limits.stroke_max_m)
        plan = OptimalCueingPlanner(workspace, params).plan(force, angular, period)
        planned.append(replace(segment, planned_poses=plan.pose))
    return planned


def segment_cue(segment: SegmentPlan, sample_period_s: float, config: SupervisorConfig) -> tuple[np.ndarray, ...]:
    """The segment's cue (N, 3) ×2 as the worker plays it: × soft-start and fade-out gains."""
    cue = cue_from_spec(segment.cue_spec, sample_period_s, segment.seed)
    force, angular = cue.generate(segment.cue_samples * sample_period_s)
    gains = cue_gains(
        np.arange(len(force)) * sample_period_s, segment.duration_s, config.soft_start_s, config.fade_out_s
    )
    return force * gains[:, None], angular * gains[:, None]


def segment_cue_poses(segment: SegmentPlan, sample_period_s: float, config: SupervisorConfig) -> tuple[np.ndarray, ...]:
    """The segment's cue (N, 3) ×2 and stance poses (N, 6) from rest: the batch twin of the worker's CUE
    phase (classical: washout and command shaping; optimal: the planned trajectory)."""
    cue = cue_from_spec(segment.cue_spec, sample_period_s, segment.seed)
    force, angular = cue.generate(segment.cue_samples * sample_period_s)
    if segment.planned_poses is not None:
        return force, angular, segment.planned_poses
    played_force, played_angular = segment_cue(segment, sample_period_s, config)
    trajectory = washout_batch(segment.washout, sample_period_s, played_force, played_angular)
    poses = CommandShaper(segment.shaping, sample_period_s).shape_batch(trajectory.pose)
    return force, angular, poses


def finite_differences(
    poses: np.ndarray, sample_period_s: float, previous: np.ndarray, previous_velocity: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Backward-difference velocity and acceleration, as the worker computes them tick by tick."""
    velocity = np.diff(poses, axis=0, prepend=previous[None, :]) / sample_period_s
    acceleration = np.diff(velocity, axis=0, prepend=previous_velocity[None, :]) / sample_period_s
    return velocity, acceleration


def return_ramp(
    position: np.ndarray,
    velocity: np.ndarray,
    acceleration: np.ndarray,
    sample_period_s: float,
    config: SupervisorConfig,
) -> np.ndarray:
    """Stance poses (M, 6) of the quintic return to neutral the worker plays after a segment."""
    ramp = PoseRamp()
    velocity = start_velocity(velocity, acceleration, sample_period_s, np.zeros(6))
    duration = return_duration_s(
        position,
        velocity,
        minimum_s=config.return_min_s,
        speed_m_s=config.return_speed_m_s,
        rate_rad_s=config.return_rate_rad_s,
        acceleration_m_s2=config.return_acceleration_m_s2,
        angular_acceleration_rad_s2=config.return_angular_acceleration_rad_s2,
    )
    ramp.to_pose(position, velocity, acceleration, np.zeros(6), duration)
    times = np.arange(1, math.ceil(duration / sample_period_s) + 1) * sample_period_s
    t = np.minimum(times, duration)[:, None]
    c = ramp.coefficients
    return c[0] + t * (c[1] + t * (c[2] + t * (c[3] + t * (c[4] + t * c[5]))))


def check_prescription(
    prescription: Mapping[str, Any],
    twin: TwinRobot,
    *,
    control_rate_hz: int = DEFAULT_CONTROL_RATE_HZ,
    config: SupervisorConfig | None = None,
    patient: Mapping[str, Any] | None = None,
) -> PrescriptionReport:
    """Run the whole prescription offline; raise `PrescriptionRejected` at the first limit it breaks."""
    plan = plan_prescription(prescription, twin, control_rate_hz=control_rate_hz, config=config, patient=patient)
    return check_plan(plan, twin)


def check_plan(plan: PrescriptionPlan, twin: TwinRobot) -> PrescriptionReport:
    period, config = plan.sample_period_s, plan.config
    dynamics = TwinInverseDynamics(twin, plan.patient.payload() if plan.patient else None)
    neutral_sliders = _neutral_sliders(twin)
    previous_pose, previous_velocity = np.zeros(6), np.zeros(6)
    previous_sliders, previous_slider_velocity = neutral_sliders, np.zeros(12)
    peak_use: dict[str, float] = {}
    segment_start_s, elapsed = [], 0.0
    samples = 0
    for segment in plan.segments:
        segment_start_s.append(elapsed)
        _, _, cue_poses = segment_cue_poses(segment, period, config)
        velocity, acceleration = finite_differences(cue_poses, period, previous_pose, previous_velocity)
        back = return_ramp(cue_poses[-1], velocity[-1], acceleration[-1], period, config)
        poses = np.concatenate([cue_poses, back])
        velocity, acceleration = finite_differences(poses, period, previous_pose, previous_velocity)
        sliders = _check_samples(
            twin,
            segment,
            poses,
            velocity,
            acceleration,
            period,
            dynamics,
            previous_sliders,
            previous_slider_velocity,
            peak_use,
        )
        previous_slider_velocity = (sliders[-1] - sliders[-2]) / period
        previous_sliders = sliders[-1]
        previous_pose, previous_velocity = poses[-1], velocity[-1]
        elapsed += len(poses) * period
        samples += len(poses)
    return PrescriptionReport(elapsed, samples, segment_start_s, {k: round(v, 4) for k, v in peak_use.items()})


def _neutral_sliders(twin: TwinRobot) -> np.ndarray:
    solutions = twin_inverse_kinematics(twin, np.zeros((1, 6)))
    return np.concatenate([solutions[side].slider_positions_m[0] for side in twin.sides])


def _check_samples(
    twin: TwinRobot,
    segment: SegmentPlan,
    poses: np.ndarray,
    velocity: np.ndarray,
    acceleration: np.ndarray,
    period: float,
    dynamics: TwinInverseDynamics,
    previous_sliders: np.ndarray,
    previous_slider_velocity: np.ndarray,
    peak_use: dict[str, float],
) -> np.ndarray:
    """Every limit over one segment's samples; raises at the earliest breach. Returns sliders (N, 12)."""
    limits = segment.motion_limits.motion
    solutions = twin_inverse_kinematics(twin, poses, check=False)
    sides = [solutions[side] for side in ("right", "left")]
    sliders = np.concatenate([s.slider_positions_m for s in sides], axis=1)
    unreachable = np.isnan(sliders)
    # Distance from each platform joint to its rail (only reported when the rod cannot reach).
    reach = np.where(unreachable, twin.robot.rod_length_m + 1e-9, 0.0)
    sliders_filled = np.where(unreachable, previous_sliders, sliders)
    slider_velocity = np.diff(sliders_filled, axis=0, prepend=previous_sliders[None, :]) / period
    slider_acceleration = np.diff(slider_velocity, axis=0, prepend=previous_slider_velocity[None, :]) / period
    tilt = np.arccos(np.clip(np.cos(poses[:, 3]) * np.cos(poses[:, 4]), -1.0, 1.0))
    forces = dynamics.slider_forces(np.where(unreachable.any(axis=1)[:, None], 0.0, poses), velocity, acceleration)
    violations = np.concatenate([s.violations for s in sides], axis=1)
    singular = (violations & np.uint8(LegViolation.SINGULARITY)) != 0
    collisions = sides[0].collisions
    clearance = collisions.clearance_m if collisions is not None else np.full(len(poses), np.inf)
    clearance_min = segment.motion_limits.clearance_min_m  # the robot's margin plus the stop margin
    base_cone = np.concatenate([s.base_cone_rad for s in sides], axis=1)
    platform_cone = np.concatenate([s.platform_cone_rad for s in sides], axis=1)
    stroke_min, stroke_max = segment.motion_limits.stroke_min_m, segment.motion_limits.stroke_max_m
    below, above = sliders_filled < stroke_min, sliders_filled > stroke_max
    checks: list[tuple[LimitCode, np.ndarray, np.ndarray, float | np.ndarray]] = [
        # code, breached (N, k), value (N, k), limit
        (LimitCode.ROD_REACH, unreachable, reach, twin.robot.rod_length_m),
        (LimitCode.STROKE, below | above, sliders_filled, np.where(below, stroke_min, stroke_max)),
        (LimitCode.BASE_JOINT_CONE, base_cone > limits.base_joint_cone_rad, base_cone, limits.base_joint_cone_rad),
        (
            LimitCode.PLATFORM_JOINT_CONE,
            platform_cone > limits.platform_joint_cone_rad,
            platform_cone,
            limits.platform_joint_cone_rad,
        ),
        (LimitCode.TILT, (tilt > limits.tilt_max_rad)[:, None], tilt[:, None], limits.tilt_max_rad),
        (
            LimitCode.SLIDER_VELOCITY,
            np.abs(slider_velocity) > limits.slider_velocity_max_m_s,
            slider_velocity,
            limits.slider_velocity_max_m_s,
        ),
        (
            LimitCode.SLIDER_ACCELERATION,
            np.abs(slider_acceleration) > limits.slider_acceleration_max_m_s2,
            slider_acceleration,
            limits.slider_acceleration_max_m_s2,
        ),
        (LimitCode.DRIVE_FORCE, np.abs(forces) > limits.drive_force_max_n, forces, limits.drive_force_max_n),
        (LimitCode.SINGULARITY, singular, singular.astype(float), 0.0),
        (LimitCode.COLLISION, (~(clearance >= clearance_min))[:, None], clearance[:, None], clearance_min),
    ]
    first: tuple[int, LimitCode, int, float, float] | None = None
    for code, breached, values, limit in checks:
        if code in (
            LimitCode.TILT,
            LimitCode.SLIDER_VELOCITY,
            LimitCode.SLIDER_ACCELERATION,
            LimitCode.DRIVE_FORCE,
            LimitCode.BASE_JOINT_CONE,
            LimitCode.PLATFORM_JOINT_CONE,
        ):
            use = float(np.nanmax(np.abs(values))) / float(np.max(limit))
            peak_use[code.label] = max(peak_use.get(code.label, 0.0), use)
        rows = np.flatnonzero(breached.any(axis=1))
        if rows.size and (first is None or rows[0] < first[0]):
            sample = int(rows[0])
            axis = int(np.argmax(breached[sample]))
            limit_value = float(np.broadcast_to(limit, breached.shape)[sample, axis])
            first = (sample, code, axis, float(values[sample, axis]), limit_value)
    if first is not None:
        sample, code, axis, value, limit_value = first
        time_s = sample * period
        where = "" if code is LimitCode.TILT else f", {_axis_label(axis)}"
        unit = LIMIT_UNITS[code]
        phase = "cue" if sample < segment.cue_samples else "return to neutral"
        name = code.label.replace("_", " ")
        times = np.arange(len(poses)) * period
        details: dict[str, Any] = {"violations_by_reason": violation_stretches(solutions, times)}
        if code is LimitCode.SINGULARITY:
            reports = twin_singularity_report(twin, poses, times)
            details["singularity"] = {side: report.to_dict() for side, report in reports.items()}
            worst = max(reports.items(), key=lambda item: item[1].worst_condition_number)
            side, report = worst
            detail = f"the platform would come too close to (or pass) a singularity; {side} robot: {report.summary()}"
        elif code is LimitCode.COLLISION and collisions is not None:
            where = ""
            pair = collisions.pair_names[int(collisions.closest_pair[sample])]
            detail = f"collision {pair}: clearance {value * 1e3:.1f} mm against the margin {limit_value * 1e3:.1f} mm"
        elif code is LimitCode.ROD_REACH:
            detail = "a rod could not reach its rail"
        else:
            detail = (
                f"{name} {value:.6g} {unit} exceeds the limit {limit_value:.6g} {unit} "
                "(normal motion keeps the configured stop margin inside each limit)"
            )
        raise PrescriptionRejected(
            segment.index,
            time_s,
            code.label,
            value,
            f"segment {segment.index} at t = {time_s:.3f} s ({phase}{where}): {detail}",
            details,
        )
    return sliders_filled


def _axis_label(axis: int) -> str:
    return f"{('right', 'left')[axis // 6]} slider {axis % 6 + 1}"
