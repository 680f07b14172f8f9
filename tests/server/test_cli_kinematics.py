"""The `ik`, `fk` and `workspace` CLI contracts (scripts rely on their JSON keys)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from core.robot import default_twin, save_twin, twin_to_dict
from server.cli.main import app

NEUTRAL_SLIDERS_MM = [793.13, 1209.09, 965.26, -965.26, -1209.09, -793.13]
ROLL_20_SLIDERS_MM = [885.05, 1166.37, 831.88, -831.88, -1166.37, -885.05]

runner = CliRunner()


def run_json(*args: str) -> tuple[int, dict]:  # type: ignore[type-arg]
    result = runner.invoke(app, [*args, "--json"])
    return result.exit_code, json.loads(result.stdout)


def test_ik_json_gives_paper_roll_20_sliders() -> None:
    code, data = run_json("ik", "--pose", "0", "0", "600", "20", "0", "0")
    assert code == 0
    assert data["sliders_mm"] == pytest.approx(ROLL_20_SLIDERS_MM, abs=0.01)


def test_ik_unreachable_pose_is_refused_with_the_reason() -> None:
    code, data = run_json("ik", "--pose", "700", "0", "600", "0", "0", "0")
    assert code != 0
    assert "slider outside its stroke" in data["error"]
    assert "sliders_mm" not in data


def test_fk_json_contract_and_round_trip() -> None:
    code, data = run_json("fk", "--sliders", *map(str, ROLL_20_SLIDERS_MM))
    assert code == 0
    assert set(data) >= {"pose", "iterations", "residual_mm"}
    pose = data["pose"]
    # The published sliders are rounded to 0.01 mm, so the pose is recovered to about that.
    assert pose["roll_deg"] == pytest.approx(20.0, abs=0.01)
    assert pose["z_mm"] == pytest.approx(600.0, abs=0.02)
    for key in ("x_mm", "y_mm", "pitch_deg", "yaw_deg"):
        assert pose[key] == pytest.approx(0.0, abs=0.02)
    assert data["iterations"] >= 1
    assert data["residual_mm"] < 1e-9


def test_fk_impossible_sliders_fail_clearly() -> None:
    sliders = list(NEUTRAL_SLIDERS_MM)
    sliders[0] += 1500
    sliders[5] -= 1500
    code, data = run_json("fk", "--sliders", *map(str, sliders))
    assert code != 0
    assert "did not converge" in data["error"]


def test_robot_file_option_is_used_and_validated(tmp_path: Path) -> None:
    path = tmp_path / "robot.toml"
    save_twin(default_twin(), path)
    code, data = run_json("ik", "--pose", "0", "0", "600", "0", "0", "0", "--robot", str(path))
    assert code == 0
    assert data["sliders_mm"] == pytest.approx(NEUTRAL_SLIDERS_MM, abs=0.01)
    broken = twin_to_dict(default_twin())
    broken["robot"]["rod_length_m"] = -1.0
    import tomli_w

    path.write_text(tomli_w.dumps(broken))
    code, data = run_json("ik", "--pose", "0", "0", "600", "0", "0", "0", "--robot", str(path))
    assert code != 0
    assert "rod_length_m" in data["error"]


def test_workspace_json_and_plots(tmp_path: Path) -> None:
    code, data = run_json("workspace", "--samples", "20000", "--plot", str(tmp_path))
    assert code == 0
    axes = data["axes"]
    assert list(axes) == ["x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg"]
    # Along the rails the stroke limits x to ±641 mm; the singularity at roll ≈ −11° bounds roll.
    assert axes["x_mm"]["min"] == pytest.approx(-640.9, abs=1.0)
    assert axes["x_mm"]["max"] == pytest.approx(640.9, abs=1.0)
    assert -11.2 < axes["roll_deg"]["min"] < 0 < 20 < axes["roll_deg"]["max"]
    assert axes["x_mm"]["limited_by"]["max"] == "slider outside its stroke"
    assert 0.0 < data["cloud"]["reachable_fraction"] < 1.0
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    assert len(pngs) >= 3
    assert all((tmp_path / name).stat().st_size > 1000 for name in pngs)


def test_ik_twin_json_contract() -> None:
    """`ik --twin --pose X Y Z ROLL PITCH YAW --json`: a stance pose relative to neutral (issue 13)."""
    code, data = run_json("ik", "--twin", "--pose", "0", "0", "0", "0", "0", "0")
    assert code == 0, data
    assert data["reachable"] is True and data["violations"] == []
    for side in ("right", "left"):
        robot = data["robots"][side]
        assert len(robot["sliders_mm"]) == 6
        assert [len(row) for row in robot["slider_joints_mm"]] == [3] * 6
        assert [len(row) for row in robot["platform_joints_mm"]] == [3] * 6
        # Each rod end at the platform is one rod length from its end at the slider.
        rods = [
            sum((p - s) ** 2 for p, s in zip(platform, slider, strict=True)) ** 0.5
            for platform, slider in zip(robot["platform_joints_mm"], robot["slider_joints_mm"], strict=True)
        ]
        assert rods == pytest.approx([1000.0] * 6, abs=1e-6)
    right_foot, left_foot = data["foot_plates_mm"]
    width = sum((a - b) ** 2 for a, b in zip(right_foot, left_foot, strict=True)) ** 0.5
    assert 150.0 <= width <= 450.0


def test_ik_twin_reports_an_unreachable_stance_pose_with_its_violations() -> None:
    code, data = run_json("ik", "--twin", "--pose", "0", "0", "0", "30", "0", "0")
    assert code != 0
    assert data["reachable"] is False and data["violations"]
    assert all("robot" in violation for violation in data["violations"])
