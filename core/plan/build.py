"""`build_plan`: a validated prescription and the twin (with the patient, the control rate and the plan
settings) → the checked plan the real-time worker plays.

    prescription (core.plan.prescription) → per segment: the robot's limits tightened by the segment's,
    with the stop margin for normal motion; the washout and shaping parameter sets; the cue generator
    → cueing: classical (washout and shaping over the whole cue, `core.plan.timeline`) or optimal (the
    stance trajectory planned from the whole cue, `core.optimal_cueing`) → the independent check
    (`core.plan.check`); the worker plays the checked samples and computes no cueing of its own

What depends on the robot or the rate (a limit may only tighten the robot's; the shaper at this rate; the
soft start within the segment) is checked here, with the same error shape as the model's
(`PrescriptionError`: field path, value, limit).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from core.cues import CueSpecError, validate_cue_spec
from core.dynamics import PayloadModel
from core.falls import FallDetectorConfig
from core.optimal_cueing import CueingWorkspace, OptimalCueingParameters, OptimalCueingPlanner
from core.patient import PatientParameters
from core.perception import head_height_m
from core.plan.check import PrescriptionReport, check_plan
from core.plan.config import DEFAULT_CONTROL_RATE_HZ, PlanConfig
from core.plan.limits import LimitOverrideError, SessionLimits
from core.plan.motion import PLANNED_SHARE, PlannedMotion
from core.plan.prescription import Prescription, PrescriptionBody, PrescriptionError, Segment, parse_prescription
from core.plan.rejection import PrescriptionRejected
from core.plan.timeline import segment_cue
from core.robot import TwinRobot, twin_digest
from core.shaping import CommandShaper, ParameterError, ShapingParameters
from core.washout import WashoutParameters

Progress = Callable[[float], None]
CONTROL_RATE_RANGE_HZ = (10, 10_000)  # the cue generators sample at least every 0.1 s; the worker allows less


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
    config: PlanConfig
    patient: PatientSetup | None = None
    robot_digest: str = ""  # `core.robot.twin_digest` of the robot it was made for
    motion: PlannedMotion | None = None  # every tick as the worker plays it (set by `plan_prescription`)

    @property
    def played(self) -> PlannedMotion:
        """The motion the check validates and the worker plays."""
        if self.motion is None:
            raise ValueError("the plan has no motion yet (made by plan_prescription)")
        return self.motion

    @property
    def sample_period_s(self) -> float:
        return 1.0 / self.control_rate_hz


@dataclass(frozen=True)
class CheckedPlan:
    """A plan and the check's verdict: its report, or the first limit it would break."""

    plan: PrescriptionPlan
    report: PrescriptionReport | None
    rejection: PrescriptionRejected | None

    def accepted(self) -> PrescriptionReport:
        """The report of an accepted plan; raises the rejection otherwise."""
        if self.rejection is not None:
            raise self.rejection
        assert self.report is not None
        return self.report


def _robot_settings(
    index: int, segment: Segment, twin: TwinRobot, period: float, config: PlanConfig
) -> tuple[SessionLimits, ShapingParameters]:
    """What the model cannot know: the robot's limits (only ever tightened), the shaper at this control rate,
    the soft start within the segment; and what it leaves to a worker thread (a CSV cue's rows). Refuses
    with the model's error shape, at the segment's field."""
    prefix = f"segments[{index}]"
    if segment.cue.check_deferred:
        try:
            validate_cue_spec(segment.cue.spec())
        except CueSpecError as error:
            raise PrescriptionError(f"{prefix}.cue.{error.field}", error.value, error.limit) from None
    if segment.duration_s < config.soft_start_s:
        raise PrescriptionError(
            f"{prefix}.duration_s", segment.duration_s, f"must be at least the soft start, {config.soft_start_s:g} s"
        )
    try:
        limits = SessionLimits.for_twin(twin, segment.limit_overrides(), f"{prefix}.limits")
    except LimitOverrideError as error:
        raise PrescriptionError(error.field, error.value, error.limit) from None
    shaping = segment.shaping.parameters()
    try:
        CommandShaper(shaping, period)
    except ParameterError as error:
        raise PrescriptionError(f"{prefix}.shaping.{error.field}", error.value, error.limit) from None
    return limits, shaping


def check_for_robot(
    prescription: PrescriptionBody,
    twin: TwinRobot,
    *,
    control_rate_hz: int = DEFAULT_CONTROL_RATE_HZ,
    config: PlanConfig | None = None,
) -> None:
    """The robot- and rate-dependent checks of `plan_prescription` alone, and the CSV parse the model leaves
    to a worker thread: the API runs them (in the request's thread) before it stores a prescription."""
    for index, segment in enumerate(prescription.segments):
        _robot_settings(index, segment, twin, 1.0 / control_rate_hz, config or PlanConfig())


