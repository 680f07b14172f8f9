"""The offline check's verdicts stay what they were before its speed work (issue 21, "Ready before the patient
steps on"): the same peak use of every limit on accepted prescriptions, and the same first breach (segment,
time, limit, value, message and details) on rejected ones.

The pinned verdicts in `data/plan_check_reports.json` were written by the check as it stood on main at
1454a39, before it was vectorised and chunked, with `python -m tests.core.test_plan_check_pinned --write`.
Some cases run longer than one of the check's chunks, and some break a limit only in a later chunk.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import pytest

from core.plan.build import build_plan
from core.robot import TwinRobot, default_twin, symmetric_placements

PINNED = Path(__file__).with_name("data") / "plan_check_reports.json"
PATIENT = {"body_mass_kg": 82.0, "height_m": 1.8}
GENTLE = {"cue": {"kind": "sine", "axis": "x", "amplitude_m_s2": 0.5, "frequency_hz": 0.5}, "duration_s": 3.0}
TILT_STEP = {"kind": "step", "axis": "y", "final_m_s2": 0.12 * 9.80665, "step_time_s": 0.5}
SQUARE = {"kind": "square_wave", "axis": "x", "amplitude_m_s2": 2.0, "period_s": 2.0}
SLOW_WASHOUT = {"translational_break_rad_s": 0.05, "translational_first_order_break_rad_s": 0.01}
CASES: dict[str, tuple[str, dict[str, Any], dict[str, Any] | None]] = {
    "two gentle sways": ("default", {"segments": [GENTLE, GENTLE]}, None),
    "a mixed session with a patient": (
        "default",
        {
            "seed": 7,
            "segments": [
                {
                    "cue": {"kind": "perturbations", "translation_m_s2": 1.0, "pulse_duration_s": 0.6},
                    "duration_s": 40.0,
                },
                {
                    "cue": {
                        "kind": "gait",
                        "cadence_steps_per_min": 100.0,
                        "vertical_amplitude_m_s2": 0.5,
                        "forward_amplitude_m_s2": 0.3,
                        "lateral_amplitude_m_s2": 0.4,
                    },
                    "duration_s": 25.0,
                },
                {
                    "cue": {"kind": "sine", "axis": "pitch", "amplitude_rad_s": 0.05, "frequency_hz": 0.3},
                    "duration_s": 12.0,
                },
                {
                    "cue": {
                        "kind": "multisine",
                        "components": [
                            {"axis": "y", "amplitude_m_s2": 0.3, "frequency_hz": 0.2},
                            {"axis": "roll", "amplitude_rad_s": 0.04, "frequency_hz": 0.45},
                        ],
                    },
                    "duration_s": 20.0,
                },
            ],
        },
        PATIENT,
    ),
    "tilt beyond a tightened limit": (
        "default",
        {"segments": [GENTLE, {"cue": TILT_STEP, "duration_s": 6.0, "limits": {"tilt_max_rad": 0.08}}]},
        None,
    ),
    "tilt beyond a tightened limit in a later chunk": (
        "default",
        {
            "segments": [
                GENTLE,
                {"cue": {**TILT_STEP, "step_time_s": 37.0}, "duration_s": 42.0, "limits": {"tilt_max_rad": 0.08}},
            ]
        },
        PATIENT,
    ),
    "slider velocity": (
        "default",
        {"segments": [{"cue": SQUARE, "duration_s": 4.0, "limits": {"slider_velocity_max_m_s": 0.05}}]},
        None,
    ),
    "slider acceleration": (
        "default",
        {"segments": [{"cue": SQUARE, "duration_s": 4.0, "limits": {"slider_acceleration_max_m_s2": 0.2}}]},
        None,
    ),
    "drive force": (
        "default",
        {"segments": [{"cue": SQUARE, "duration_s": 4.0, "limits": {"drive_force_max_n": 700.0}}]},
        PATIENT,
    ),
    "base joint cone": (
        "default",
        {"segments": [{"cue": SQUARE, "duration_s": 4.0, "limits": {"base_joint_cone_rad": 0.01}}]},
        None,
    ),
    "platform joint cone": (
        "default",
        {
            "segments": [
                {
                    "cue": {"kind": "step", "axis": "x", "final_m_s2": 6.0, "step_time_s": 0.5, "end_time_s": 3.0},
                    "duration_s": 6.0,
                }
            ]
        },
        None,
    ),
    "stroke": (
        "default",
        {
            "segments": [
                {
                    "cue": {"kind": "step", "axis": "x", "final_m_s2": 0.4, "step_time_s": 0.5, "end_time_s": 4.0},
                    "duration_s": 10.0,
                    "washout": {**SLOW_WASHOUT, "tilt_break_rad_s": 0.001},
                }
            ]
        },
        None,
    ),
    "singularity (paper §5's lateral step)": (
        "default",
        {
            "segments": [
                {
                    "cue": {"kind": "step", "axis": "y", "final_m_s2": 0.2 * 9.80665, "step_time_s": 0.5},
                    "duration_s": 10.0,
                }
            ]
        },
        None,
    ),
    "collision on a near-miss layout": (
        "near miss",
        {
            "segments": [
                {"cue": {"kind": "step", "axis": "y", "final_m_s2": 1.96, "step_time_s": 0.3}, "duration_s": 6.0}
            ]
        },
        None,
    ),
}


def _twin(name: str) -> TwinRobot:
    if name == "near miss":  # bases staggered by ±60 mm (tests/server/test_collision_stop.py)
        right, left = symmetric_placements(0.5, 0.06, 0.5)
        return TwinRobot(right=right, left=left)
    return default_twin()


def verdict(case: str) -> dict[str, Any]:
    """The check's verdict on a case as JSON: the report, or the rejection with its details."""
    twin_name, prescription, patient = CASES[case]
    checked = build_plan(prescription, _twin(twin_name), patient=patient)
    if checked.rejection is not None:
        return {"rejected": checked.rejection.to_dict()}
    assert checked.report is not None
    return {"accepted": checked.report.to_dict()}


