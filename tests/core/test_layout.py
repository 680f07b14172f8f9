"""The layout study's building blocks (core/layout.py, core.robot.symmetric_placements)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.kinematics import foot_plate_neutral_world
from core.layout import DEFAULT_LAYOUT, LayoutCandidate, LayoutSearchError, evaluate_layout, layout_search
from core.robot import default_twin, named_twin


@pytest.mark.parametrize("yaw_deg", [0.0, 7.0])
def test_symmetric_placements_put_the_feet_side_by_side_at_the_asked_width(yaw_deg: float) -> None:
    twin = LayoutCandidate(0.9, 0.1, math.radians(yaw_deg), 0.3).twin()
    right, left = (foot_plate_neutral_world(twin, side) for side in twin.sides)
    np.testing.assert_allclose(right, [0.0, -0.15, 0.6], atol=1e-12)
    np.testing.assert_allclose(left, [0.0, 0.15, 0.6], atol=1e-12)


def test_the_default_layout_is_the_studys_reference_and_the_legacy_layout_is_refused() -> None:
    assert DEFAULT_LAYOUT.twin() == default_twin()
    metrics = evaluate_layout(default_twin())
    assert metrics is not None and metrics.neutral_clearance_m > 0.05
    assert metrics.symmetric_reach("roll") == pytest.approx(math.radians(12.0), abs=math.radians(0.1))
    assert evaluate_layout(named_twin("legacy-interleaved")) is None  # collides at neutral


def test_the_search_refuses_bad_settings_naming_them() -> None:
    with pytest.raises(LayoutSearchError) as refused:
        layout_search(population=2, generations=2, stagger_max_m=2.0)
    assert refused.value.field == "stagger_max_m"