def plan_prescription(
    prescription: PrescriptionBody | Mapping[str, Any],
    twin: TwinRobot,
    *,
    control_rate_hz: int = DEFAULT_CONTROL_RATE_HZ,
    config: PlanConfig | None = None,
    patient: Mapping[str, Any] | None = None,
    progress: Progress | None = None,
) -> PrescriptionPlan:
    """The plan of a prescription (validated by `core.plan.prescription` if it is not yet a model), before
    the check; refuses with `PrescriptionError`."""
    config = config or PlanConfig()
    valid: Prescription = parse_prescription(prescription)
    low, high = CONTROL_RATE_RANGE_HZ
    if isinstance(control_rate_hz, bool) or not isinstance(control_rate_hz, int) or not low <= control_rate_hz <= high:
        raise PrescriptionError("control_rate_hz", control_rate_hz, f"must be an integer in [{low}, {high}] Hz")
    period = 1.0 / control_rate_hz
    plans = []
    for index, segment in enumerate(valid.segments):
        limits, shaping = _robot_settings(index, segment, twin, period, config)
        plans.append(
            SegmentPlan(
                index=index,
                cue_spec=segment.cue.spec(),
                duration_s=segment.duration_s,
                washout=segment.washout.parameters(),
                shaping=shaping,
                limits=limits,
                motion_limits=limits.with_margin(
                    config.limit_margin_fraction, config.stroke_margin_m, config.clearance_margin_m
                ),
                seed=valid.seed + index,
                cue_samples=round((segment.duration_s + config.fade_out_s) * control_rate_hz),
                cueing=valid.cueing,
            )
        )
    setup = None if patient is None else PatientSetup.from_dict(patient)
    if valid.cueing == "optimal":
        plans = _optimal_segments(plans, twin, period, config, setup, progress)
    plan = PrescriptionPlan(tuple(plans), control_rate_hz, config, setup, twin_digest(twin))
    return replace(plan, motion=PlannedMotion.of(plan, progress))


def _optimal_segments(
    segments: list[SegmentPlan],
    twin: TwinRobot,
    period: float,
    config: PlanConfig,
    patient: PatientSetup | None,
    progress: Progress | None = None,
) -> list[SegmentPlan]:
    """Plan every segment's stance trajectory from its whole cue (as played: × soft-start/fade gains), within
    the limits normal motion keeps, perceived at this patient's head."""
    params = OptimalCueingParameters(head_height_m=head_height_m(patient.height_m if patient else None))
    planned = []
    for segment in segments:
        force, angular = segment_cue(segment, period, config)
        limits = segment.motion_limits
        workspace = CueingWorkspace(
            twin, limits.motion, limits.stroke_min_m, limits.stroke_max_m, clearance_min_m=limits.clearance_min_m
        )
        plan = OptimalCueingPlanner(workspace, params).plan(force, angular, period)
        planned.append(replace(segment, planned_poses=plan.pose))
        if progress is not None:
            progress(PLANNED_SHARE * len(planned) / len(segments))
    return planned


def build_plan(
    prescription: PrescriptionBody | Mapping[str, Any],
    twin: TwinRobot,
    *,
    control_rate_hz: int = DEFAULT_CONTROL_RATE_HZ,
    config: PlanConfig | None = None,
    patient: Mapping[str, Any] | None = None,
    progress: Progress | None = None,
) -> CheckedPlan:
    """The one pipeline the worker, the preview and the offline checks use: plan, then check every sample.
    `progress` hears the fraction done (0 to 1) as segments are planned and checked."""
    plan = plan_prescription(
        prescription, twin, control_rate_hz=control_rate_hz, config=config, patient=patient, progress=progress
    )
    try:
        return CheckedPlan(plan, check_plan(plan, twin, progress), None)
    except PrescriptionRejected as rejection:
        return CheckedPlan(plan, None, rejection)


def check_prescription(
    prescription: PrescriptionBody | Mapping[str, Any],
    twin: TwinRobot,
    *,
    control_rate_hz: int = DEFAULT_CONTROL_RATE_HZ,
    config: PlanConfig | None = None,
    patient: Mapping[str, Any] | None = None,
) -> PrescriptionReport:
    """Run the whole prescription offline; raise `PrescriptionRejected` at the first limit it breaks."""
    checked = build_plan(prescription, twin, control_rate_hz=control_rate_hz, config=config, patient=patient)
    return checked.accepted()
