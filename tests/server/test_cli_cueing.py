"""`ssp-rehab cueing plan|compare` through the real CLI: the contract scripts rely on (issue 14)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from server.cli.main import app

runner = CliRunner()
CONTRACT = {
    "feasible",
    "reason",
    "duration_s",
    "planning_wall_s",
    "perceived_specific_force_error_rms_m_s2",
    "perceived_specific_force_error_rms_raw_m_s2",
    "perceived_angular_velocity_error_rms_rad_s",
    "peak_tilt_rate_rad_s",
    "max_condition_number",
    "min_clearance_mm",
    "max_stroke_use_fraction",
}
SWAY = {"name": "sway", "segments": [{"cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.3,
                                              "frequency_hz": 0.3}, "duration_s": 6.0}]}  # fmt: skip


def test_plan_prints_exactly_the_contract_and_optimal_beats_classical(tmp_path: Path) -> None:
    path = tmp_path / "sway.json"
    path.write_text(json.dumps(SWAY))
    results = {}
    for cueing in ("classical", "optimal"):
        outcome = runner.invoke(app, ["cueing", "plan", str(path), "--cueing", cueing, "--json"])
        assert outcome.exit_code == 0, outcome.output
        results[cueing] = json.loads(outcome.stdout)
        assert set(results[cueing]) == CONTRACT
        assert results[cueing]["feasible"] is True and results[cueing]["reason"] is None
        assert results[cueing]["duration_s"] > 6.0 and results[cueing]["max_stroke_use_fraction"] < 1.0
    optimal, classical = results["optimal"], results["classical"]
    # The twin's collision clearance (core.clearance), never null: the default twin's closest parts are
    # the inner sliders 3 and 4 of the two robots, 80 mm apart on parallel rails whatever the pose.
    for result in results.values():
        assert result["min_clearance_mm"] == pytest.approx(80.0, abs=0.5)
    assert (
        optimal["perceived_specific_force_error_rms_m_s2"] < 0.5 * classical["perceived_specific_force_error_rms_m_s2"]
    )
    assert optimal["peak_tilt_rate_rad_s"] < 0.0524  # 3 °/s


def test_plan_names_a_refused_field_and_an_infeasible_plan_gives_its_reason(tmp_path: Path) -> None:
    path = tmp_path / "bad.json"
    no_amplitude = {"kind": "sine", "axis": "y", "frequency_hz": 0.5}
    path.write_text(json.dumps({"segments": [{"cue": no_amplitude, "duration_s": 6.0}]}))
    outcome = runner.invoke(app, ["cueing", "plan", str(path), "--json"])
    assert outcome.exit_code == 2 and "amplitude_m_s2" in json.loads(outcome.stdout)["error"]
    refused = runner.invoke(app, ["cueing", "plan", str(path), "--cueing", "magic", "--json"])
    assert refused.exit_code == 2 and "optimal" in json.loads(refused.stdout)["error"]
    tight = {"segments": [{**SWAY["segments"][0], "limits": {"tilt_max_rad": 0.001}}]}
    tight["segments"][0]["cue"] = {"kind": "sine", "axis": "roll", "amplitude_rad_s": 0.2, "frequency_hz": 0.3}
    path.write_text(json.dumps(tight))
    outcome = runner.invoke(app, ["cueing", "plan", str(path), "--json"])
    data = json.loads(outcome.stdout)
    assert outcome.exit_code == 0 and data["feasible"] is False and "tilt" in data["reason"]


def test_compare_json_shape_and_plot(tmp_path: Path) -> None:
    outcome = runner.invoke(app, ["cueing", "compare", "--scenario", "sine-sway", "--json", "--plot", str(tmp_path)])
    assert outcome.exit_code == 0, outcome.output
    data = json.loads(outcome.stdout)
    (row,) = data["scenarios"]
    assert row["name"] == "sine-sway" and set(row["classical"]) == set(row["optimal"]) == CONTRACT
    assert Path(data["plots"][0]).stat().st_size > 1000
    assert runner.invoke(app, ["cueing", "compare", "--scenario", "loop"]).exit_code == 2


SQUARE = {"segments": [{"cue": {"kind": "square_wave", "axis": "x", "amplitude_m_s2": 2.0, "period_s": 2.0},
                        "duration_s": 6.0}]}  # fmt: skip


def test_plan_judges_against_the_cue_as_written_beside_the_cue_as_played(tmp_path: Path) -> None:
    """Issue 21, defect 5: the raw figure compares what the head feels with the prescribed cue as written
    (no soft start, nothing after the segment's duration), perceived through the same otolith model."""
    import numpy as np

    from core.cues import cue_from_spec
    from core.perception import DEFAULT_HEAD_HEIGHT_M, head_specific_force
    from core.plan.build import plan_prescription
    from core.plan.timeline import prescription_timeline
    from core.robot import default_twin
    from core.vestibular import VestibularModel

    path = tmp_path / "square.json"
    path.write_text(json.dumps(SQUARE))
    outcome = runner.invoke(app, ["cueing", "plan", str(path), "--json"])
    assert outcome.exit_code == 0, outcome.output
    result = json.loads(outcome.stdout)
    plan = plan_prescription(SQUARE, default_twin())
    timeline = prescription_timeline(plan)
    dt = plan.sample_period_s
    segment = plan.segments[0]
    raw = np.zeros((len(timeline["poses"]), 3))
    written, _ = cue_from_spec(segment.cue_spec, dt, segment.seed).generate(segment.duration_s)
    raw[: len(written)] = written
    delivered = head_specific_force(
        timeline["poses"].T, timeline["velocity"].T, timeline["acceleration"].T, DEFAULT_HEAD_HEIGHT_M
    ).T
    model = VestibularModel(sample_period_s=dt)
    error = model.perceive_specific_force(delivered) - model.perceive_specific_force(raw)
    expected = float(np.sqrt(np.mean(np.sum(error**2, axis=1))))
    assert result["perceived_specific_force_error_rms_raw_m_s2"] == pytest.approx(expected, rel=1e-9)
    # The soft start alone makes the square wave's first half-period softer than written.
    assert result["perceived_specific_force_error_rms_raw_m_s2"] > result["perceived_specific_force_error_rms_m_s2"]
