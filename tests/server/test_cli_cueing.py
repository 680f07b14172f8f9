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
