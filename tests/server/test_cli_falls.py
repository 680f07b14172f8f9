"""`simulate-cohort` → `evaluate-falls` round trip on a tiny cohort."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from server.cli.main import app

runner = CliRunner()


@pytest.fixture(scope="module")
def cohort(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("cohort")
    # Seed 15 gives two falls among three impaired patients in 30 s (deterministic).
    args = ["simulate-cohort", "--patients", "3", "--seed", "15", "--duration-s", "30", "--impaired-share", "1"]
    result = runner.invoke(app, [*args, str(out), "--json"])
    assert result.exit_code == 0, result.output
    return out, json.loads(result.stdout)


def test_simulate_cohort_writes_self_describing_logs(cohort: tuple[Path, dict]) -> None:
    out, summary = cohort
    assert summary["sessions"] == 3 and summary["impaired"] == 3
    assert summary["falls"] == 2
    logs = sorted(out.glob("*.npz"))
    assert [p.stem for p in logs] == ["session_0001", "session_0002", "session_0003"]
    sidecar = json.loads(logs[0].with_suffix(".json").read_text())
    assert sidecar["format"] == "ssp-rehab-session-log/1"
    assert {"body_mass_kg", "height_m", "preset"} <= set(sidecar["patient"])
    with np.load(logs[0]) as columns:
        count = len(columns["time_s"])
        assert columns["plate_force_z_n"].shape == (count, 2)
        assert columns["plate_cop_m"].shape == (count, 2, 2)
        assert columns["harness_load_n"].shape == (count,)
        assert columns["support_acceleration_m_s2"].shape == (count, 3)
    onsets = [f["onset_s"] for p in logs for f in json.loads(p.with_suffix(".json").read_text())["falls"]]
    assert len(onsets) == 2


def test_evaluate_falls_scores_the_cohort_and_plots(cohort: tuple[Path, dict], tmp_path: Path) -> None:
    out, _ = cohort
    result = runner.invoke(app, ["evaluate-falls", str(out), "--json", "--plot", str(tmp_path)])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["sessions"] == 3 and data["falls"] == 2
    by_name = {d["detector"]: d for d in data["detectors"]}
    assert set(by_name) == {"harness_load", "cop_outside_base", "foot_unloaded", "fused", "any"}
    assert by_name["any"]["detected"] >= by_name["harness_load"]["detected"]
    assert by_name["harness_load"]["sensitivity"] == by_name["harness_load"]["detected"] / 2
    assert {Path(p).name for p in data["plots"]} == {
        "latency_histogram.png",
        "sensitivity.png",
        "example_trace.png",
        "roc.png",
    }
    assert all(Path(p).stat().st_size > 1000 for p in data["plots"])
    # ROC curves with the operating point: it is the configured threshold's own score.
    fused = data["roc"]["fused"]
    assert fused["parameter"] == "fused.threshold" and len(fused["points"]) > 10
    assert fused["operating_point"]["sensitivity"] == by_name["fused"]["sensitivity"]
    assert fused["operating_point"]["false_alarms_per_hour"] == by_name["fused"]["false_alarms_per_hour"]
    harness = sorted(data["roc"]["harness_load"]["points"], key=lambda p: p["threshold"])
    assert all(a["sensitivity"] >= b["sensitivity"] for a, b in itertools.pairwise(harness))


def test_tune_falls_writes_settings_that_evaluate_falls_takes(cohort: tuple[Path, dict], tmp_path: Path) -> None:
    out, _ = cohort
    settings = tmp_path / "fused.json"
    result = runner.invoke(app, ["tune-falls", str(out), "--out", str(settings), "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["combinations"] == 81 and data["training"]["false_alarms_per_hour"] <= 1.0
    assert set(json.loads(settings.read_text())) == {"fused"}
    evaluated = runner.invoke(app, ["evaluate-falls", str(out), "--detectors", str(settings), "--json"])
    assert evaluated.exit_code == 0, evaluated.output
    scores = {d["detector"]: d for d in json.loads(evaluated.stdout)["detectors"]}
    assert scores["fused"]["sensitivity"] == data["training"]["sensitivity"]
    refused = runner.invoke(app, ["tune-falls", str(out), "--max-false-alarms-per-hour", "-1", "--json"])
    assert refused.exit_code == 2 and "max_false_alarms_per_hour" in json.loads(refused.stdout)["error"]


def test_a_truth_file_replaces_the_sidecar_labels(cohort: tuple[Path, dict], tmp_path: Path) -> None:
    out, _ = cohort
    truth = tmp_path / "truth.json"
    truth.write_text(json.dumps({"session_0001": [5.0, 25.0]}))
    result = runner.invoke(app, ["evaluate-falls", str(out), "--truth", str(truth), "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["falls"] == 2
    human = runner.invoke(app, ["evaluate-falls", str(out / "session_0001.npz")])
    assert human.exit_code == 0 and "harness_load" in human.stdout
    assert "operating point fused: fused.threshold = 1" in human.stdout


def test_bad_arguments_are_refused_naming_them(tmp_path: Path) -> None:
    result = runner.invoke(app, ["simulate-cohort", "--patients", "0", str(tmp_path), "--json"])
    assert result.exit_code == 2 and "--patients" in json.loads(result.stdout)["error"]
    result = runner.invoke(app, ["evaluate-falls", str(tmp_path / "missing"), "--json"])
    assert result.exit_code == 2 and "LOGS" in json.loads(result.stdout)["error"]