def _pinned() -> dict[str, Any]:
    pinned: dict[str, Any] = json.loads(PINNED.read_text())
    return pinned


@pytest.mark.parametrize("case", list(CASES))
def test_the_check_gives_the_verdict_it_gave_before_its_speed_work(case: str) -> None:
    expected, found = _pinned()[case], verdict(case)
    assert found.keys() == expected.keys()
    if "accepted" in expected:
        # Peak uses are rounded to 4 digits by the report: the same figures, exactly.
        assert found == expected
        return
    breach, pinned = found["rejected"], expected["rejected"]
    for key in ("segment", "time_s", "limit", "message", "violations_by_reason"):
        assert breach[key] == pinned[key], key
    assert breach["value"] == pytest.approx(pinned["value"], rel=1e-9)
    for side, report in pinned.get("singularity", {}).items():
        found_report = dict(breach["singularity"][side])
        # cond(J) near a singularity is itself ill-conditioned: compared to a relative tolerance.
        worst = found_report.pop("worst_condition_number")
        assert worst == pytest.approx(report["worst_condition_number"], rel=1e-6)
        assert found_report == {k: v for k, v in report.items() if k != "worst_condition_number"}
    assert breach.keys() == pinned.keys()


def test_the_pinned_cases_cover_every_limit_the_plans_can_break() -> None:
    limits = {v["rejected"]["limit"] for v in _pinned().values() if "rejected" in v}
    assert limits == {
        "tilt",
        "slider_velocity",
        "slider_acceleration",
        "drive_force",
        "base_joint_cone",
        "platform_joint_cone",
        "stroke",
        "singularity",
        "collision",
    }
    assert sum("accepted" in v for v in _pinned().values()) == 2


if __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    PINNED.write_text(json.dumps({case: verdict(case) for case in CASES}, indent=1, sort_keys=True) + "\n")
