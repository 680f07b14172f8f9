"""Issue 13's defects, reproduced on the pre-issue default layout (interleaved rails, bases at y = ±0.5 m)."""

from __future__ import annotations

import numpy as np
import pytest

from core.kinematics import UnreachablePoseError, twin_inverse_kinematics
from core.robot import RobotPlacement, TwinRobot
from core.shaping import ShapingParameters
from core.washout import paper_tilt_parameters
from server.cli.washout_commands import paper_tilt_step


def interleaved_twin() -> TwinRobot:
    """The layout every version before issue 13 shipped as its default."""
    return TwinRobot(
        right=RobotPlacement(base_origin_m=(0.0, -0.5, 0.0), foot_plate_offset_m=(0.0, 0.25, 0.0)),
        left=RobotPlacement(base_origin_m=(0.0, 0.5, 0.0), mirrored=True, foot_plate_offset_m=(0.0, -0.25, 0.0)),
    )


def test_the_interleaved_layout_reports_its_rods_3_and_4_colliding_at_neutral() -> None:
    with pytest.raises(UnreachablePoseError) as refused:
        twin_inverse_kinematics(interleaved_twin(), np.zeros((1, 6)))
    message = str(refused.value)
    assert "collision" in message
    assert "right rod 3" in message and "left rod 3" in message


def test_the_section_5_lateral_step_reports_its_singularity_crossings_and_worst_conditioning() -> None:
    data = paper_tilt_step(interleaved_twin(), paper_tilt_parameters(), ShapingParameters())
    left = data["singularity"]["left"]
    # The left robot leaves its assembly mode twice (det J changes sign and back), as the issue found.
    excursions = [(c["from_s"], c["to_s"]) for c in left["other_assembly_mode"]]
    assert len(excursions) == 2
    (first_from, first_to), (second_from, second_to) = excursions
    assert 3.1 < first_from < 3.2 and 3.6 < first_to < 3.75
    assert 10.4 < second_from < 10.5 and 11.0 < second_to < 11.1
    assert len(left["det_sign_changes"]) == 4
    assert left["worst_condition_number"] > 1e5
    assert 3.1 < left["worst_condition_number_time_s"] < 3.75 or 10.4 < left["worst_condition_number_time_s"] < 11.1
    assert data["singularity"]["right"]["det_sign_changes"] == []
    # Every breach, not the first three: the margin is broken on thousands of samples.
    assert left["samples_beyond_margin"] > 1000
    assert left["beyond_margin"][0]["from_s"] == pytest.approx(2.262, abs=0.002)
