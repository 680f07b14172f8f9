"""The robot description (core/robot.py): paper geometry, validation naming the field, TOML, twin layout."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from core.robot import (
    DescriptionError,
    MotionLimits,
    RobotPlacement,
    Slider,
    SSPRobot,
    TwinRobot,
    load_twin,
    paper_robot,
    save_twin,
    twin_to_dict,
)


def with_slider(robot: SSPRobot, index: int, **changes: object) -> tuple[Slider, ...]:
    sliders = list(robot.sliders)
    sliders[index] = replace(sliders[index], **changes)  # type: ignore[arg-type]
    return tuple(sliders)


def test_paper_geometry_matches_reference_table(robot: SSPRobot) -> None:
    expected_mm = [
        (75.000, -447.446),
        (425.000, 158.771),
        (350.000, 288.675),
        (-350.000, 288.675),
        (-425.000, 158.771),
        (-75.000, -447.446),
    ]
    np.testing.assert_allclose(robot.platform_joints_m[:, :2] * 1e3, expected_mm, atol=1e-3)
    np.testing.assert_array_equal(robot.rail_y_m, [-0.8, 0.0, 0.8, 0.8, 0.0, -0.8])
    np.testing.assert_array_equal(robot.sides, [1, 1, 1, -1, -1, -1])
    assert robot.rod_length_m == 1.0
    assert robot.neutral_pose == (0.0, 0.0, 0.6, 0.0, 0.0, 0.0)


@pytest.mark.parametrize("rod_length_m", [0.0, -1.0])
def test_non_positive_rod_length_is_refused(robot: SSPRobot, rod_length_m: float) -> None:
    with pytest.raises(DescriptionError) as error:
        replace(robot, rod_length_m=rod_length_m)
    assert error.value.field == "rod_length_m"
    assert "> 0" in error.value.limit


@pytest.mark.parametrize("count", [0, 5, 7])
def test_other_than_six_joints_is_refused(robot: SSPRobot, count: int) -> None:
    sliders = (robot.sliders * 2)[:count]
    with pytest.raises(DescriptionError) as error:
        replace(robot, sliders=sliders)
    assert error.value.field == "sliders"
    assert error.value.value == count


def test_rod_that_cannot_reach_its_rail_at_neutral_is_refused(robot: SSPRobot) -> None:
    # The platform joints sit 0.6 m above the rails: a 0.55 m rod cannot reach.
    with pytest.raises(DescriptionError) as error:
        replace(robot, rod_length_m=0.55)
    assert error.value.field == "sliders[1].platform_joint_m"
    assert "cannot reach its rail" in error.value.limit


def test_platform_joint_moved_out_of_reach_names_that_slider(robot: SSPRobot) -> None:
    with pytest.raises(DescriptionError) as error:
        replace(robot, sliders=with_slider(robot, 3, platform_joint_m=(-0.35, -0.6, 0.0)))
    assert error.value.field == "sliders[4].platform_joint_m"
    assert "cannot reach" in str(error.value)


NAN = float("nan")
NAN_CASES = [
    ("rod_length_m", lambda r: replace(r, rod_length_m=NAN)),
    ("rail_z_m", lambda r: replace(r, rail_z_m=NAN)),
    ("neutral_pose", lambda r: replace(r, neutral_pose=(0.0, 0.0, NAN, 0.0, 0.0, 0.0))),
    ("limits.tilt_max_rad", lambda r: replace(r, limits=replace(r.limits, tilt_max_rad=NAN))),
    ("limits.condition_number_max", lambda r: replace(r, limits=replace(r.limits, condition_number_max=NAN))),
    ("mass.platform_mass_kg", lambda r: replace(r, mass=replace(r.mass, platform_mass_kg=NAN))),
    ("mass.platform_inertia_kg_m2", lambda r: replace(r, mass=replace(r.mass, platform_inertia_kg_m2=(1, NAN, 1)))),
    ("sliders[2].rail_y_m", lambda r: replace(r, sliders=with_slider(r, 1, rail_y_m=NAN))),
    ("sliders[3].platform_joint_m", lambda r: replace(r, sliders=with_slider(r, 2, platform_joint_m=(0, NAN, 0)))),
    ("sliders[6].stroke_m", lambda r: replace(r, sliders=with_slider(r, 5, stroke_m=(NAN, -0.15)))),
]


@pytest.mark.parametrize(("field", "build"), NAN_CASES, ids=[case[0] for case in NAN_CASES])
def test_nan_anywhere_is_refused_naming_the_field(robot: SSPRobot, field: str, build) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(DescriptionError) as error:
        build(robot)
    assert error.value.field == field
    assert "finite" in error.value.limit


@pytest.mark.parametrize("field", ["base_origin_m", "base_yaw_rad", "foot_plate_offset_m"])
def test_nan_in_twin_placement_is_refused(field: str) -> None:
    value = NAN if field == "base_yaw_rad" else (0.0, NAN, 0.0)
    placement = replace(RobotPlacement(base_origin_m=(0.0, -0.5, 0.0)), **{field: value})
    with pytest.raises(DescriptionError) as error:
        TwinRobot(right=placement)
    assert error.value.field == f"right.{field}"


@pytest.mark.parametrize("side", [0, 2, -2])
def test_bad_side_is_refused(robot: SSPRobot, side: int) -> None:
    with pytest.raises(DescriptionError) as error:
        replace(robot, sliders=with_slider(robot, 1, side=side))
    assert error.value.field == "sliders[2].side"
    assert error.value.value == side


def test_stroke_with_min_not_below_max_is_refused(robot: SSPRobot) -> None:
    with pytest.raises(DescriptionError) as error:
        replace(robot, sliders=with_slider(robot, 0, stroke_m=(1.85, 0.15)))
    assert error.value.field == "sliders[1].stroke_m"
    assert "min must be < max" in error.value.limit


def test_stroke_that_excludes_the_neutral_position_is_refused(robot: SSPRobot) -> None:
    # Slider 1 sits at 793.13 mm at neutral.
    with pytest.raises(DescriptionError) as error:
        replace(robot, sliders=with_slider(robot, 0, stroke_m=(0.8, 1.85)))
    assert error.value.field == "sliders[1].stroke_m"
    assert "outside the stroke" in error.value.limit


def test_non_positive_limit_is_refused(robot: SSPRobot) -> None:
    with pytest.raises(DescriptionError) as error:
        replace(robot, limits=MotionLimits(slider_velocity_max_m_s=0.0))
    assert error.value.field == "limits.slider_velocity_max_m_s"


def test_non_numeric_value_is_refused_naming_the_field(robot: SSPRobot) -> None:
    with pytest.raises(DescriptionError) as error:
        replace(robot, rail_z_m="high")  # type: ignore[arg-type]
    assert error.value.field == "rail_z_m"


def test_error_message_names_field_value_and_limit(robot: SSPRobot) -> None:
    with pytest.raises(DescriptionError, match=r"rod_length_m = -1\.0: must be > 0"):
        replace(robot, rod_length_m=-1.0)


# --- TOML ------------------------------------------------------------------------------------------


def test_toml_round_trip_preserves_every_field(tmp_path: Path) -> None:
    base = paper_robot()
    twin = TwinRobot(
        robot=replace(base, limits=replace(base.limits, tilt_max_rad=0.3), rail_z_m=0.01),
        right=RobotPlacement(base_origin_m=(0.1, -0.6, 0.0), base_yaw_rad=0.05, foot_plate_offset_m=(0.02, 0.2, 0.0)),
        left=RobotPlacement(base_origin_m=(0.1, 0.6, 0.0), mirrored=True, foot_plate_offset_m=(0.02, -0.2, 0.0)),
    )
    path = tmp_path / "robot.toml"
    save_twin(twin, path)
    assert load_twin(path) == twin


def write_toml(path: Path, data: dict) -> Path:  # type: ignore[type-arg]
    path.write_text(tomli_w.dumps(data))
    return path


@pytest.mark.parametrize(
    ("where", "expected_field"),
    [
        (("robot",), "robot.rod_lenght_m"),
        (("robot", "limits"), "robot.limits.rod_lenght_m"),
        (("robot", "mass"), "robot.mass.rod_lenght_m"),
        (("twin", "left"), "twin.left.rod_lenght_m"),
        ((), "rod_lenght_m"),
        (("twin",), "twin.rod_lenght_m"),
    ],
)
def test_unknown_field_is_refused(tmp_path: Path, twin: TwinRobot, where: tuple[str, ...], expected_field: str) -> None:
    data = twin_to_dict(twin)
    section = data
    for key in where:
        section = section[key]
    section["rod_lenght_m"] = 1.0  # a typo must not be silently ignored
    with pytest.raises(DescriptionError) as error:
        load_twin(write_toml(tmp_path / "robot.toml", data))
    assert error.value.field == expected_field
    assert "unknown field" in error.value.limit


def test_unknown_field_in_a_slider_is_refused(tmp_path: Path, twin: TwinRobot) -> None:
    data = twin_to_dict(twin)
    data["robot"]["sliders"][2]["colour"] = "red"
    with pytest.raises(DescriptionError) as error:
        load_twin(write_toml(tmp_path / "robot.toml", data))
    assert error.value.field == "robot.sliders[3].colour"


def test_invalid_value_in_toml_is_refused_naming_the_field(tmp_path: Path, twin: TwinRobot) -> None:
    data = twin_to_dict(twin)
    data["robot"]["sliders"][4]["side"] = 0
    with pytest.raises(DescriptionError) as error:
        load_twin(write_toml(tmp_path / "robot.toml", data))
    assert error.value.field == "sliders[5].side"


def test_malformed_toml_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "robot.toml"
    path.write_text("[robot\nrod_length_m = 1")
    with pytest.raises(DescriptionError, match="not valid TOML"):
        load_twin(path)


# --- Twin layout -------------------------------------------------------------------------------------


def test_mirrored_robot_is_the_mirror_image(robot: SSPRobot) -> None:
    mirrored = robot.mirrored()
    np.testing.assert_array_equal(mirrored.rail_y_m, -robot.rail_y_m)
    np.testing.assert_array_equal(mirrored.platform_joints_m[:, 1], -robot.platform_joints_m[:, 1])
    np.testing.assert_array_equal(mirrored.platform_joints_m[:, [0, 2]], robot.platform_joints_m[:, [0, 2]])
    assert mirrored.mirrored() == robot


def test_default_twin_places_the_feet_side_by_side_0_4_m_apart(twin: TwinRobot) -> None:
    assert twin.robot_for("right") == twin.robot
    assert twin.robot_for("left") == twin.robot.mirrored()
    right = np.add(twin.right.base_origin_m, twin.right.foot_plate_offset_m)
    left = np.add(twin.left.base_origin_m, twin.left.foot_plate_offset_m)
    assert math.isclose(float(np.linalg.norm(left - right)), 0.4)  # issue 13 layout study (was 0.5)
    assert math.isclose(float(left[0] - right[0]), 0.0, abs_tol=1e-12)  # side by side, not one ahead


def test_unknown_twin_side_is_refused(twin: TwinRobot) -> None:
    with pytest.raises(DescriptionError) as error:
        twin.placement("middle")
    assert error.value.field == "side"
