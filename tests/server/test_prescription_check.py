"""The offline prescription check: a prescription that would exceed a limit is refused before any motion."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from core.plan.build import check_prescription, plan_prescription
from core.plan.prescription import PrescriptionError
from core.plan.rejection import PrescriptionRejected
from core.robot import TwinRobot
from server.hal.kinematic import KinematicHal
from server.realtime.pipeline import TickPipeline, start_along_checked_approach
from server.realtime.supervisor import SupervisorConfig
from server.realtime.telemetry import SupervisorState

GENTLE = {"cue": {"kind": "sine", "axis": "x", "amplitude_m_s2": 0.5, "frequency_hz": 0.5}, "duration_s": 3.0}
# A lateral step in the manner of paper §4.3 (which uses 0.2 g): tilt coordination settles at asin(0.12) rad.
TILT_STEP = {"kind": "step", "axis": "y", "final_m_s2": 0.12 * 9.80665, "step_time_s": 0.5}


def test_a_feasible_prescription_passes_with_its_peak_limit_use(twin: TwinRobot) -> None:
    report = check_prescription({"segments": [GENTLE, GENTLE]}, twin)
    assert report.segment_start_s[0] == 0.0 and report.segment_start_s[1] > 3.0
    assert set(report.peak_use) >= {"tilt", "slider_velocity", "slider_acceleration", "drive_force"}
    assert 0.0 < max(report.peak_use.values()) < 1.0


def test_refusal_names_the_segment_the_time_and_the_limit(twin: TwinRobot) -> None:
    tight = {"cue": TILT_STEP, "duration_s": 6.0, "limits": {"tilt_max_rad": 0.08}}
    with pytest.raises(PrescriptionRejected) as refused:
        check_prescription({"segments": [GENTLE, tight]}, twin)
    rejection = refused.value
    assert rejection.segment == 1 and rejection.limit == "tilt"
    assert 0.5 < rejection.time_s < 3.0  # after the step, while the platform tilts towards 0.12 rad
    assert rejection.value > 0.08 * (1 - SupervisorConfig().limit_margin_fraction)
    assert "segment 1" in str(rejection) and "tilt" in str(rejection)
    # The same cue passes under the robot's own 25° limit: the refusal came from the limit, not the cue.
    check_prescription({"segments": [{"cue": TILT_STEP, "duration_s": 6.0}]}, twin)


@pytest.mark.parametrize(
    ("limits", "code"),
    [
        ({"slider_velocity_max_m_s": 0.05}, "slider_velocity"),
        ({"slider_acceleration_max_m_s2": 0.2}, "slider_acceleration"),
        ({"drive_force_max_n": 300.0}, "drive_force"),
        ({"base_joint_cone_rad": 0.01}, "base_joint_cone"),
    ],
)
def test_every_limit_kind_can_refuse(twin: TwinRobot, limits: dict[str, float], code: str) -> None:
    segment = {
        "cue": {"kind": "square_wave", "axis": "x", "amplitude_m_s2": 2.0, "period_s": 2.0},
        "duration_s": 4.0,
        "limits": limits,
    }
    with pytest.raises(PrescriptionRejected) as refused:
        check_prescription({"segments": [segment]}, twin)
    assert refused.value.limit == code


def test_the_offline_check_and_the_running_pipeline_agree_on_when_a_limit_is_hit(twin: TwinRobot) -> None:
    prescription = {"segments": [{"cue": TILT_STEP, "duration_s": 6.0, "limits": {"tilt_max_rad": 0.08}}]}
    with pytest.raises(PrescriptionRejected) as refused:
        check_prescription(prescription, twin)
    hal = KinematicHal(twin, 0.001, communication_timeout_s=30.0)
    hal.configure()
    events: list[tuple[str, dict[str, Any]]] = []
    pipeline = TickPipeline(
        twin, hal, 1000, SupervisorConfig(), lambda kind, details, _: events.append((kind, details))
    )
    pipeline.load(plan_prescription(prescription, twin))  # unchecked, on purpose
    pipeline.heartbeat()
    start_along_checked_approach(pipeline)
    approach_ticks = 0
    for _ in range(10_000):
        pipeline.heartbeat()
        pipeline.tick(0)
        approach_ticks += pipeline.source.plan_index < 0
        if pipeline.supervisor.state is not SupervisorState.RUNNING:
            break
    hit = next(details for kind, details in events if kind == "limit_hit")
    assert hit["limit"] == "tilt"
    assert math.isclose(hit["segment_time_s"], refused.value.time_s + 0.001, abs_tol=0.0015)


@pytest.mark.parametrize(
    ("prescription", "field"),
    [
        ({"segments": []}, "segments"),
        ({"segments": [{**GENTLE, "duration_s": -1.0}]}, "segments[0].duration_s"),
        ({"segments": [{**GENTLE, "cue": {"kind": "sine", "axis": "x"}}]}, "segments[0].cue.frequency_hz"),
        (
            {"segments": [{**GENTLE, "cue": {"kind": "sine", "axis": "x", "frequency_hz": 0.5}}]},
            "segments[0].cue.amplitude_m_s2",
        ),
        ({"segments": [{**GENTLE, "duration_s": 0.5}]}, "segments[0].duration_s"),  # shorter than the soft start
        ({"segments": [{**GENTLE, "shaping": {"lowpass_cutoff_hz": 9.0}}]}, "segments[0].shaping.lowpass_cutoff_hz"),
        ({"segments": [{**GENTLE, "limits": {"tilt_max_rad": 1.0}}]}, "segments[0].limits.tilt_max_rad"),
        ({"segments": [{**GENTLE, "limits": {"speed": 1.0}}]}, "segments[0].limits.speed"),
        ({"segments": [{**GENTLE, "washout": {"tilt_break_rad_s": -2.0}}]}, "segments[0].washout.tilt_break_rad_s"),
        ({"segments": [GENTLE], "colour": "red"}, "colour"),
    ],
)
def test_malformed_prescriptions_are_refused_naming_the_field(twin: TwinRobot, prescription: dict, field: str) -> None:
    with pytest.raises(PrescriptionError) as refused:
        check_prescription(prescription, twin)
    assert refused.value.field == field


def test_patient_data_is_validated(twin: TwinRobot) -> None:
    with pytest.raises(PrescriptionError, match="height_m"):
        check_prescription({"segments": [GENTLE]}, twin, patient={"body_mass_kg": 70.0})
    report = check_prescription({"segments": [GENTLE]}, twin, patient={"body_mass_kg": 120.0, "height_m": 1.9})
    light = check_prescription({"segments": [GENTLE]}, twin, patient={"body_mass_kg": 50.0, "height_m": 1.6})
    assert report.peak_use["drive_force"] > light.peak_use["drive_force"]  # the payload enters the dynamics
    assert np.isfinite(report.duration_s)


def test_a_singularity_refusal_reports_the_worst_conditioning_and_every_crossing(twin: TwinRobot) -> None:
    """Paper §5's lateral step (0.2 g): the mirrored left robot passes its singularity. The refusal gives
    the worst condition number and when, every det J sign change, and every limit's stretches (issue 13)."""
    step = {"kind": "step", "axis": "y", "final_m_s2": 0.2 * 9.80665, "step_time_s": 0.5}
    with pytest.raises(PrescriptionRejected) as refused:
        check_prescription({"segments": [{"cue": step, "duration_s": 10.0}]}, twin)
    rejection = refused.value
    assert rejection.limit == "singularity"
    assert "worst condition number" in str(rejection) and "other assembly mode" in str(rejection)
    left = rejection.to_dict()["singularity"]["left"]
    assert left["worst_condition_number"] > 1e4 and left["det_sign_changes"]
    assert len(left["det_sign_changes"]) == 2 * len(left["other_assembly_mode"])  # in and back out
    assert left["samples_beyond_margin"] > 1000
    by_reason = rejection.to_dict()["violations_by_reason"]["left"]
    assert by_reason["too close to or beyond a singularity"]["samples"] >= left["samples_beyond_margin"] - 1
