"""The geometry kernels were merged (issue 13 §4) without changing a result: IK, FK, dynamics and the tick
reproduce, to 1e-12, the outputs the code gave before (tests/core/data/kernel_reference.npz, written by
`tests/core/kernel_reference.py` at commit fe74a48, the last one with four copies of the leg formula)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.kinematics import LegViolation
from tests.core import kernel_reference

REFERENCE = Path(__file__).parent / "data" / "kernel_reference.npz"
# The reference layout collides (issue 13); the old code had no COLLISION flag to compare.
WITHOUT_COLLISION = np.int64(0xFF & ~int(LegViolation.COLLISION))


@pytest.fixture(scope="module")
def outputs() -> dict[str, np.ndarray]:
    return kernel_reference.compute()


@pytest.mark.parametrize(
    "name",
    [
        "ik_sliders",
        "ik_base_cone",
        "ik_platform_cone",
        "fk_poses",
        "fk_residuals",
        "twin_right_sliders",
        "twin_left_sliders",
        "single_forces",
        "twin_forces",
        "tick_sliders",
        "tick_measured_stance",
    ],
)
def test_results_are_unchanged_to_1e_12(outputs: dict[str, np.ndarray], name: str) -> None:
    expected = np.load(REFERENCE)[name]
    assert outputs[name].shape == expected.shape
    np.testing.assert_allclose(outputs[name], expected, rtol=0.0, atol=1e-12, equal_nan=True)


def test_the_first_tick_violation_is_unchanged(outputs: dict[str, np.ndarray]) -> None:
    """Code, axis and limit exactly; the value (a slider acceleration, ∝ 1/dt² = 1e6 of the slider
    positions' rounding) to 1e-12 relative."""
    expected = np.load(REFERENCE)["tick_violations"]
    found = outputs["tick_violations"]
    np.testing.assert_array_equal(found[:, [0, 1, 3]], expected[:, [0, 1, 3]])
    np.testing.assert_allclose(found[:, 2], expected[:, 2], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", ["ik_violations", "fk_iterations", "twin_right_violations", "twin_left_violations"])
def test_flags_and_counts_are_identical(outputs: dict[str, np.ndarray], name: str) -> None:
    expected = np.load(REFERENCE)[name]
    found = outputs[name] & WITHOUT_COLLISION if "violations" in name else outputs[name]
    np.testing.assert_array_equal(found, expected)
