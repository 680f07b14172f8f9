"""`ssp-rehab layout search` (issue 13 §3): the Pareto set as JSON, PNG plots and a TOML `--robot` accepts."""

from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from core.layout import CLINICAL_AXES, FEET_APART_RANGE_M
from server.cli.main import app

runner = CliRunner()


def test_layout_search_json_plots_and_a_toml_the_robot_option_accepts(tmp_path: Path) -> None:
    toml = tmp_path / "recommended.toml"
    outcome = runner.invoke(
        app,
        [
            "layout", "search", "--population", "4", "--generations", "2", "--json", "--no-progress",
            "--plot", str(tmp_path), "--toml", str(toml),
        ],
    )  # fmt: skip
    assert outcome.exit_code == 0, outcome.output
    data = json.loads(outcome.stdout)
    assert data["pareto"] and 0 <= data["recommended"] < len(data["pareto"])
    for entry in data["pareto"]:
        metrics = entry["metrics"]
        assert set(metrics["symmetric_reach"]) == set(CLINICAL_AXES)
        assert FEET_APART_RANGE_M[0] * 1e3 - 1e-6 <= metrics["feet_apart_mm"] <= FEET_APART_RANGE_M[1] * 1e3 + 1e-6
        assert metrics["neutral_clearance_mm"] >= 50.0 and metrics["peak_force_n"] > 0
        assert metrics["ranges"]["roll"]["unit"] == "deg" and metrics["ranges"]["y"]["unit"] == "mm"
    assert data["reference"]["layout"]["mirrored"] is True  # today's default is seeded and reported
    assert {Path(p).name for p in data["plots"]} == {"layout_axis_ranges.png", "layout_roll_pitch.png"}
    assert all(Path(p).stat().st_size > 5000 for p in data["plots"])
    twin_ik = runner.invoke(
        app, ["ik", "--twin", "--pose", "0", "0", "0", "0", "0", "0", "--json", "--robot", str(toml)]
    )
    assert twin_ik.exit_code == 0 and json.loads(twin_ik.stdout)["reachable"] is True


def test_layout_search_refuses_a_too_small_population() -> None:
    outcome = runner.invoke(app, ["layout", "search", "--population", "1", "--json", "--no-progress"])
    assert outcome.exit_code == 2
    assert "population" in json.loads(outcome.stdout)["error"]


def test_the_legacy_layout_stays_loadable_by_name_and_shows_its_collision() -> None:
    outcome = runner.invoke(
        app, ["ik", "--twin", "--pose", "0", "0", "0", "0", "0", "0", "--json", "--robot", "legacy-interleaved"]
    )
    data = json.loads(outcome.stdout)
    assert outcome.exit_code == 1 and data["reachable"] is False
    assert any("right rod 3 – left rod 3" in v["reason"] for v in data["violations"])
